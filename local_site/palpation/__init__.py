"""Palpation analysis from what the local station received: tumors found, located, typed, ranked.

Only the tactile frames and platform positions that reached the local station are used: the
same information the operator had. See :mod:`local_site.palpation.maps` and
:mod:`local_site.palpation.findings` for the method.
"""

from local_site.palpation.findings import DetectionConfig, Finding, find_tumors
from local_site.palpation.maps import MapConfig, PalpationMaps, build_maps, pad_profile
from local_site.recording import Recording, load_recording
from shared.workspace import WorkspaceMap, load_workspace

__all__ = ["DetectionConfig", "Finding", "MapConfig", "PalpationMaps", "Recording",
           "analyse_recording", "build_maps", "find_tumors", "load_recording", "pad_profile"]


def analyse_recording(recording: Recording, workspace: WorkspaceMap | None = None,
                      map_config: MapConfig | None = None,
                      detection: DetectionConfig | None = None) -> list[Finding]:
    """Build the maps of ``recording`` and return the tumors found in them.

    Args:
        recording: what the local station received.
        workspace: the platform <-> phantom map; by default the one the station recorded in
            its metadata (``meta["workspace"]``), else the configured default.
        map_config: map settings.
        detection: detection and typing thresholds.

    Raises:
        InputDataError: nothing was palpated.
        ConfigError: the recorded workspace settings are invalid.
    """
    if workspace is None:
        recorded = recording.meta.get("workspace")
        workspace = load_workspace(explicit=recorded if isinstance(recorded, dict) else None)
    return find_tumors(build_maps(recording, workspace, map_config), detection)
