"""The local station's tactile renderer: scene layers -> 4 x 4 pin commands."""

from local_site.render.interpolation import INTERPOLATION_ORDERS, GridLayers
from local_site.render.pin_command import (
    N_COLS,
    N_ROWS,
    PIN_PITCH_MM,
    STROKE_MM,
    PinCommand,
    pin_offsets_mm,
)
from local_site.render.renderer import HEIGHT_MODES, Renderer, RendererConfig, RenderStats

__all__ = [
    "HEIGHT_MODES",
    "INTERPOLATION_ORDERS",
    "N_COLS",
    "N_ROWS",
    "PIN_PITCH_MM",
    "STROKE_MM",
    "GridLayers",
    "PinCommand",
    "RenderStats",
    "Renderer",
    "RendererConfig",
    "pin_offsets_mm",
]
