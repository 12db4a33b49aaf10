"""The simulated world of the remote station (simulator code): a phantom for sim backends.

With ``--phantom SCENE|FILE.toml --seed N`` the sim arm feels that phantom (force at every
1 kHz step) and the sim sensor renders that phantom's gel contact depth map at the arm's
current pose. The station reaches this module only by name, through
:data:`remote_site.agent.devices.WORLDS` (``"phantom"`` -> :func:`build_world`), and uses
the world through the :class:`remote_site.agent.devices.World` protocol: product code never
imports it.

**Realistic by default.** Unless ``--ideal`` is given the world is imperfect, at the levels
of :data:`REALISTIC` (each with its source or, where nothing could be measured here, marked
as an assumption):

* a per-session **registration error** between the arm's frame and the phantom: the phantom
  lies shifted and turned from where the station's workspace map says, drawn once per
  session from the seed and never told to the station (:class:`Registration`);
* the arm's **force reading** with white noise, a residual bias after taring and a drift;
* the arm's **reported position** with noise around the true pad position;
* the sensor's **camera noise** and a slow per-channel **LED brightness drift**;
* a **strain-stiffening** (non-linear) tissue layer when the phantom file gives a linear one.

``--ideal`` (:data:`IDEAL`) keeps the noise-free, perfectly registered, linear world.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from remote_site.arm.base import Arm
from remote_site.arm.sim import ArmNoise
from remote_site.phantom.phantom import Phantom, PixelGrid
from remote_site.phantom.phantom_file import resolve_phantom
from remote_site.sensor.base import TactileSensor
from remote_site.sensor.photometric import PhotometricSettings
from shared.errors import ConfigError

__all__ = ["IDEAL", "REALISTIC", "Realism", "Registration", "SimWorld", "build_world",
           "world_for"]


@dataclass(frozen=True)
class Realism:
    """How imperfect the simulated world is (0 everywhere: :data:`IDEAL`).

    Attributes:
        registration_mm: standard deviation of the phantom's shift per axis (x, y).
        registration_deg: standard deviation of its rotation about z.
        registration_z_mm: standard deviation of the surface height error.
        force_noise_n: white noise of the force reading (per 1 kHz sample).
        force_bias_n: standard deviation of the per-session residual force offset.
        force_drift_n_per_min: standard deviation of the per-session force drift rate.
        position_noise_mm: noise of the arm's reported position.
        camera_noise_dn: camera noise sigma (8-bit digital numbers).
        led_drift_per_min: standard deviation of each LED channel's brightness drift rate.
        tissue_nonlinearity: strain stiffening given to a layer the file leaves linear.
    """

    registration_mm: float = 0.0
    registration_deg: float = 0.0
    registration_z_mm: float = 0.0
    force_noise_n: float = 0.0
    force_bias_n: float = 0.0
    force_drift_n_per_min: float = 0.0
    position_noise_mm: float = 0.0
    camera_noise_dn: float = 0.0
    led_drift_per_min: float = 0.0
    tissue_nonlinearity: float = 0.0

    def __post_init__(self) -> None:
        for name, value in self.__dict__.items():
            if not (math.isfinite(value) and value >= 0):
                raise ConfigError(f"realism {name} must be finite and >= 0, got {value!r}")

    def scaled(self, factor: float) -> Realism:
        """Every noise level times ``factor`` (registration and tissue included)."""
        return Realism(**{k: v * factor for k, v in self.__dict__.items()})


#: the noise-free world (``--ideal``): perfect registration, force and position; the camera
#: keeps the simulator's 1 DN noise it always had
IDEAL = Realism(camera_noise_dn=1.0)

#: the default simulated world; every level with its source
REALISTIC = Realism(
    # The issue's own outside-evaluator figure for a phantom placed by hand on the table
    # and registered by eye: 1-3 mm and 2-5 degrees. sigma 1.5 mm per axis (mean 1.9 mm)
    # and 3 degrees spans it.
    registration_mm=1.5, registration_deg=3.0,
    # the surface height is found by touching; 0.2 mm is the press-detection threshold
    registration_z_mm=0.2,
    # ASSUMED (no data here): a Franka-class arm's external-force estimate from joint torques,
    # after taring at the start of the session: noise 0.1 N rms per sample, residual offset
    # 0.1 N, drift 0.05 N/min (joint-torque sensors warm up). A wrist F/T sensor would be
    # about 10x better.
    force_noise_n=0.1, force_bias_n=0.1, force_drift_n_per_min=0.05,
    # Franka datasheet: pose repeatability +-0.1 mm
    position_noise_mm=0.1,
    # MEASURED on the shipped GelSight Mini presses (data/gelsight/gsmini_ball_9.47mm):
    # high-pass residual of single frames against the 10-frame mean background, away from
    # the contact: 2.2 DN median over 20 frames, i.e. about 2.1 DN per frame.
    camera_noise_dn=2.1,
    # Same data: the press frames' flat areas sit 0-1 DN (up to ~1.2 % in blue) off the
    # background taken at the start of the calibration session. ASSUMED session of ~10 min:
    # 0.1 %/min per channel.
    led_drift_per_min=0.001,
    # Silicone phantoms and breast tissue stiffen with strain (Samani & Plewes 2004: tangent
    # modulus 2-4x higher at 20 % strain); beta = 1.5 raises the secant stiffness by 22 %
    # at a 3 mm press into 20 mm.
    tissue_nonlinearity=1.5,
)


@dataclass(frozen=True)
class Registration:
    """Where the phantom really is relative to the arm's (believed) phantom frame.

    ``p_phantom = R(yaw) (p_arm - 0) + (dx, dy, dz)`` about the frame origin.
    """

    dx_mm: float = 0.0
    dy_mm: float = 0.0
    dz_mm: float = 0.0
    yaw_deg: float = 0.0

    @classmethod
    def draw(cls, realism: Realism, seed: int) -> Registration:
        """The session's unknown error, drawn from ``seed``."""
        rng = np.random.default_rng([seed, 0x5E55])
        dx, dy = rng.normal(0.0, realism.registration_mm, 2)
        dz = rng.normal(0.0, realism.registration_z_mm)
        yaw = rng.normal(0.0, realism.registration_deg)
        return cls(float(dx), float(dy), float(dz), float(yaw))

    def to_phantom(self, position_mm: Sequence[float]) -> tuple[float, float, float]:
        """An arm-frame position in the true phantom frame."""
        x, y, z = (float(v) for v in position_mm)
        c, s = math.cos(math.radians(self.yaw_deg)), math.sin(math.radians(self.yaw_deg))
        return c * x - s * y + self.dx_mm, s * x + c * y + self.dy_mm, z + self.dz_mm

    def to_dict(self) -> dict[str, float]:
        """Plain JSON."""
        return dict(self.__dict__)


