"""Settings of the local station agent: TOML table ``[local.agent]``.

The table is ``[local.agent]`` rather than ``[local]`` because ``[local]`` already holds the
``[local.link]`` and ``[local.render]`` sub-tables, which :func:`shared.config.resolve_config`
would report as unknown keys of a ``local`` section. Environment variables are therefore
``TELETOUCH_LOCAL_AGENT_<FIELD>`` (for example ``TELETOUCH_LOCAL_AGENT_DISPLAY=sim``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from local_site.agent.platform_process import HANG_TIMEOUT_S as PLATFORM_HANG_TIMEOUT_S
from local_site.agent.platform_reader import POLL_S as PLATFORM_POLL_S
from local_site.render.interpolation import DEFAULT_ORDER
from shared.config import check_count, check_positive
from shared.errors import ConfigError
from shared.loop_watchdog import check_hang_timeout
from shared.view.server import check_host_names

__all__ = ["MAX_SAFETY_TIMEOUT_S", "RENDER_LOOP_MODES", "SAFE_STATE_MODES", "LocalAgentConfig"]

#: the longest link-loss, stale-frame and frame-age bound (docs/safety.md: the pins safe
#: within 100 ms of the last valid input by default): beyond it, a rule that puts the pins in
#: their safe state no longer acts in any meaningful time (``100`` meant as milliseconds
#: would hold a touch 100 s after the link died)
MAX_SAFETY_TIMEOUT_S = 5.0
#: the longest silence of the drive board before its link counts as lost
MAX_FEEDBACK_TIMEOUT_S = 10.0

SAFE_STATE_MODES = ("flat", "hold")
#: where the display loop runs: a dedicated thread (default, by measurement) or an asyncio task
RENDER_LOOP_MODES = ("thread", "asyncio", "process")


@dataclass(frozen=True)
class LocalAgentConfig:
    """Everything the local agent can be told (flags override, see ``teletouch local -h``).

    Attributes:
        platform: platform spec for :func:`local_site.devices.open_platform` (``sim``,
            ``/dev/ttyUSB0``, ``socket://host:port``...).
        display: display spec for :func:`local_site.devices.open_display` (``sim``,
            ``sim-serial``, ``can://socketcan/can0``...).
        motion: scripted operator of the simulated platform (see
            :mod:`local_site.platform.motion_spec`); empty: the backend's default.
        scene: a local scene (shape name or ``.npz`` layer file) to run without a relay;
            empty: render the remote tactile stream from the relay.
        safe_state: display safe state on link loss / stale scene / lost platform.
        link_loss_timeout_s: link down longer than this puts the display in its safe state
            (at most :data:`MAX_SAFETY_TIMEOUT_S`, 5 s, as the next two).
        stale_frame_timeout_s: no tactile frame for this long (while linked) does the same.
        max_frame_age_s: a tactile frame that may be older than this by its own capture
            stamp (clock-corrected with the relay's offsets, their error bound included) is
            never rendered; the pins go to their safe state instead.
        max_offset_uncertainty_s: frames are not rendered while that error bound is wider
            (below ``max_frame_age_s``: a bound as wide refuses every frame as stale).
        platform_send_rate_hz: platform_state messages per second to the relay (at most).
        render_rate_hz: display loop rate (the array refresh; 1 kHz by default; its ticks
            send the board's keepalive, so at least two ticks within display_watchdog_ms).
        render_loop: where the display loop runs: ``thread`` (a thread of the station),
            ``asyncio`` (a task on its event loop) or ``process`` (a process of its own with
            the board link and the renderer, :mod:`local_site.agent.display_process`; the
            platform is then read in a process of its own too).
        platform_read_timeout_s: no new platform sample for this long means it is lost
            (0.25 s: on a loaded 2-core host the reader thread was seen starved > 100 ms).
        platform_reopen_after_s: a platform silent this long (its port still open) is closed
            and reopened; before that its samples are taken the moment they come back
            (>= ``platform_read_timeout_s``; < 15 s, the platform process's hang timeout,
            when the platform is read in a process of its own).
        platform_process: read the platform in a process of its own, the newest sample in
            shared memory (:mod:`local_site.agent.platform_process`): the platform's threads
            then no longer take the display loop's GIL.
        device_retry_min_s: first delay before reopening a lost device.
        device_retry_max_s: largest such delay (the delay doubles up to it).
        display_keepalive_interval_s: unchanged commands are re-sent this often.
        display_watchdog_ms: the drive board's link-loss watchdog.
        display_feedback_timeout_s: no feedback from the drive board for this long (by the
            driver's reader) breaks the link, and the display loop reopens it (default 0.2 s:
            100 periods of the board's 500 Hz feedback; a board set to feed back slower needs
            more, at most 10 s).
        interpolation_order: interpolation of grid scenes (0, 1 or 3; default
            :data:`~local_site.render.interpolation.DEFAULT_ORDER`, Keys cubic).
        scene_center_x_mm: x where a shape without ``x_mm`` is placed (platform frame).
        scene_center_y_mm: y where a shape without ``y_mm`` is placed.
        status_interval_s: status line refresh period.
        record_queue_size: items the ``--record`` writer thread may fall behind by before
            new ones are dropped (counted; the loops never wait for the disk).
        record_pins_rate_hz: rate of the recording's ``/local/pins`` channel.
        record_image_rate_hz: also record the tactile patch as a ``foxglove.CompressedImage``
            PNG (``/local/tactile_image``) at most this often; 0: off (the default; the PNG
            encoding costs the writer thread CPU, benchmarks/results/recording_image.md).
        record_findings: at a clean stop of a relay session, run the palpation analysis on
            the recording and add its findings (``/local/findings``) before closing it.
        motion_done_grace_s: with ``--until-motion-done``, keep running this long after the
            motion finished so the last tactile frames come back.
        gil_switch_interval_s: ``sys.setswitchinterval`` while the agent runs (restored
            after), in the process that runs the display loop (with ``render_loop =
            "process"``, the display process; the station then keeps Python's: less CPU and
            no worse motion-to-touch in paired runs, docs/speed.md section 21). 0.2 ms
            (default) bounds how long a busy thread can hold the display loop and the
            platform reader off the GIL.
            Measured (docs/speed.md section 9, benchmarks/results/cpu_gil_switch/): 1 ms
            cost about 0.05 cores less and ran the loop faster, but the demo's palpation
            typing then scattered from session to session (its benign tumor's malignant
            score 0.52-1.06 in 8 sessions, typed malignant once in a CI run, against
            0.74-0.84 at 0.2 ms: at 1 ms the platform went silent for 250 ms more often, 5
            of 20 sessions against 1 of 16, and such a gap in the uplink moves the score,
            benchmarks/results/platform_silence.md). 0 leaves the interpreter's setting
            alone.
        display_thread_nice: the display loop thread's nice value while it runs (-20..19;
            Linux, per thread). Negative asks the OS to run the 1 kHz loop before ordinary
            work when it wakes (a loaded machine otherwise makes it wait for a core); it
            needs the right to raise priority (root or ``CAP_SYS_NICE``), else the thread
            keeps its priority and the summary says so. 0 (the default) leaves the priority
            alone: in the demo, where both stations share two cores, -10 raised the loop to
            ~790-950 Hz but the remote station then stalled (0.3-4.4 s) in 5 of 6 runs
            (docs/speed.md section 7), so it is for a station on a machine of its own.
        display_thread_realtime: the display loop thread's ``SCHED_FIFO`` priority while it
            runs (1..99; 0: left alone; default 10). The thread then runs as soon as it
            wakes, ahead of all ordinary threads and processes, as a haptic loop should; it
            needs root or ``CAP_SYS_NICE`` (else logged once at INFO, the thread keeps its
            policy and the summary's ``display_loop.thread_realtime`` is null). It sleeps
            every period, and the kernel's real-time throttling bounds it in any case.
            Measured in the demo (docs/speed.md sections 10 and 12): the loop at 989-999 Hz
            against 940-988 Hz, period jitter p99 0.51-0.96 ms against 1.3-2.0 ms, for about
            the same CPU; the demo's motion-to-touch no better (both stations share its two
            cores). Only the loop's thread: the threads the display starts when the loop
            opens it (its reader) run with the main thread's policy (docs/speed.md section 19).
        lock_memory: keep the station's memory in RAM while it runs (``mlockall`` on
            fault, :mod:`shared.memlock`): no page of the display loop, the platform reader or
            the link is read back from disk mid-session. Taken only where it cannot make a
            later allocation fail (``RLIMIT_MEMLOCK`` unlimited, as the systemd unit sets, or
            ``CAP_IPC_LOCK``); otherwise logged at INFO and the summary's
            ``memory_lock.reason`` says why.
        view: serve the live view in the browser on ``HOST:PORT`` (empty: no view;
            ``127.0.0.1:8780`` keeps it on this machine, see docs/view.md).
        view_rate_hz: the view's snapshot rate (the page's update rate).
        view_allowed_hosts: host names (besides IP addresses, ``localhost``, the bound name
            and, bound beyond loopback, the machine's name) the browser may reach the view
            by: a tunnel's or a proxy's name (``TELETOUCH_LOCAL_AGENT_VIEW_ALLOWED_HOSTS=
            a.example,b.example``); any other name gets HTTP 403 (DNS rebinding,
            docs/security.md).
        hang_timeout_s: the station's event loop stuck this long (a busy loop, a call that
            never returns), once its loops run: every thread's stack is written to standard
            error and the process exits with code 1 (:mod:`shared.loop_watchdog`), for
            systemd or a container's ``restart: on-failure`` to start it again. The pins
            (the board's watchdog, the display process's own checks) do not wait for it. 0:
            no such watchdog (a debugger's breakpoint stops the loop); else at least 1 s.
    """

    platform: str = "sim"
    display: str = "sim"
    motion: str = ""
    scene: str = ""
    safe_state: str = "flat"
    link_loss_timeout_s: float = 0.1
    stale_frame_timeout_s: float = 0.08
    max_frame_age_s: float = 0.15
    max_offset_uncertainty_s: float = 0.03
    platform_send_rate_hz: float = 250.0
    render_rate_hz: float = 1000.0
    render_loop: str = "thread"
    platform_read_timeout_s: float = 0.25
    platform_reopen_after_s: float = 1.0
    platform_process: bool = False
    device_retry_min_s: float = 0.2
    device_retry_max_s: float = 5.0
    display_keepalive_interval_s: float = 0.02
    display_watchdog_ms: int = 100
    display_feedback_timeout_s: float = 0.2
    interpolation_order: int = DEFAULT_ORDER
    scene_center_x_mm: float = 30.0
    scene_center_y_mm: float = 30.0
    status_interval_s: float = 0.25
    record_queue_size: int = 8192
    record_pins_rate_hz: float = 50.0
    record_image_rate_hz: float = 0.0
    record_findings: bool = True
    motion_done_grace_s: float = 0.5
    gil_switch_interval_s: float = 0.0002
    display_thread_nice: int = 0
    display_thread_realtime: int = 10
    lock_memory: bool = True
    view: str = ""
    view_rate_hz: float = 40.0
    view_allowed_hosts: tuple[str, ...] = ()
    hang_timeout_s: float = 30.0

    def _check_display_timing(self) -> None:
        """The board's watchdog against the ticks and keepalives that feed it."""
        watchdog_ms = self.display_watchdog_ms
        if isinstance(watchdog_ms, bool) or not isinstance(watchdog_ms, int) \
                or not 1 <= watchdog_ms <= 0xFFFF:
            raise ConfigError("local.agent.display_watchdog_ms must be an integer in [1, 65535] "
                              f"(the board's watchdog, ms), got {watchdog_ms!r}")
        tick_ms = 1000.0 / self.render_rate_hz
        if not tick_ms <= watchdog_ms / 2:  # the ticks send the keepalives
            raise ConfigError(
                f"local.agent.render_rate_hz ({self.render_rate_hz:g} Hz: a tick every "
                f"{tick_ms:g} ms) must tick at least twice within display_watchdog_ms "
                f"({watchdog_ms}): the loop's ticks send the board's keepalive, and the board "
                "parks the pins between ticks further apart")
        feedback_s = self.display_feedback_timeout_s
        if isinstance(feedback_s, bool) or not isinstance(feedback_s, int | float) \
                or not 0 < feedback_s <= MAX_FEEDBACK_TIMEOUT_S:
            raise ConfigError(
                "local.agent.display_feedback_timeout_s must be a number in (0, "
                f"{MAX_FEEDBACK_TIMEOUT_S:g}] s (a silent drive board counts as lost after it), "
                f"got {feedback_s!r}")
        keepalive_ms = self.display_keepalive_interval_s * 1000.0
        if not keepalive_ms + tick_ms < watchdog_ms:  # a keepalive goes out on a tick
            raise ConfigError(
                f"local.agent.display_keepalive_interval_s ({keepalive_ms:g} ms) plus a tick "
                f"({tick_ms:g} ms) must be shorter than display_watchdog_ms ({watchdog_ms}): "
                "a keepalive goes out on the first tick after its interval")

    def _check_recording(self) -> None:
        """What ``--record`` hands the recorder (checked whether it records or not)."""
        check_count("local.agent.record_queue_size", self.record_queue_size)
        check_positive("local.agent.record_pins_rate_hz", self.record_pins_rate_hz)
        image = self.record_image_rate_hz
        if isinstance(image, bool) or not isinstance(image, int | float) \
                or not (image == 0 or 0 < image <= 1000):
            raise ConfigError("local.agent.record_image_rate_hz must be 0 (no images) or in "
                              f"(0, 1000], got {image!r}")

    def __post_init__(self) -> None:
        check_hang_timeout("local.agent.hang_timeout_s", self.hang_timeout_s)
        if self.safe_state not in SAFE_STATE_MODES:
            raise ConfigError(f"local.agent.safe_state must be one of {SAFE_STATE_MODES}, "
                              f"got {self.safe_state!r}")
        if self.render_loop not in RENDER_LOOP_MODES:
            raise ConfigError(f"local.agent.render_loop must be one of {RENDER_LOOP_MODES}, "
                              f"got {self.render_loop!r}")
        positive = ("link_loss_timeout_s", "stale_frame_timeout_s", "max_frame_age_s",
                    "max_offset_uncertainty_s", "platform_send_rate_hz",
                    "render_rate_hz", "platform_read_timeout_s", "device_retry_min_s",
                    "device_retry_max_s", "display_keepalive_interval_s",
                    "status_interval_s")
        for name in positive:
            check_positive(f"local.agent.{name}", getattr(self, name))
        for name in ("link_loss_timeout_s", "stale_frame_timeout_s", "max_frame_age_s"):
            if not getattr(self, name) <= MAX_SAFETY_TIMEOUT_S:
                raise ConfigError(
                    f"local.agent.{name} ({getattr(self, name):g} s) must be <= "
                    f"{MAX_SAFETY_TIMEOUT_S:g} s: it bounds how long the pins may hold a touch "
                    "that is no longer valid (docs/safety.md; a value in ms?)")
        if not self.max_offset_uncertainty_s < self.max_frame_age_s:
            raise ConfigError(
                f"local.agent.max_offset_uncertainty_s ({self.max_offset_uncertainty_s:g} s) "
                f"must be < local.agent.max_frame_age_s ({self.max_frame_age_s:g} s): a frame "
                "whose age is that uncertain is refused as stale anyway")
        if not 1.0 <= self.render_rate_hz <= 10_000.0:
            raise ConfigError("local.agent.render_rate_hz must lie in [1, 10000]")
        if not 1.0 <= self.platform_send_rate_hz <= 10_000.0:
            raise ConfigError("local.agent.platform_send_rate_hz must lie in [1, 10000]")
        self._check_display_timing()
        if not self.platform_read_timeout_s > PLATFORM_POLL_S:
            raise ConfigError(f"local.agent.platform_read_timeout_s must be > {PLATFORM_POLL_S:g} "
                              "s (the platform reader's poll), got "
                              f"{self.platform_read_timeout_s!r}")
        self._check_recording()
        if not (isinstance(self.platform_reopen_after_s, int | float)
                and not isinstance(self.platform_reopen_after_s, bool)
                and math.isfinite(self.platform_reopen_after_s)
                and self.platform_reopen_after_s >= self.platform_read_timeout_s):
            raise ConfigError("local.agent.platform_reopen_after_s must be finite and >= "
                              f"platform_read_timeout_s, got {self.platform_reopen_after_s!r}")
        own_process = self.platform_process or self.render_loop == "process"
        if own_process and not self.platform_reopen_after_s < PLATFORM_HANG_TIMEOUT_S:
            raise ConfigError(
                f"local.agent.platform_reopen_after_s must be < {PLATFORM_HANG_TIMEOUT_S:g} s "
                "with the platform read in a process of its own (platform_process, or "
                "render_loop = \"process\"; that process's hang timeout), got "
                f"{self.platform_reopen_after_s!r}")
        if self.device_retry_max_s < self.device_retry_min_s:
            raise ConfigError("local.agent.device_retry_max_s must be >= device_retry_min_s")
        if self.interpolation_order not in (0, 1, 3):
            raise ConfigError("local.agent.interpolation_order must be 0, 1 or 3")
        if not (math.isfinite(self.motion_done_grace_s) and self.motion_done_grace_s >= 0):
            raise ConfigError("local.agent.motion_done_grace_s must be >= 0")
        if not (math.isfinite(self.gil_switch_interval_s)
                and 0.0 <= self.gil_switch_interval_s <= 0.1):
            raise ConfigError("local.agent.gil_switch_interval_s must lie in [0, 0.1] s")
        if isinstance(self.display_thread_nice, bool) \
                or not isinstance(self.display_thread_nice, int) \
                or not -20 <= self.display_thread_nice <= 19:
            raise ConfigError("local.agent.display_thread_nice must be an integer in [-20, 19]")
        if isinstance(self.display_thread_realtime, bool) \
                or not isinstance(self.display_thread_realtime, int) \
                or not 0 <= self.display_thread_realtime <= 99:
            raise ConfigError("local.agent.display_thread_realtime must be an integer in "
                              "[0, 99] (a SCHED_FIFO priority; 0: off)")
        if not isinstance(self.lock_memory, bool):
            raise ConfigError(f"local.agent.lock_memory must be true or false, "
                              f"got {self.lock_memory!r}")
        if not (isinstance(self.view_rate_hz, int | float)
                and 1.0 <= self.view_rate_hz <= 120.0):
            raise ConfigError("local.agent.view_rate_hz must lie in [1, 120]")
        check_host_names("local.agent.view_allowed_hosts", self.view_allowed_hosts)
        for name in ("scene_center_x_mm", "scene_center_y_mm"):
            if not math.isfinite(getattr(self, name)):
                raise ConfigError(f"local.agent.{name} must be finite")
