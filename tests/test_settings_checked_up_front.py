"""Settings that a component built from them would refuse, or act on badly, are refused
where they are read, naming the user's setting: before, each of these passed the settings'
checks and then failed at start-up with an error naming a parameter no user has, or was
acted on quietly (the board's watchdog tripping between two display ticks, the arm halted
at every check)."""

from __future__ import annotations

from typing import Any

import pytest

from local_site.agent.config import LocalAgentConfig
from relay_server.config import RelayConfig
from remote_site.agent.app import check_arm_watchdog
from remote_site.agent.config import RemoteAgentConfig
from remote_site.arm.safety import SafetyConfig
from shared.config import resolve_config
from shared.errors import ConfigError
from shared.link_settings import StationLinkConfig

_LOCAL: list[tuple[dict[str, Any], str]] = [
    # the display loop's tick sends the board's keepalive: ticks further apart than half the
    # board's watchdog let it trip between them (5 Hz: parked between nearly every tick)
    ({"render_rate_hz": 5.0}, r"render_rate_hz \(5 Hz: a tick every 200 ms\) must tick at "
                              r"least twice within display_watchdog_ms \(100\)"),
    ({"render_rate_hz": 500.0, "display_watchdog_ms": 3},
     r"render_rate_hz \(500 Hz: a tick every 2 ms\)"),
    ({"display_watchdog_ms": 0}, r"display_watchdog_ms must be an integer in \[1, 65535\] "
                                 r"\(the board's watchdog, ms\), got 0"),
    ({"display_watchdog_ms": 70_000}, r"display_watchdog_ms must be an integer in"),
    ({"display_watchdog_ms": 100.5}, r"display_watchdog_ms must be an integer in"),
    ({"display_keepalive_interval_s": 0.2}, r"display_keepalive_interval_s \(200 ms\) plus a "
                                            r"tick \(1 ms\) must be shorter than "
                                            r"display_watchdog_ms \(100\)"),
    # both rules apart would pass: a keepalive every second tick of 50 ms, 100 ms apart
    ({"render_rate_hz": 20.0, "display_keepalive_interval_s": 0.06},
     r"display_keepalive_interval_s \(60 ms\) plus a tick \(50 ms\)"),
    ({"platform_read_timeout_s": 0.004, "platform_reopen_after_s": 0.5},
     r"platform_read_timeout_s must be > 0\.005 s \(the platform reader's poll\), got 0\.004"),
    ({"display_feedback_timeout_s": 0.0}, r"display_feedback_timeout_s must be a number in "
                                          r"\(0, 10\] s"),
    ({"display_feedback_timeout_s": 200}, r"display_feedback_timeout_s must be a number in"),
    ({"display_feedback_timeout_s": float("nan")}, r"display_feedback_timeout_s must be"),
    ({"record_queue_size": 0}, r"record_queue_size must be an integer >= 1, got 0"),
    ({"record_pins_rate_hz": 0.0}, r"record_pins_rate_hz must be a finite number > 0"),
    ({"record_image_rate_hz": -1.0}, r"record_image_rate_hz must be 0 \(no images\) or in "
                                     r"\(0, 1000\]"),
    ({"record_image_rate_hz": 2000.0}, r"record_image_rate_hz must be 0"),
]


@pytest.mark.parametrize(("settings", "message"), _LOCAL)
def test_local_settings_a_component_would_refuse_are_refused_by_name(
        settings: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError, match=r"^local\.agent\." + message):
        LocalAgentConfig(**settings)


def test_the_local_defaults_and_their_edges_pass() -> None:
    LocalAgentConfig()
    LocalAgentConfig(render_rate_hz=20.0)  # a tick every 50 ms: twice within 100 ms
    LocalAgentConfig(display_watchdog_ms=65535, render_rate_hz=1.0)
    LocalAgentConfig(platform_read_timeout_s=0.006)
    LocalAgentConfig(record_image_rate_hz=1000.0, record_queue_size=1)
    LocalAgentConfig(display_feedback_timeout_s=10)


def test_the_display_feedback_timeout_reaches_the_driver() -> None:
    """A board set to feed back slower than ~50 Hz needs a longer limit than the driver's
    0.2 s default, or its healthy link is reopened over and over: the station had no
    setting for it."""
    from local_site.agent.station import LocalAgent

    agent = LocalAgent(LocalAgentConfig(scene="hemisphere", display_feedback_timeout_s=1.5))
    agent.open()
    assert agent.loop is not None
    display = agent.loop.display
    assert display._feedback_timeout_s == 1.5  # type: ignore[union-attr]