@dataclass
class _RegisteredPhantom:
    """The phantom as the arm feels it: arm-frame poses go through the registration."""

    phantom: Phantom
    registration: Registration

    def force_n(self, position_mm: Sequence[float]) -> float:
        return self.phantom.force_n(self.registration.to_phantom(position_mm))


@dataclass
class SimWorld:
    """The simulated scene simulated backends act on.

    Attributes:
        phantom: the phantom pressed by the sim arm and seen by the sim sensor.
        realism: the noise levels (:data:`IDEAL` for a perfect world).
        registration: the session's arm -> phantom error (identity when ideal).
        seed: the session seed (noise draws).
    """

    phantom: Phantom
    realism: Realism = IDEAL
    registration: Registration = Registration()
    seed: int = 0

    def true_pose(self, arm_position_mm: Sequence[float]) -> tuple[float, float, float]:
        """Where the pad really is on the phantom for an arm-frame position."""
        return self.registration.to_phantom(arm_position_mm)

    def depth_provider(self, arm: Arm, grid: Callable[[], PixelGrid],
                       true_position: Callable[[], Sequence[float]] | None = None
                       ) -> Callable[[], np.ndarray]:
        """A sensor depth provider: the phantom's contact depth map at the arm's pose.

        ``true_position`` gives the arm's true (not reported) position when known; the
        reported one (which carries the position noise) otherwise.
        """
        where = true_position or (lambda: arm.state().position_mm)

        def provide() -> np.ndarray:
            pose = self.true_pose(where())
            contact = self.phantom.contact(pose, grid())
            depth = contact.depth_map_mm
            # without contact the map is all zeros, and so is its rotation
            if self.registration.yaw_deg and contact.in_contact:
                depth = _rotate(depth, self.registration.yaw_deg)
            return depth

        return provide

    def arm_noise(self) -> ArmNoise:
        """The sim arm's sensing noise for this session (bias and drift drawn from the seed)."""
        r = self.realism
        rng = np.random.default_rng([self.seed, 0xA53])
        return ArmNoise(force_noise_n=r.force_noise_n,
                        force_bias_n=float(rng.normal(0.0, r.force_bias_n)),
                        force_drift_n_per_min=float(rng.normal(0.0, r.force_drift_n_per_min)),
                        position_noise_mm=r.position_noise_mm)

    def arm_options(self) -> dict[str, Any]:
        """The sim arm presses the (mis-registered) phantom with this session's noise."""
        options: dict[str, Any] = {"phantom": self.phantom}
        if self.registration != Registration():
            options["phantom"] = _RegisteredPhantom(self.phantom, self.registration)
        if self.arm_noise() != ArmNoise():
            options["noise"] = self.arm_noise()
        return options

    def sensor_settings(self) -> PhotometricSettings:
        """The camera's optical settings with this world's noise."""
        return replace(PhotometricSettings(), noise_dn=self.realism.camera_noise_dn)

    def sensor_options(self, arm: Arm,
                       sensor: Callable[[], TactileSensor]) -> dict[str, Any]:
        """The sim sensor renders the phantom's contact at ``arm``'s pose."""

        def grid() -> PixelGrid:
            built = sensor()
            return PixelGrid(width_px=built.shape_hw[1], height_px=built.shape_hw[0],
                             mm_per_px=built.mm_per_px)

        true_position = getattr(arm, "true_position_mm", None)
        options: dict[str, Any] = {
            "depth_provider": self.depth_provider(arm, grid, true_position)}
        if self.realism != IDEAL:
            options.update(settings=self.sensor_settings(), seed=self.seed,
                           led_drift_per_min=self.realism.led_drift_per_min,
                           clock_s=lambda: arm.state().t_s)
        return options

    def prepare_sensor(self, sensor: TactileSensor) -> None:
        """Build the contact table now, not on the first pressed frame."""
        self.phantom.modulus_table(sensor.mm_per_px)

    def describe(self) -> dict[str, Any]:
        """The world's hidden truth for the evaluation (never sent to a station)."""
        return {"realism": dict(self.realism.__dict__),
                "registration": self.registration.to_dict(),
                "arm_noise": dict(self.arm_noise().__dict__)}


