"""The NATS hop benchmark's floor paths against a real nats-server: every measured message
arrives on each path, warm-up messages are not counted, and the one-way times are
plausible (positive, under the test's own duration)."""

from __future__ import annotations

import asyncio
import math

import pytest

from tests.support import MachineStalls, scaled

pytest.importorskip("nats", reason="the floor's nats-py path needs nats-py")
from lab.bench.nats_floor import PATHS, FloorSender, start_receiver
from tests.relay_server.test_cluster import nats_server

SIZE = 19_452


async def _run(url: str) -> tuple[dict[str, int], dict[str, list[int]], float,
                                  dict[str, MachineStalls]]:
    loop = asyncio.get_running_loop()
    t0 = loop.time()
    receiver, pipe, port = await asyncio.to_thread(start_receiver, url, SIZE)
    sender = FloorSender(url, port, SIZE)
    try:
        await sender.open()
        sent: dict[str, int] = {}
        stalls: dict[str, MachineStalls] = {}
        for path in PATHS:
            with MachineStalls() as stalls[path]:
                sent[path] = await sender.phase(path, 50.0, 0.4, 0.2)
        pipe.send("done")
        async with asyncio.timeout(scaled(20.0)):
            got: dict[str, list[int]] = await asyncio.to_thread(pipe.recv)
    finally:
        await sender.close()
        receiver.join(scaled(10.0))
        if receiver.is_alive():
            receiver.kill()
    return sent, got, loop.time() - t0, stalls


def test_every_measured_message_arrives_once_on_each_path() -> None:
    async def main() -> tuple[dict[str, int], dict[str, list[int]], float,
                              dict[str, MachineStalls]]:
        async with nats_server() as url:
            return await _run(url)

    sent, got, elapsed_s, stalls = asyncio.run(main())
    for path in PATHS:
        # 0.4 s at 50 Hz after a 0.2 s warm-up: about 20 measured, none of the ~10 warm-up.
        # The sender catches up after a stall and its phase ends on the clock: a stall of the
        # machine moves warm-up messages into the count or ends it early, a message per 20 ms
        slack = math.ceil(50.0 * stalls[path].total_s)
        assert 15 - slack <= sent[path] <= 22 + slack, (path, sent, stalls[path].stalls_s)
        assert len(got[path]) == sent[path], (path, sent, {p: len(v) for p, v in got.items()})
        assert all(0 < us < elapsed_s * 1e6 for us in got[path]), (path, got[path])


@pytest.mark.parametrize("flags", [["--rounds", "0"], ["--rate-hz", "0"], ["--round-s", "nan"],
                                   ["--rate-hz", "-5"]])
def test_bench_nats_hop_refuses_bad_settings_before_starting_anything(flags: list[str]) -> None:
    """A usage error, with the flag named, before any server is started (exit 1, no traceback
    from inside the benchmark)."""
    from lab.cli import main

    assert main(["bench", "nats-hop", *flags]) == 1
