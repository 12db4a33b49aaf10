"""The seed corpus: real encoded messages of every type, and session scripts built from them.

Every message is encoded by the product encoder (``shared.protocol.encode``), so the seeds are
what stations and the relay really put on the wire; the fuzzers start from them and mutate.
"""

from __future__ import annotations

import numpy as np

from lab.fuzz.script import Kind, Op, dump
from relay_server.auth import derive_token, make_token
from shared.protocol import (
    MESSAGE_TYPES,
    ArmCommand,
    ArmState,
    Bye,
    ClockPing,
    ClockPong,
    Error,
    Hello,
    Hop,
    Message,
    PlatformState,
    Stats,
    TactileFrame,
    Welcome,
    encode,
)
from shared.protocol.tactile_codec import TactileEncoder

__all__ = ["FUZZ_SECRET", "SESSIONS", "hello_for", "sample_messages", "seed_messages",
           "seed_scripts"]

#: the relay secret of the fuzz harnesses (tokens in the seeds are derived from it)
FUZZ_SECRET = "fuzz-secret-0123456789abcdef0123456789"
#: session ids used by the seeds (two, so cross-session isolation is exercised)
SESSIONS = ("s1", "s2")
_FAR_FUTURE_S = 4_000_000_000  # a v2 token expiry in 2096


def hello_for(role: str, session: str = SESSIONS[0], *, v2: bool = False) -> Hello:
    """A hello the fuzz relay accepts (legacy derived token, or a v2 token)."""
    token = (make_token(FUZZ_SECRET, session, role, _FAR_FUTURE_S) if v2
             else derive_token(FUZZ_SECRET, session))
    return Hello(role=role, session=session, token=token, name=f"fuzz-{role}")


def sample_messages() -> list[Message]:
    """At least one realistic message of every type (several for the richer ones)."""
    ts = 1_700_000_000_000_000
    hops = (Hop("local", "capture", ts), Hop("relay", "relay_in", ts + 150))
    rng = np.random.default_rng(7)
    height = rng.uniform(-2.0, 2.0, (6, 6)).astype("<f4")
    stiff = np.full((6, 6), 0.75, "<f8")
    msgs: list[Message] = [
        hello_for("local"), hello_for("remote", v2=True), hello_for("observer"),
        Welcome(session="s1", role="local", server_time_us=ts, ping_interval_s=1.0,
                max_message_bytes=4 * 1024 * 1024),
        ClockPing(ping_id=3, t0_us=ts),
        ClockPong(ping_id=3, t0_us=ts, t1_us=ts + 40, t2_us=ts + 55),
        Stats(scope="relay", time_us=ts, metrics={
            "session": "s1", "clock_offset_us": {"local": 120, "remote": None},
            "drops": {"local_to_remote": {"lost": 0, "latest_wins": 3}}, "ok": True,
            "rate_hz": 999.5}),
        Error(code="bad_field", message="platform_state.seq is missing", fatal=False),
        Error(code="queue_full", message="arm_command seq 9 refused", fatal=False,
              stream="arm_command", seq=9),
        Bye(reason="done"),
        PlatformState(seq=1, ts_us=ts, hops=hops[:1], position_mm=(1.5, -2.0, 30.0),
                      velocity_mm_s=(0.0, 12.5, -3.0)),
        ArmCommand(seq=2, ts_us=ts, action="move", target_mm=(10.0, 20.0, 5.0)),
        ArmCommand(seq=3, ts_us=ts, action="set_force_limit", force_limit_n=4.5),
        ArmCommand(seq=4, ts_us=ts, action="stop"),
        ArmState(seq=5, ts_us=ts, hops=hops, position_mm=(10.0, 20.0, 4.0), force_n=1.25,
                 status="moving", source_seq=1),
        TactileFrame(seq=6, ts_us=ts, hops=hops, center_mm=(1.5, -2.0), pitch_mm=1.7,
                     layers={"height_mm": height, "stiffness_k": stiff}, contact=True,
                     force_n=2.0, indentation_mm=0.4, source_seq=1, source_ts_us=ts),
    ]
    # the compact codec's key frame and a delta against it (protocol v2)
    encoder = TactileEncoder()
    for seq, h in ((7, height), (8, height + np.float32(0.05))):
        msgs.append(encoder.encode(TactileFrame(
            seq=seq, ts_us=ts, hops=hops, center_mm=(1.5, -2.0), pitch_mm=1.7,
            layers={"height_mm": h, "stiffness_k": stiff}, contact=True, force_n=2.0,
            indentation_mm=0.4, source_seq=1, source_ts_us=ts)))
    missing = set(MESSAGE_TYPES) - {m.TYPE for m in msgs}
    assert not missing, f"seed corpus lacks {sorted(missing)}"
    return msgs


