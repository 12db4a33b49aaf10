"""Photometric forward model: gel contact depth map (mm) -> GelSight-style RGB frame.

The gel surface is the contact depth smoothed by an elastic "drape" kernel (Gaussian of
``drape_sigma_mm``): real gel does not follow a sharp edge. Its unit normal ``n`` is lit by
three coloured lights at 120 degrees around the optical axis, each ``light_elevation_deg``
from the gel normal (the GelSight Mini layout). A pixel's colour is the background times
``1 + shading_gain * sum_k colour_k * (n.l_k / cos(elevation) - 1)``: flat gel reproduces the
background, tilted gel brightens towards the lights it faces. The background is a smooth gel
colour with radial vignetting and a linear illumination gradient; camera noise is Gaussian;
optional markers are dark dots on a square grid (static: the gel's lateral
shear is not modelled). Noise windows are drawn from a pre-computed pool (3 frames' worth,
random offset per frame) to keep rendering fast. ``brightness`` scales the whole frame per
channel (to emulate drift of the LEDs/exposure between the background and a press).

Conventions: depth/height positive where the object presses into the gel; x = columns,
y = rows; slopes ``dh/dx`` etc. are in mm/mm. The Taxim polynomial tables in the team kit
(``gelsight/taxim_polytables``) are *not* used: their backgrounds are missing from the
snapshot and their resolution/scale differ, so this analytic model is the default; their
conventions (normal-magnitude and direction bins, [x^2, y^2, xy, x, y, 1] coefficients,
``dzdx`` along rows) are noted in remote_site/sensor/README.md for a later table backend.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from shared.errors import InputDataError

__all__ = ["PhotometricModel", "PhotometricSettings"]


@dataclass(frozen=True)
class PhotometricSettings:
    """Optical parameters of a simulated sensor.

    Attributes:
        shape_hw: frame (rows, cols).
        mm_per_px: pixel pitch on the gel.
        gel_rgb: mean background colour at the centre (0-255).
        vignetting: relative darkening at the corners.
        illumination_tilt: relative brightness change across the frame (left to right).
        light_elevation_deg: angle of each light from the gel normal.
        light_azimuth_deg: azimuth of the first light; the others follow at +120, +240.
        light_rgb: (3 lights x 3 channels) colour mix of each light.
        shading_gain: strength of the shading relative to the background.
        drape_sigma_mm: Gaussian smoothing of the depth map by the gel.
        noise_dn: camera noise sigma in digital numbers (0 = none).
        marker_pitch_mm: marker grid pitch (0 = no markers).
        marker_radius_mm: marker dot radius.
        brightness: per-channel gain applied to the rendered frame.
    """

    shape_hw: tuple[int, int] = (240, 320)
    mm_per_px: float = 0.0634
    gel_rgb: tuple[float, float, float] = (125.0, 120.0, 85.0)
    vignetting: float = 0.25
    illumination_tilt: float = 0.08
    light_elevation_deg: float = 65.0
    light_azimuth_deg: float = 90.0
    light_rgb: tuple[tuple[float, float, float], ...] = ((1.0, 0.15, 0.1), (0.1, 1.0, 0.15),
                                                         (0.15, 0.1, 1.0))
    shading_gain: float = 0.45
    drape_sigma_mm: float = 0.08
    noise_dn: float = 1.0
    marker_pitch_mm: float = 0.0
    marker_radius_mm: float = 0.15
    brightness: tuple[float, float, float] = (1.0, 1.0, 1.0)


class PhotometricModel:
    """Renders RGB frames from depth maps (stateless apart from a seeded noise generator).

    Args:
        settings: optical parameters.
        seed: noise seed.

    Raises:
        InputDataError: implausible settings (shape, pitch).
    """

    def __init__(self, settings: PhotometricSettings | None = None, seed: int = 0) -> None:
        self.settings = s = settings or PhotometricSettings()
        rows, cols = s.shape_hw
        if rows < 8 or cols < 8 or not (np.isfinite(s.mm_per_px) and s.mm_per_px > 0):
            raise InputDataError(f"bad sensor geometry {s.shape_hw}, {s.mm_per_px} mm/px")
        self._rng = np.random.default_rng(seed)
        self._noise_pool: np.ndarray | None = None
        #: the flat gel's shading before noise (computed on the first frame without contact)
        self._flat_values: np.ndarray | None = None
        yy, xx = np.mgrid[0:rows, 0:cols].astype(np.float32)
        u = (xx + 0.5) / cols - 0.5
        v = (yy + 0.5) / rows - 0.5
        illum = (1.0 - s.vignetting * 2.0 * (u**2 + v**2)) * (1.0 + s.illumination_tilt * u)
        self._background = (illum[..., None] * np.asarray(s.gel_rgb, np.float32)).astype(np.float32)
        elev = np.deg2rad(s.light_elevation_deg)
        az = np.deg2rad(s.light_azimuth_deg + np.array([0.0, 120.0, 240.0]))
        self._lights = np.stack([np.cos(az) * np.sin(elev), np.sin(az) * np.sin(elev),
                                 np.full(3, np.cos(elev))], axis=1).astype(np.float32)
        self._cos_elev = np.float32(np.cos(elev))
        self._mix = np.asarray(s.light_rgb, np.float32)  # (light, channel)
        self._markers = np.ones((rows, cols), np.float32)
        if s.marker_pitch_mm > 0:
            pitch_px = s.marker_pitch_mm / s.mm_per_px
            du = (xx % pitch_px) - pitch_px / 2
            dv = (yy % pitch_px) - pitch_px / 2
            dot = np.hypot(du, dv) < s.marker_radius_mm / s.mm_per_px
            self._markers[dot] = 0.25
        # Static terms of the shading (see render): the lit colour is
        # A (1 + gain * sum_k mix_kc (max(n.l_k, 0) / cos(elev) - 1)) with the albedo
        # A = background * markers * brightness, i.e. A (w0 + sum_k W_k * max(n.l_k, 0)).
        gain = np.float32(s.shading_gain)
        self._albedo = np.ascontiguousarray(
            self._background * self._markers[..., None] * np.asarray(s.brightness, np.float32),
            dtype=np.float32)
        self._weights = np.ascontiguousarray(np.concatenate(
            [1.0 - gain * self._mix.sum(axis=0, keepdims=True),  # w0 per channel
             gain / self._cos_elev * self._mix]), dtype=np.float32)  # W (light, channel)

    @property
    def background_rgb(self) -> np.ndarray:
        """Noise-free no-contact frame (with markers, without brightness drift) as uint8."""
        return np.clip(np.rint(self._background * self._markers[..., None]), 0,
                       255).astype(np.uint8)

    def gel_surface_mm(self, depth_mm: np.ndarray) -> np.ndarray:
        """The gel surface actually rendered: the depth map smoothed by the drape kernel.

        Raises:
            InputDataError: wrong shape, NaN/Inf or negative depth.
        """
        surface, flat = self._surface(depth_mm)
        return surface.copy() if flat else surface  # never the caller's own array

    def _surface(self, depth_mm: np.ndarray) -> tuple[np.ndarray, bool]:
        """:meth:`gel_surface_mm`, and whether the gel is flat (no contact: all zeros)."""
        import cv2

        s = self.settings
        depth = np.asarray(depth_mm, dtype=np.float32)
        if depth.shape != s.shape_hw:
            raise InputDataError(f"depth map shape {depth.shape} != sensor {s.shape_hw}")
        if not np.isfinite(depth).all():
            raise InputDataError("depth map contains NaN or Inf")
        if depth.min() < 0:
            raise InputDataError("depth map must be >= 0 (mm into the gel)")
        if not depth.any():
            return depth, True  # the drape kernel leaves a flat gel flat
        sigma_px = s.drape_sigma_mm / s.mm_per_px
        if sigma_px > 0.1:
            depth = np.asarray(cv2.GaussianBlur(depth, (0, 0), sigma_px,
                                                borderType=cv2.BORDER_REPLICATE), np.float32)
        return depth, False

    def render(self, depth_mm: np.ndarray, noise: bool = True,
               gain: np.ndarray | None = None) -> np.ndarray:
        """Render one RGB uint8 frame from a contact depth map (mm, >= 0, sensor shape).

        ``gain`` (per channel, e.g. an LED drift) scales the 8-bit frame as
        ``cv2.multiply(frame, gain, dtype=cv2.CV_8U)`` would, in the same pass.

        Without contact (an all-zero map) the shading is the same every frame: it is
        computed once and only the frame's noise is added (:func:`finish_frame`).

        Raises:
            InputDataError: wrong shape, NaN/Inf or negative depth.
        """
        from remote_site.sensor.shading import finish_frame, shade_frame, shaded_values

        s = self.settings
        surface, flat = self._surface(depth_mm)
        camera_noise = self._noise_sample() if noise and s.noise_dn > 0 else None
        if flat:
            if self._flat_values is None:
                self._flat_values = shaded_values(self._albedo, self._weights, self._lights)
            return finish_frame(self._flat_values, camera_noise, gain)
        # Unit normal of the surface z = h(x, y), seen from the camera side:
        # (-h_x, -h_y, 1) / sqrt(1 + h_x^2 + h_y^2); one fused pass with the static terms.
        return shade_frame(surface, s.mm_per_px, self._albedo, self._weights, self._lights,
                           camera_noise, gain)

    def _noise_sample(self) -> np.ndarray:
        """Camera noise for one frame: a random window of a pre-drawn pool (fast)."""
        size = int(np.prod(self._background.shape))
        if self._noise_pool is None:
            self._noise_pool = self._rng.standard_normal(3 * size, dtype=np.float32) * np.float32(
                self.settings.noise_dn)
        start = int(self._rng.integers(0, 2 * size))
        return self._noise_pool[start:start + size].reshape(self._background.shape)
