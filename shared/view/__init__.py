"""The live view in the browser: one static page, one WebSocket server, one snapshot protocol.

The local station (``teletouch local --view HOST:PORT``) serves it, and the relay can serve the
same page to a session's observers. What a station shows is given by a :class:`ViewSource`;
:class:`ViewServer` samples it at a bounded rate into a latest-wins slot and sends each
browser the newest snapshot when that browser is ready for it (slow browsers skip snapshots,
they never hold the station back). See ``docs/view.md``.
"""

from shared.view.server import (
    PAGE_FILES,
    ViewAddress,
    ViewServer,
    ViewServerConfig,
    ViewSource,
    parse_view_address,
)

__all__ = ["PAGE_FILES", "ViewAddress", "ViewServer", "ViewServerConfig", "ViewSource",
           "parse_view_address"]