@pytest.mark.parametrize(("settings", "message"), [
    ({"reconnect_min_s": 1.0}, r"reconnect_min_s \(1\.0\) must be > 0 and <= "
                               r"reconnect_max_s \(0\.5\)"),
    ({"reconnect_min_s": 0.0}, r"reconnect_min_s \(0\.0\) must be > 0"),
    ({"connect_timeout_s": 0.0}, r"connect_timeout_s must be a finite number > 0, got 0\.0"),
    ({"liveness_timeout_s": -1.0}, r"liveness_timeout_s must be a finite number > 0"),
    ({"max_message_bytes": 0}, r"max_message_bytes must be an integer >= 1, got 0"),
])
def test_link_settings_are_checked_where_they_are_read(settings: dict[str, Any],
                                                       message: str) -> None:
    """Named with their table by the resolver (before: "need 0 < reconnect_min_s <=
    reconnect_max_s" from the link, on the remote only once the arm had been moved)."""
    with pytest.raises(ConfigError, match=r"^" + message):
        StationLinkConfig(**settings)
    env = {f"TELETOUCH_REMOTE_LINK_{k.upper()}": str(v) for k, v in settings.items()}
    with pytest.raises(ConfigError, match=r"^\[remote\.link\]: " + message):
        resolve_config(StationLinkConfig, "remote.link", environ=env)


@pytest.mark.parametrize(("settings", "message"), [
    ({"port": 65535}, r"relay\.port=65535 leaves no port for the TCP listener \(port \+ 1\): "
                      r"set relay\.tcp_port"),
    ({"ping_interval_s": 5.1}, r"relay\.silence_timeout_s \(10 s\) must be at least twice "
                               r"relay\.ping_interval_s \(5\.1 s\)"),
])
def test_relay_settings_that_would_fail_or_misbehave_are_refused(settings: dict[str, Any],
                                                                 message: str) -> None:
    with pytest.raises(ConfigError, match=r"^" + message):
        RelayConfig(**settings)
    RelayConfig(port=65535, tcp_port=65534)
    RelayConfig(ping_interval_s=5.0)


def test_an_arm_watchdog_period_near_the_command_timeout_is_refused() -> None:
    """The watchdog halts the arm once a command is older than the timeout less its period:
    at a period of half the timeout or more, commands arriving every few ms were halted."""
    with pytest.raises(ConfigError, match=r"^remote\.agent\.watchdog_period_s \(50 ms\) must "
                                          r"be under half arm\.safety\.command_timeout_ms "
                                          r"\(100 ms\)"):
        check_arm_watchdog(RemoteAgentConfig(watchdog_period_s=0.05), SafetyConfig())
    check_arm_watchdog(RemoteAgentConfig(watchdog_period_s=0.049), SafetyConfig())
    check_arm_watchdog(RemoteAgentConfig(), SafetyConfig(command_timeout_ms=20.0))


def test_arm_states_faster_than_the_arm_is_polled_are_refused() -> None:
    """Each arm_state carries one poll's reading: more states than polls were capped
    without a word."""
    with pytest.raises(ConfigError, match=r"^remote\.agent\.arm_state_hz \(300\) must be <= "
                                          r"remote\.agent\.arm_poll_hz \(250\): each "):
        RemoteAgentConfig(arm_state_hz=300.0)
    RemoteAgentConfig(arm_state_hz=250.0)


@pytest.mark.parametrize(("variable", "value", "said"), [
    ("WATCHDOG_PERIOD_S", "0.08", "remote.agent.watchdog_period_s (80 ms) must be under half"),
    # a tiny cell allocated a map of the phantom's area in such cells
    ("STIFFNESS_CELL_MM", "0.001", "in cells of 0.001 mm would hold 3,600,000,000 cells"),
    ("ARM_STATE_HZ", "1000", "remote.agent.arm_state_hz (1000) must be <= ")])
