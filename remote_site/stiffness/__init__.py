"""Stiffness from force and indentation: contact point, robust regression, gel compensation,
loading-only streaming, a stiffness map, and the N/mm -> Shore 00 -> k conversion."""

from remote_site.stiffness.estimator import (
    METHODS,
    StiffnessConfig,
    StiffnessEstimate,
    compensate_gel,
    estimate_press,
)
from remote_site.stiffness.shore import ShoreConversion, durometer_modulus_kpa
from remote_site.stiffness.stiffness_map import MapBounds, StiffnessMap
from remote_site.stiffness.tracker import PressResult, SegmentConfig, StiffnessTracker

__all__ = ["METHODS", "MapBounds", "PressResult", "SegmentConfig", "ShoreConversion",
           "StiffnessConfig", "StiffnessEstimate", "StiffnessMap", "StiffnessTracker",
           "compensate_gel", "durometer_modulus_kpa", "estimate_press"]
