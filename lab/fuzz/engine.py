"""A coverage-less mutation fuzzer: seeds, mutations, a per-input time limit, crash buckets.

It drives the same targets as atheris (:mod:`lab.fuzz.atheris_main`) without coverage
feedback: each input is a seed or an earlier mutant, mutated one to four times
(:mod:`lab.fuzz.mutate`); one mutant in 64 joins the corpus (bounded) so mutations stack.
An input that runs longer than ``hang_s`` is interrupted (SIGALRM) and counted as a hang.
Reproducible from ``seed``.
"""

from __future__ import annotations

import logging
import random
import resource
import signal
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field

from lab.fuzz.mutate import mutate_input
from lab.fuzz.seeds import seed_messages, seed_scripts

__all__ = ["Crash", "EngineResult", "Hang", "run_engine", "seeds_for"]

_CORPUS_MAX = 2000


class Hang(Exception):
    """An input ran longer than the per-input time limit."""


@dataclass
class Crash:
    """The first input of one crash bucket (exception type and the innermost frame)."""

    bucket: str
    error: str
    traceback: str
    data: bytes
    count: int = 1


@dataclass
class EngineResult:
    """What one run did."""

    target: str
    inputs: int
    seconds: float
    crashes: dict[str, Crash] = field(default_factory=dict)
    hangs: int = 0
    slowest_s: float = 0.0
    peak_rss_mb: float = 0.0

    @property
    def crash_count(self) -> int:
        return sum(c.count for c in self.crashes.values())


def seeds_for(target: str) -> list[bytes]:
    """The seed corpus of a target."""
    if target == "decoder":
        return seed_messages()
    if target == "framing":
        return [bytes([60, 23]) + b"".join(len(m).to_bytes(4, "big") + m
                                          for m in seed_messages()[i:i + 3])
                for i in range(0, 16, 3)]
    return seed_scripts(target)


def _bucket(err: BaseException) -> str:
    tb = traceback.extract_tb(err.__traceback__)
    where = f"{tb[-1].filename.rsplit('/', 1)[-1]}:{tb[-1].lineno}" if tb else "?"
    return f"{type(err).__name__} at {where}"


def run_engine(target: str, fn: Callable[[bytes], None], inputs: int, *, seed: int = 0,
               hang_s: float = 5.0, max_seconds: float | None = None) -> EngineResult:
    """Fuzz ``fn`` with ``inputs`` inputs (the seeds first), or until ``max_seconds``."""
    rng = random.Random(seed)
    corpus = seeds_for(target)
    result = EngineResult(target, 0, 0.0)

    def alarm(signum: int, frame: object) -> None:
        raise Hang(f"input ran longer than {hang_s} s")

    old = signal.signal(signal.SIGALRM, alarm)
    logging.disable(logging.CRITICAL)  # the code under test logs every refusal
    start = time.perf_counter()
    try:
        for i in range(inputs):
            if i < len(corpus):
                data = corpus[i]
            else:
                data = rng.choice(corpus)
                for _ in range(1 + rng.randrange(4)):
                    data = mutate_input(rng, target, data, corpus)
                if rng.randrange(64) == 0:
                    if len(corpus) < _CORPUS_MAX:
                        corpus.append(data)
                    else:
                        corpus[rng.randrange(len(seeds_for(target)), _CORPUS_MAX)] = data
            t0 = time.perf_counter()
            signal.setitimer(signal.ITIMER_REAL, hang_s)
            try:
                fn(data)
            except Hang:
                result.hangs += 1
            except Exception as err:  # every other exception is a crash to report
                bucket = _bucket(err)
                if bucket in result.crashes:
                    result.crashes[bucket].count += 1
                else:
                    result.crashes[bucket] = Crash(bucket, f"{type(err).__name__}: {err}"[:2000],
                                                   traceback.format_exc()[-4000:], data)
            finally:
                signal.setitimer(signal.ITIMER_REAL, 0)
            result.slowest_s = max(result.slowest_s, time.perf_counter() - t0)
            result.inputs += 1
            if max_seconds is not None and time.perf_counter() - start > max_seconds:
                break
    finally:
        signal.signal(signal.SIGALRM, old)
        logging.disable(logging.NOTSET)
    result.seconds = time.perf_counter() - start
    result.peak_rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return result