def test_the_remote_station_refuses_it_before_anything_opens(
        variable: str, value: str, said: str, caplog: pytest.LogCaptureFixture,
        monkeypatch: pytest.MonkeyPatch) -> None:
    from lab.cli import main

    opened: list[object] = []
    monkeypatch.setattr("remote_site.agent.app.open_world",
                        lambda *args, **kwargs: opened.append(args))  # the first device opened
    monkeypatch.setenv(f"TELETOUCH_REMOTE_AGENT_{variable}", value)
    monkeypatch.setenv("TELETOUCH_REMOTE_LINK_TOKEN", "x")
    assert main(["remote", "--relay", "tcp://127.0.0.1:9", "--session", "s1", "--arm", "sim",
                 "--sensor", "sim", "--phantom", "severity", "--seed", "2", "--ideal"]) == 1
    assert any(said in r.getMessage() for r in caplog.records), caplog.records
    assert opened == []


@pytest.mark.parametrize(("settings", "message"), [
    # 100 meant as milliseconds: the pins would hold a touch 100 s after the link died
    ({"link_loss_timeout_s": 100.0}, r"link_loss_timeout_s \(100 s\) must be <= 5 s: it "
                                     r"bounds how long the pins may hold a touch"),
    ({"stale_frame_timeout_s": 1e6}, r"stale_frame_timeout_s \(1e\+06 s\) must be <= 5 s"),
    ({"max_frame_age_s": 1e6}, r"max_frame_age_s \(1e\+06 s\) must be <= 5 s"),
    ({"max_frame_age_s": 5.01}, r"max_frame_age_s \(5\.01 s\) must be <= 5 s"),
    ({"max_offset_uncertainty_s": 1e6}, r"max_offset_uncertainty_s \(1e\+06 s\) must be < "
                                        r"local\.agent\.max_frame_age_s \(0\.15 s\)"),
])
def test_local_safety_timeouts_beyond_any_meaning_are_refused(settings: dict[str, Any],
                                                              message: str) -> None:
    with pytest.raises(ConfigError, match=r"^local\.agent\." + message):
        LocalAgentConfig(**settings)
    env = {f"TELETOUCH_LOCAL_AGENT_{k.upper()}": str(v) for k, v in settings.items()}
    with pytest.raises(ConfigError, match=r"^local\.agent\." + message):
        resolve_config(LocalAgentConfig, "local.agent", environ=env)


def test_local_safety_timeouts_at_their_bound_pass() -> None:
    LocalAgentConfig(link_loss_timeout_s=5.0, stale_frame_timeout_s=5.0, max_frame_age_s=5.0)
    LocalAgentConfig(max_offset_uncertainty_s=0.149)


def test_a_remote_link_loss_halt_beyond_any_meaning_is_refused() -> None:
    with pytest.raises(ConfigError, match=r"^remote\.agent\.link_loss_halt_ms \(100000\) must "
                                          r"be <= 5000"):
        RemoteAgentConfig(link_loss_halt_ms=100_000.0)
    RemoteAgentConfig(link_loss_halt_ms=5000.0)


@pytest.mark.parametrize(("argv", "said"), [
    # before: refused only once the arm and the sensor had been opened (the station's run)
    (["--duration", "nan"], "--duration must be a finite number of seconds > 0, got nan"),
    (["--duration", "-1"], "--duration must be a finite number of seconds > 0, got -1.0"),
    (["--duration", "inf"], "--duration must be a finite number of seconds > 0, got inf"),
    # a hello the relay refuses at every attempt, retried for ever
    (["--session", "lab 1"], "session 'lab 1' is not a session id"),
    (["--relay", "ws://u:hunter2@127.0.0.1:9/"], "holds user information"),
])
def test_a_remote_command_line_that_cannot_work_is_refused_before_anything_opens(
        argv: list[str], said: str, caplog: pytest.LogCaptureFixture,
        monkeypatch: pytest.MonkeyPatch) -> None:
    from lab.cli import main

    opened: list[object] = []
    monkeypatch.setattr("remote_site.agent.app.open_world",
                        lambda *args, **kwargs: opened.append(args))  # the first device opened
    monkeypatch.setattr("remote_site.agent.app.open_world_arm",
                        lambda *args, **kwargs: opened.append(args))
    monkeypatch.setenv("TELETOUCH_REMOTE_LINK_TOKEN", "x")
    base = {"--relay": "tcp://127.0.0.1:9", "--session": "s1"}
    base.update(dict(zip(argv[::2], argv[1::2], strict=True)))
    args = [item for pair in base.items() for item in pair]
    assert main(["remote", *args, "--arm", "sim", "--sensor", "sim", "--phantom", "severity",
                 "--seed", "2", "--ideal"]) == 1
    assert any(said in r.getMessage() for r in caplog.records), caplog.records
    assert not any("hunter2" in r.getMessage() for r in caplog.records)
    assert opened == []
