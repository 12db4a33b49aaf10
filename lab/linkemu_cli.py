"""Emulate a long-haul link between a station and the relay (or any two TCP endpoints).

An asyncio TCP proxy: listens on --listen, forwards to --target, and adds one-way delay,
jitter (in-order, like TCP), loss (as the retransmission delay it costs), a bandwidth cap
and outages to each direction. Works for WebSocket and raw TCP alike.

Profiles (one-way delay / jitter / loss / bandwidth):
  lan               0.1 ms / 0.02 ms / 0       / 1000 Mbit/s
  city-1000km       10 ms  / 1 ms    / 0.05 %  / 100 Mbit/s   (~20 ms round trip)
  intercontinental  90 ms  / 3 ms    / 0.1 %   / 50 Mbit/s    (~180 ms round trip)
  bad-wifi          8 ms   / 5 ms    / 3 %, bursts of ~5 segments / 20 Mbit/s
Flags override single values of the profile.

--listen may be repeated: one process then serves several legs towards the same target (the
demo's local <-> relay and remote <-> relay legs), each an independent emulated link with its
own connections, statistics and impairment seed (``--seed`` + the leg's index); the outage
schedule and SIGUSR1 apply to every leg. One process for both legs halves the emulators'
processes (and the scheduler's wake-ups) on a busy machine.

examples:
  teletouch link --listen 127.0.0.1:9765 --target 127.0.0.1:8765 --profile city-1000km
  teletouch link --listen :9765 --listen :9766 --target 127.0.0.1:8765 --delay-ms 5
  teletouch link --listen :9766 --target relay.example:8766 --profile lan --delay-ms 25 \\
      --outage 30:2 --outage-every 60 --outage-duration 0.5 --outage-close --seed 1
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from typing import Any

__all__ = ["LinkSettings", "configure_parser", "parse_host_port", "run"]


@dataclass(frozen=True)
class LinkSettings:
    """Settings of ``teletouch link`` (TOML table ``[link]``, env ``TELETOUCH_LINK_*``).

    Attributes:
        listen: ``HOST:PORT`` to listen on (``:PORT`` = 127.0.0.1); several: one leg each,
            all in this process (a TOML string with commas or a list).
        target: ``HOST:PORT`` to forward to.
        profile: a named profile (see ``--help``).
        delay_ms, jitter_ms, loss, loss_burst_len, loss_penalty_ms, bandwidth_mbps:
            overrides of the profile (None = keep the profile's value).
        outages: scheduled ``START:DURATION`` windows (seconds after start).
        outage_every_s: mean gap between random outages (None = none).
        outage_duration_s: mean duration of random outages (None = profile's).
        outage_close: reset connections at each outage.
        outage_on_signal_s: SIGUSR1 starts an outage of this many seconds (None = SIGUSR1
            is not handled); ``outage_close`` applies to it too. The fault suite
            (``lab/faults.py``) injects its blackholes and resets this way, so it knows to
            the millisecond when each began.
        seed: random seed of the impairments (leg ``i`` uses ``seed + i``).
        duration_s: stop after this many seconds (None = until Ctrl-C).
        stats_interval_s: live status period.
    """

    listen: tuple[str, ...] = ("127.0.0.1:9765",)
    target: str = "127.0.0.1:8765"
    profile: str = "lan"
    delay_ms: float | None = None
    jitter_ms: float | None = None
    loss: float | None = None
    loss_burst_len: float | None = None
    loss_penalty_ms: float | None = None
    bandwidth_mbps: float | None = None
    outages: tuple[str, ...] = ()
    outage_every_s: float | None = None
    outage_duration_s: float | None = None
    outage_close: bool = False
    outage_on_signal_s: float | None = None
    seed: int | None = None
    duration_s: float | None = None
    stats_interval_s: float = 5.0

    def __post_init__(self) -> None:
        from shared.config import check_positive

        # (0 would spin the status loop; a negative duration end at once)
        check_positive("link.stats_interval_s", self.stats_interval_s)
        if self.duration_s is not None:
            check_positive("link.duration_s", self.duration_s)


def parse_host_port(text: str, *, default_host: str = "127.0.0.1") -> tuple[str, int]:
    """Parse ``HOST:PORT``, ``:PORT`` or ``[v6]:PORT``.

    Raises:
        ConfigError: no port or a port outside 0-65535.
    """
    from shared.errors import ConfigError

    host, sep, port_text = text.rpartition(":")
    if not sep:
        raise ConfigError(f"expected HOST:PORT, got {text!r}")
    host = host.strip("[]") or default_host
    try:
        port = int(port_text)
    except ValueError as err:
        raise ConfigError(f"bad port in {text!r}") from err
    if not 0 <= port <= 65535:
        raise ConfigError(f"port out of range in {text!r}")
    return host, port


def _parse_outage(text: str) -> tuple[float, float]:
    from shared.errors import ConfigError

    start, sep, duration = text.partition(":")
    try:
        if not sep:
            raise ValueError(text)
        return float(start), float(duration)
    except ValueError as err:
        raise ConfigError(f"--outage expects START_S:DURATION_S, got {text!r}") from err


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Add the link emulator's flags (None = not given, so env/TOML/defaults apply)."""
    parser.add_argument("--listen", action="append",
                        help="HOST:PORT to listen on (default 127.0.0.1:9765); repeat it "
                             "for more legs served by this one process")
    parser.add_argument("--target", help="HOST:PORT to forward to (default 127.0.0.1:8765)")
    parser.add_argument("--profile", help="lan, city-1000km, intercontinental, bad-wifi "
                                          "(default lan)")
    parser.add_argument("--config", help="TOML file with a [link] table (or $TELETOUCH_CONFIG)")
    parser.add_argument("--delay-ms", dest="delay_ms", type=float, help="one-way delay")
    parser.add_argument("--jitter-ms", dest="jitter_ms", type=float,
                        help="standard deviation of the extra one-way delay")
    parser.add_argument("--loss", type=float, help="fraction of segments lost, e.g. 0.01")
    parser.add_argument("--loss-burst-len", dest="loss_burst_len", type=float,
                        help="mean number of consecutive lost segments (>= 1)")
    parser.add_argument("--loss-penalty-ms", dest="loss_penalty_ms", type=float,
                        help="delay a loss adds (default 2 x delay + 4 x jitter)")
    parser.add_argument("--bandwidth-mbps", dest="bandwidth_mbps", type=float,
                        help="bottleneck rate in Mbit/s")
    parser.add_argument("--outage", dest="outages", action="append", metavar="START:DURATION",
                        help="scheduled outage, seconds after start (repeatable)")
    parser.add_argument("--outage-every", dest="outage_every_s", type=float, metavar="S",
                        help="random outages with this mean gap")
    parser.add_argument("--outage-duration", dest="outage_duration_s", type=float,
                        metavar="S", help="mean duration of random outages")
    parser.add_argument("--outage-close", dest="outage_close", action="store_true",
                        default=None, help="reset connections when an outage starts")
    parser.add_argument("--outage-on-signal", dest="outage_on_signal_s", type=float,
                        metavar="S", help="SIGUSR1 starts an outage of S seconds "
                                          "(with --outage-close: a reset)")
    parser.add_argument("--seed", type=int, help="random seed of the impairments")
    parser.add_argument("--duration", dest="duration_s", type=float, metavar="S",
                        help="stop after S seconds (default: run until Ctrl-C)")
    parser.add_argument("--stats-interval", dest="stats_interval_s", type=float, metavar="S",
                        help="live status period (default 5)")
    parser.add_argument("--json", action="store_true",
                        help="print the final statistics as one JSON object")


def run(args: argparse.Namespace) -> int:
    """Resolve the settings, run the proxy, print its statistics at the end."""
    import asyncio
    import contextlib
    import logging
    import math
    import signal

    from lab.linkemu import LinkEmulator, get_profile
    from shared.config import resolve_config
    from shared.errors import ConfigError
    from shared.report import StatusLine, emit, emit_json

    names = ("listen", "target", "profile", "delay_ms", "jitter_ms", "loss", "loss_burst_len",
             "loss_penalty_ms", "bandwidth_mbps", "outages", "outage_every_s",
             "outage_duration_s", "outage_close", "outage_on_signal_s", "seed", "duration_s",
             "stats_interval_s")
    explicit = {n: getattr(args, n, None) for n in names}
    if explicit["listen"] is not None:
        explicit["listen"] = tuple(explicit["listen"])
    settings = resolve_config(LinkSettings, "link", explicit=explicit,
                              toml_path=getattr(args, "config", None))
    profile = get_profile(settings.profile).replace(
        delay_ms=settings.delay_ms, jitter_ms=settings.jitter_ms, loss=settings.loss,
        loss_burst_len=settings.loss_burst_len, loss_penalty_ms=settings.loss_penalty_ms,
        bandwidth_mbps=settings.bandwidth_mbps, outage_every_s=settings.outage_every_s,
        outage_duration_s=settings.outage_duration_s,
        outages=tuple(_parse_outage(o) for o in settings.outages) or None,
        close_on_outage=settings.outage_close or None)
    if settings.outage_on_signal_s is not None and not (
            math.isfinite(settings.outage_on_signal_s) and settings.outage_on_signal_s > 0):
        raise ConfigError("--outage-on-signal needs a finite duration > 0 s")
    if not settings.listen:
        raise ConfigError("--listen: at least one HOST:PORT")
    listens = [parse_host_port(text) for text in settings.listen]
    target = parse_host_port(settings.target)

    async def main() -> list[dict[str, Any]]:
        status = StatusLine(min_interval_s=settings.stats_interval_s)
        async with contextlib.AsyncExitStack() as stack:
            emus = [await stack.enter_async_context(LinkEmulator(
                listen=listen, target=target, profile=profile,
                seed=None if settings.seed is None else settings.seed + i))
                for i, listen in enumerate(listens)]
            loop = asyncio.get_running_loop()
            if settings.outage_on_signal_s is not None:
                signal_outage_s = settings.outage_on_signal_s

                def on_signal() -> None:
                    log.info("link emulator: outage of %.3f s (SIGUSR1)%s", signal_outage_s,
                             ", connections reset" if settings.outage_close else "")
                    for emu in emus:
                        emu.start_outage(signal_outage_s,
                                         close_connections=bool(settings.outage_close))

                loop.add_signal_handler(signal.SIGUSR1, on_signal)  # before "listening"
            for emu in emus:
                emit(f"link emulator listening on {emu.host}:{emu.port} -> "
                     f"{target[0]}:{target[1]} ({profile.name}: one-way {profile.delay_ms} ms "
                     f"+/- {profile.jitter_ms} ms, loss {profile.loss:g}, "
                     f"bandwidth {profile.bandwidth_mbps or 'unlimited'} Mbit/s)")
            end_s = None if settings.duration_s is None else loop.time() + settings.duration_s
            with contextlib.suppress(asyncio.CancelledError):
                while end_s is None or loop.time() < end_s:
                    step = settings.stats_interval_s
                    if end_s is not None:
                        step = min(step, max(0.0, end_s - loop.time()))
                    await asyncio.sleep(step)
                    status.update(" || ".join(_status_text(emu.port, emu.stats())
                                              for emu in emus))
            return [{"listen": f"{emu.host}:{emu.port}", **emu.stats()} for emu in emus]

    log = logging.getLogger("lab.linkemu")
    legs = asyncio.run(main())
    if args.json:
        # one leg: its statistics as before; several: {"legs": [...]} in --listen order
        emit_json(legs[0] if len(legs) == 1 else {"legs": legs})
    else:
        for leg in legs:
            for direction in ("up", "down"):
                d = leg[direction]
                emit(f"{leg['listen']} {direction}: {d['bytes']} B in {d['chunks']} chunks, "
                     f"{d['lost_segments']} segments lost, delay ms {d['actual_delay_ms']}")
    return 0


def _status_text(port: int, s: dict[str, Any]) -> str:
    return (f":{port} conns {s['connections_open']} open | up {s['up']['bytes']} B p50 "
            f"{s['up']['actual_delay_ms']['p50']} ms | down {s['down']['bytes']} B | "
            f"link {'up' if s['link_up'] else 'DOWN'}")
