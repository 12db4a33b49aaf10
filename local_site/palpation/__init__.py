"""Palpation analysis from what the local station received: tumors found, located, typed, ranked.

Only the tactile frames and platform positions that reached the local station are used: the
same information the operator had. See :mod:`local_site.palpation.maps` and
:mod:`local_site.palpation.findings` for the method.
"""

import logging

from local_site.palpation.findings import DetectionConfig, Finding, find_tumors, rank_by_severity
from local_site.palpation.lag import correct_lag, estimate_lag_mm
from local_site.palpation.maps import (
    MapConfig,
    PalpationMaps,
    build_maps,
    build_maps_at,
    pad_profile,
)
from local_site.recording import Recording, load_recording
from shared.workspace import WorkspaceMap, load_workspace

__all__ = ["DetectionConfig", "Finding", "MapConfig", "PalpationMaps", "Recording",
           "analyse_recording", "build_maps", "correct_lag", "estimate_lag_mm", "find_tumors",
           "load_recording", "maps_and_findings", "pad_profile", "rank_by_severity"]

log = logging.getLogger(__name__)


def analyse_recording(recording: Recording, workspace: WorkspaceMap | None = None,
                      map_config: MapConfig | None = None,
                      detection: DetectionConfig | None = None, *,
                      lag_correction: bool = True) -> list[Finding]:
    """Build the maps of ``recording`` and return the tumors found in them.

    With ``lag_correction`` a lag between the frames' images and their stamped positions
    is estimated from passes in opposite directions and corrected first
    (:mod:`local_site.palpation.lag`; nothing is corrected when it cannot be estimated).

    Args:
        recording: what the local station received.
        workspace: the platform <-> phantom map; by default the one the station recorded in
            its metadata (``meta["workspace"]``), else the configured default.
        map_config: map settings.
        detection: detection and typing thresholds.
        lag_correction: estimate and correct the image <-> position lag first.

    Raises:
        InputDataError: nothing was palpated.
        ConfigError: the recorded workspace settings are invalid.
    """
    if workspace is None:
        recorded = recording.meta.get("workspace")
        workspace = load_workspace(explicit=recorded if isinstance(recorded, dict) else None)
    if lag_correction:
        lag = estimate_lag_mm(recording, workspace, map_config)
        if lag is not None:
            log.info("frame positions lag their images by %.3f mm along the motion: "
                     "corrected", lag)
            recording = correct_lag(recording, lag)
    return maps_and_findings(recording, workspace, map_config, detection)[1]


def maps_and_findings(recording: Recording, workspace: WorkspaceMap,
                      map_config: MapConfig | None = None,
                      detection: DetectionConfig | None = None
                      ) -> tuple[PalpationMaps, list[Finding]]:
    """The maps of ``recording`` (no lag correction) and the tumors found in them, typed
    from a second map at ``MapConfig.typing_signal_percentile`` when it is set (the
    default, 20: see :class:`MapConfig`).

    Raises:
        InputDataError: nothing was palpated.
    """
    cfg = map_config or MapConfig()
    typing_p = cfg.typing_signal_percentile
    if typing_p is None:
        maps = build_maps(recording, workspace, cfg)
        return maps, find_tumors(maps, detection)
    maps, typing_maps = build_maps_at(recording, workspace, cfg,
                                      (cfg.signal_percentile, typing_p))
    return maps, find_tumors(maps, detection, typing_maps=typing_maps)
