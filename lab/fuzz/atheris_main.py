"""Coverage-guided fuzzing of one target under atheris (libFuzzer), as its own process.

    python -m lab.fuzz.atheris_main TARGET [libFuzzer flags] CORPUS_DIR

The code under test (``shared``, ``relay_server``) is imported inside
``atheris.instrument_imports`` so libFuzzer sees its branch coverage; the harness itself is
not instrumented. Mutations alternate between libFuzzer's own and the msgpack-structure
mutator of :mod:`lab.fuzz.mutate`. libFuzzer ends the process: with ``-runs=N`` after N
inputs, on the first crash (an exception escaping the target, traceback on stderr, the input
saved under ``-artifact_prefix``) or on a hang (``-timeout``). ``lab.bench.fuzz`` starts it
and reads its final statistics (``-print_final_stats=1``).
"""

from __future__ import annotations

import logging
import random
import sys


def main() -> None:
    """Fuzz ``sys.argv[1]`` with the remaining arguments passed to libFuzzer."""
    import atheris

    if len(sys.argv) < 2:
        sys.exit("usage: python -m lab.fuzz.atheris_main TARGET [libFuzzer flags] [CORPUS]")
    target = sys.argv.pop(1)
    with atheris.instrument_imports(include=["shared", "relay_server"]):
        import relay_server.server  # noqa: F401  (instrumented before the harness uses it)
        import shared.protocol  # noqa: F401
    from lab.fuzz.mutate import mutate_input
    from lab.fuzz.registry import TARGETS

    fn = TARGETS[target]
    logging.disable(logging.CRITICAL)  # the code under test logs every refusal

    def custom_mutator(data: bytes, max_size: int, seed: int) -> bytes:
        rng = random.Random(seed)
        if rng.random() < 0.5:
            return bytes(atheris.Mutate(data, max_size))
        return mutate_input(rng, target, data)[:max_size]

    atheris.Setup(sys.argv, fn, custom_mutator=custom_mutator)
    atheris.Fuzz()


if __name__ == "__main__":
    main()