def _rotate(depth: np.ndarray, yaw_deg: float) -> np.ndarray:
    """The depth map seen by a sensor turned by ``yaw_deg`` against the phantom.

    The sensor's pixel rows and columns follow the arm's frame, the phantom's tumors the
    phantom's: the contact image turns by the yaw about its centre.
    """
    import cv2

    rows, cols = depth.shape
    m = cv2.getRotationMatrix2D(((cols - 1) / 2.0, (rows - 1) / 2.0), yaw_deg, 1.0)
    out = cv2.warpAffine(depth, m, (cols, rows), flags=cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE)
    return np.maximum(np.asarray(out, np.float32), 0.0)


def build_world(scene: str, seed: int = 0, *, ideal: bool = False,
                realism: Realism | None = None) -> SimWorld:
    """The simulated world for ``--phantom SCENE|FILE.toml --seed N`` (``--ideal``).

    Args:
        scene: a shipped scene name or a phantom file.
        seed: the phantom's placement seed and the session's noise seed.
        ideal: the noise-free world (:data:`IDEAL`).
        realism: explicit noise levels (overrides ``ideal``).

    Raises:
        ConfigError: an unknown scene name, or an unreadable or invalid phantom file.
    """
    level = realism if realism is not None else (IDEAL if ideal else REALISTIC)
    return world_for(resolve_phantom(scene, seed), level, seed)


def world_for(phantom: Phantom, realism: Realism, seed: int,
              registration: Registration | None = None) -> SimWorld:
    """A world around ``phantom``: the realism's tissue stiffening (for a linear layer) and
    the session's registration error (drawn from ``seed`` unless given)."""
    if realism.tissue_nonlinearity > 0 and phantom.layer.nonlinearity == 0:
        phantom = replace(phantom, layer=replace(phantom.layer,
                                                 nonlinearity=realism.tissue_nonlinearity))
    if registration is None:
        registration = Registration.draw(realism, seed)
    return SimWorld(phantom, realism, registration, seed)
