"""The local station's live view: what it shows (:class:`StationView`) and its analysis.

The page and the server are shared with the relay (:mod:`shared.view`); this package reads
the running :class:`~local_site.agent.station.LocalAgent` and runs the palpation analysis in
a child process (:mod:`local_site.view.analysis`).
"""

from local_site.view.analysis import LiveAnalysis, LiveAnalysisConfig, encode_map
from local_site.view.station_view import StationView

__all__ = ["LiveAnalysis", "LiveAnalysisConfig", "StationView", "encode_map"]
