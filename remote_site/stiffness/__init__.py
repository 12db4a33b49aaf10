"""Stiffness from force and indentation: contact point, robust regression, gel compensation,
loading-only streaming, a stiffness map, and the stiffness calibration fit (gel and
N/mm -> Shore 00 from reference presses; the N/mm -> k mapping is :mod:`shared.hardness`)."""

from remote_site.stiffness.calibrate import (
    PressRecord,
    fit_stiffness_calibration,
    read_presses_csv,
)
from remote_site.stiffness.estimator import (
    METHODS,
    StiffnessConfig,
    StiffnessEstimate,
    compensate_gel,
    estimate_press,
)
from remote_site.stiffness.stiffness_map import MapBounds, StiffnessMap
from remote_site.stiffness.tracker import PressResult, SegmentConfig, StiffnessTracker

__all__ = ["METHODS", "MapBounds", "PressRecord", "PressResult", "SegmentConfig",
           "StiffnessConfig", "StiffnessEstimate", "StiffnessMap", "StiffnessTracker",
           "compensate_gel", "estimate_press", "fit_stiffness_calibration", "read_presses_csv"]