def seed_messages() -> list[bytes]:
    """Every sample message encoded (one msgpack map each, no framing)."""
    return [encode(m) for m in sample_messages()]


def _station_traffic(role: str) -> list[bytes]:
    """Messages a station of ``role`` sends after its hello (its streams and control)."""
    out = []
    for m in sample_messages():
        if (role == "local" and m.TYPE in ("platform_state", "arm_command")) or (
                role == "remote" and m.TYPE in ("arm_state", "tactile_frame")) or (
                m.TYPE in ("clock_ping", "clock_pong", "stats", "bye")):
            out.append(encode(m))
    return out


def seed_scripts(target: str) -> list[bytes]:
    """Seed inputs of a session target (``station``, ``peer`` or ``relay``)."""
    msgs = {m.TYPE: encode(m) for m in sample_messages()}
    every = seed_messages()
    scripts: list[bytes] = []
    if target == "station":
        welcome = Op(Kind.MSG, payload=msgs["welcome"])
        relay_side = [encode(m) for m in sample_messages() if m.TYPE not in ("hello", "welcome")]
        for options in (0, 1):  # tcp, ws
            scripts.append(dump(options, [welcome, *(Op(Kind.MSG, payload=p)
                                                     for p in relay_side), Op(Kind.FLUSH)]))
            scripts.append(dump(options, [Op(Kind.MSG, payload=msgs["error"])]))
            scripts.append(dump(options, [welcome, Op(Kind.MSG, payload=msgs["clock_ping"]),
                                          Op(Kind.STEP, value=-5_000_000), Op(Kind.FLUSH),
                                          Op(Kind.TIME, value=6_000_000), Op(Kind.TICK),
                                          Op(Kind.CLOSE), welcome]))
        return scripts
    if target == "peer":
        for options in (0, 1):
            for role in ("local", "remote", "observer"):
                hello = Op(Kind.MSG, payload=encode(hello_for(role, v2=role == "remote")))
                scripts.append(dump(options, [hello, *(Op(Kind.MSG, payload=p) for p in every),
                                              Op(Kind.TICK), Op(Kind.FLUSH)]))
            scripts.append(dump(options, [Op(Kind.MSG, payload=msgs["platform_state"])]))
            scripts.append(dump(options, [Op(Kind.TIME, value=10_000_000), Op(Kind.TICK)]))
        return scripts
    if target == "relay":
        for options in (0, 1, 2, 3):
            ops = []
            for peer, role in enumerate(("local", "remote", "observer")):
                ops.append(Op(Kind.MSG, peer, encode(hello_for(role, v2=peer == 1))))
            ops.append(Op(Kind.TIME, value=25_000))
            ops.append(Op(Kind.TICK))
            ops.append(Op(Kind.FLUSH))
            for peer, role in ((0, "local"), (1, "remote")):
                ops.extend(Op(Kind.MSG, peer, p) for p in _station_traffic(role))
            ops.extend([Op(Kind.FLUSH, 1), Op(Kind.FLUSH, 0), Op(Kind.FLUSH, 2),
                        Op(Kind.MSG, 3, encode(hello_for("local", SESSIONS[1]))),
                        Op(Kind.MSG, 3, msgs["platform_state"]), Op(Kind.CLOSE, 1),
                        Op(Kind.MSG, 0, msgs["arm_command"]), Op(Kind.FLUSH, 0)])
            scripts.append(dump(options, ops))
        return scripts
    raise ValueError(f"no seed scripts for target {target!r}")
