"""The local haptic station agent (``teletouch local``).

It composes the existing parts of the station: the XYZ platform (read in its own thread),
the relay link (:class:`shared.client.StationLink`), a scene (the remote tactile stream or a
local shape / layer file), the renderer and the ArrayTac display (driven by the display loop
at the array refresh rate), plus the safety rules (safe state on link loss, stale scene or a
lost platform) and the recording of what was felt.

Modules:
    config          :class:`LocalAgentConfig`, TOML table ``[local.agent]``
    period_stats    loop-period statistics (ring buffer, percentiles)
    platform_reader the platform read thread with retry and backoff
    display_loop    frame intake, safety, render and display, run in a thread or a task
    station         :class:`LocalAgent`: the asyncio orchestration and the summary
"""

from local_site.agent.config import LocalAgentConfig
from local_site.agent.station import LocalAgent

__all__ = ["LocalAgent", "LocalAgentConfig"]
