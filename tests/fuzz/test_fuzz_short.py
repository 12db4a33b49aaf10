"""The short fuzz run of the test suite: every target, both engines, a few thousand inputs.

The long run is ``teletouch bench fuzz`` (>= 100,000 inputs per target,
benchmarks/results/fuzz.md). Here: the seeds pass every oracle, a short run of the builtin
engine finds no crash, atheris (when installed) runs each target briefly, and the oracles do
fail on a relay or decoder that breaks the doc (so a green run means something).
"""

from __future__ import annotations

import importlib.util

import msgpack
import pytest

from lab.bench.fuzz import run_atheris
from lab.fuzz.engine import run_engine, seeds_for
from lab.fuzz.registry import TARGETS
from lab.fuzz.script import Kind, Op, dump
from lab.fuzz.seeds import hello_for
from lab.fuzz.targets import Finding
from shared.protocol import Hello, encode

#: inputs of the short builtin run per target (the session targets are slower per input)
SHORT = {"decoder": 2000, "framing": 2000, "station": 300, "peer": 300, "relay": 150}


@pytest.mark.parametrize("target", sorted(TARGETS))
def test_every_seed_passes_the_oracles(target: str) -> None:
    for data in seeds_for(target):
        TARGETS[target](data)


@pytest.mark.parametrize("target", sorted(TARGETS))
def test_short_builtin_run_finds_no_crash(target: str) -> None:
    result = run_engine(target, TARGETS[target], SHORT[target], seed=11, max_seconds=20.0)
    report = [f"{c.bucket} x{c.count}\n{c.traceback}" for c in result.crashes.values()]
    assert not result.crashes, "\n".join(report)
    assert result.hangs == 0
    assert result.inputs >= min(SHORT[target], 100)


@pytest.mark.slow  # a libFuzzer process: start-up and instrumentation take most of it
@pytest.mark.skipif(importlib.util.find_spec("atheris") is None, reason="atheris not installed")
def test_short_atheris_run_finds_no_crash() -> None:
    (r,) = run_atheris(["decoder"], 300, seed=3)
    assert r.crash is None, r.crash
    assert r.inputs == 300, (r.target, r.returncode)
    assert r.cov and r.cov > 50, f"{r.target}: no coverage reported ({r.cov})"


def test_the_decoder_oracle_fails_on_a_decoder_that_accepts_version_3(
        monkeypatch: pytest.MonkeyPatch) -> None:
    import shared.protocol.codec as codec

    monkeypatch.setattr(codec, "SUPPORTED_VERSIONS", frozenset({1, 2, 3}))
    body = msgpack.packb({"v": 3, "type": "bye"})
    with pytest.raises(Finding, match="version"):
        TARGETS["decoder"](body)


def test_the_peer_oracle_fails_on_a_wrong_close_code(monkeypatch: pytest.MonkeyPatch) -> None:
    """A relay that closed a wrong token with 1008 instead of the doc's 4001 is caught."""
    from shared.errors import AuthError

    monkeypatch.setattr(AuthError, "close_code", 1008)
    hello = encode(Hello(role="local", session="s1", token="wrong"))
    with pytest.raises(Finding, match=r"close code|4001"):
        TARGETS["peer"](dump(1, [Op(Kind.MSG, payload=hello), Op(Kind.FLUSH)]))


def test_the_peer_oracle_fails_when_an_error_reply_is_missing(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A relay that dropped its answer to a bad message (silent loss) is caught."""
    from shared.protocol.peer_session import PeerSession

    monkeypatch.setattr(PeerSession, "reply", lambda self, msg, build=None: None)
    script = dump(1, [Op(Kind.MSG, payload=encode(hello_for("local"))),
                      Op(Kind.MSG, payload=msgpack.packb({"v": 1, "type": "nope"})),
                      Op(Kind.FLUSH)])
    with pytest.raises(Finding, match="answered"):
        TARGETS["peer"](script)
