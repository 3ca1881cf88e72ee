"""Realism profiles of the embedded world: what a real depth camera, odometry and autopilot do.

A :class:`RealismProfile` is a world setting (never a pilot setting), chosen by name in the
benchmark config (``[world] realism = "ideal" | "realistic" | "realistic_calm"``):

- ``ideal``: today's world, bit for bit: exact depth everywhere but the sky, exact odometry,
  the vehicle follows every plan with the PD law of :mod:`onfly.world.vehicle`, every frame
  arrives at once.
- ``realistic``: an Intel RealSense D435 depth camera, a LiDAR-inertial odometry and a PX4
  multicopter position controller in gusty air (figures and sources in ``docs/realism.md``;
  each model's docstring names its source).
- ``realistic_calm``: ``realistic`` in still air, to tell the gusts' share of a result from the
  sensors' and the controller's.

Every random draw comes from ``numpy.random.default_rng([seed, stream, key])`` with the
episode seed, a fixed stream id per model and a per-draw key (frame index, step index), so
each figure is reproducible and independent of the others' draw order.

The pilot sees estimates (odometry pose, delayed and dropped frames); collisions, metrics and
the out-of-bounds check use the truth (:class:`onfly.world.world.World`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from onfly.world.scene import MATERIALS

__all__ = [
    "RealismError",
    "DepthModel",
    "OdometryModel",
    "ControllerModel",
    "WindModel",
    "FrameModel",
    "RealismProfile",
    "PROFILES",
    "realism_profile",
    "OdometryDrift",
    "GustProcess",
    "STREAM_DEPTH",
    "STREAM_ODOMETRY",
    "STREAM_WIND",
    "STREAM_FRAMES",
]

#: Stream ids of the seeded draws (``default_rng([seed, stream, key])``).
STREAM_DEPTH = 0xD435
STREAM_ODOMETRY = 0x0D0
STREAM_WIND = 0x3D1
STREAM_FRAMES = 0xF4A


class RealismError(ValueError):
    """An unknown profile name or an invalid realism parameter."""


def _check_nonneg(obj, *names: str) -> None:
    for name in names:
        v = getattr(obj, name)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
            raise RealismError(f"{type(obj).__name__}.{name} must be finite and >= 0, got {v!r}")


# -- depth ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class DepthModel:
    """Depth errors of an active stereo camera (Intel RealSense D435 at 848 x 480, its optimal
    depth resolution per Intel's tuning white paper).

    - **Noise**: Gaussian, RMS ``z^2 * subpixel / (focal_px * baseline_m)`` (the stereo RMS
      error formula of Intel's "Tuning depth cameras for best performance"): with the D435's
      50 mm baseline, 90 deg HFOV at 848 px (focal 424 px) and a subpixel of 0.08, 1.5 cm at
      2 m (0.75 %, inside the datasheet's "< 2 % at 2 m"), 9.4 cm at 5 m.
    - **Range**: no reading nearer than ``min_range_m`` (MinZ = focal_px * baseline / 126 px of
      disparity search = 0.17 m at 848 x 480) or farther than ``max_range_m`` (10 m, the
      datasheet's range).
    - **Flying pixels**: at a depth edge (neighbouring readings differing by more than
      ``edge_jump_ratio`` of the nearer one) the far-side pixel reads a depth between the two
      surfaces (``near + u * (far - near)``, ``u`` uniform), the mixed-pixel artefact of depth
      cameras at object boundaries.
    - **Materials**: pixels whose surface material is in ``no_reading_materials`` read 0 (no
      reading): glass (transparent), mirror (specular) and dark (low infrared albedo) surfaces,
      where the D4xx's matcher finds no texture (Sensors 2022, 22(19), 7378).
    - **Stereo non-overlap** (``stereo_shadows``): depth is matched with the left imager as the
      reference, so a pixel whose surface the right imager (``baseline_m`` to its right) does
      not see reads nothing. That is the datasheet's *invalid depth band* down the left edge of
      the image (``focal_px * baseline_m / z`` pixels wide: 21 px of 848 at 1 m) and the same
      shadow down the left side of every nearer object (Intel RealSense D400 Series datasheet,
      "Invalid Depth Band": "the left imager as the reference for stereo matching resulting in
      a non-overlap region ... we will not have depth data"; the occlusion geometry of Intel's
      *Projection, Texture-Mapping and Occlusion with Intel RealSense Depth Cameras*).
    - **Dropout**: independent per-pixel no-reading probability ``dropout_prob``.
    """

    subpixel: float = 0.08
    baseline_m: float = 0.050
    focal_px: float = 424.0
    min_range_m: float = 0.17
    max_range_m: float = 10.0
    edge_jump_ratio: float = 0.05
    dropout_prob: float = 0.0
    no_reading_materials: tuple[str, ...] = ("glass", "mirror", "dark")
    stereo_shadows: bool = True

    def __post_init__(self) -> None:
        _check_nonneg(self, "subpixel", "min_range_m", "edge_jump_ratio", "dropout_prob")
        for name in ("baseline_m", "focal_px", "max_range_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise RealismError(f"DepthModel.{name} must be positive and finite, got {v!r}")
        if self.max_range_m <= self.min_range_m:
            raise RealismError(f"DepthModel.max_range_m must exceed min_range_m, got {self.max_range_m} <= {self.min_range_m}")
        if not self.dropout_prob < 1.0:
            raise RealismError(f"DepthModel.dropout_prob must be < 1, got {self.dropout_prob}")
        bad = [m for m in self.no_reading_materials if m not in MATERIALS]
        if bad:
            raise RealismError(f"DepthModel.no_reading_materials: unknown material(s) {bad}; known: {list(MATERIALS)}")

    @property
    def sigma_per_m(self) -> float:
        """Quadratic RMS coefficient, 1/m: ``sigma(z) = sigma_per_m * z^2``."""
        return self.subpixel / (self.focal_px * self.baseline_m)

    def sigma_m(self, z_m) -> np.ndarray:
        """RMS depth error (metres) at z-depth ``z_m`` (metres), same shape."""
        z = np.asarray(z_m, dtype=float)
        return self.sigma_per_m * z * z

    def no_reading_codes(self) -> np.ndarray:
        """uint8 codes (indices in MATERIALS) of the materials that give no reading."""
        return np.array([MATERIALS.index(m) for m in self.no_reading_materials], dtype=np.uint8)

    def right_imager_sees(self, depth_m: np.ndarray, fx_px: float) -> np.ndarray:
        """bool (H, W): the pixels of a left-imager z-depth image whose surface the right
        imager sees too (rectified pair, right imager ``baseline_m`` along the camera's +x).

        A surface at column ``u`` and depth ``z`` lies at column ``u - fx_px * baseline_m / z``
        of the right image; it is seen there when that column is inside the image and left of
        every surface to its right in the same row (visible surfaces keep their order along an
        epipolar line; one that falls behind another's right-image column is hidden by it).
        Pixels with nothing hit (``depth_m`` 0) are at infinity: disparity 0, never in the way.

        Parameters
        ----------
        depth_m : float (H, W), exact z-depth in metres, 0 = nothing hit
        fx_px : focal length of that image, pixels (the disparity's scale at its resolution)
        """
        z = np.asarray(depth_m, dtype=np.float32)
        disparity = np.zeros_like(z)
        hit = z > 0
        disparity[hit] = np.float32(fx_px * self.baseline_m) / z[hit]
        u_right = np.arange(z.shape[1], dtype=np.float32)[None, :] - disparity
        # smallest right-image column of the surfaces strictly to the right of each pixel
        beyond = np.full_like(u_right, np.inf)
        beyond[:, :-1] = np.minimum.accumulate(u_right[:, :0:-1], axis=1)[:, ::-1]
        return (u_right > -0.5) & (u_right < beyond)

    def apply(self, depth_m: np.ndarray, material: np.ndarray | None, rng: np.random.Generator,
              fx_px: float | None = None) -> np.ndarray:
        """The sensor's reading of an exact z-depth image.

        Parameters
        ----------
        depth_m : float32 (H, W), exact z-depth in metres, 0 = nothing hit
        material : uint8 (H, W), material code per pixel (index in MATERIALS), or None
        rng : the frame's generator
        fx_px : the image's focal length, pixels; needed for the stereo non-overlap
            (``stereo_shadows``), which is left out without it

        Returns
        -------
        float32 (H, W), metres, 0 = no reading
        """
        z = np.asarray(depth_m, dtype=np.float32)
        valid = z > 0
        if self.stereo_shadows and fx_px is not None:
            valid &= self.right_imager_sees(z, fx_px)
        if material is not None and len(self.no_reading_materials):
            reads = np.ones(len(MATERIALS), dtype=bool)
            reads[self.no_reading_codes()] = False
            valid &= np.take(reads, material)
        z = np.where(valid, z, np.float32(0.0))
        out = z.copy()
        if self.edge_jump_ratio > 0:
            self._flying_pixels(z, valid, out, rng)
        noise = rng.standard_normal(z.shape, dtype=np.float32)
        out += noise * np.float32(self.sigma_per_m) * z * z
        # the range gate reads the true depth: a surface nearer than MinZ gives no reading
        keep = valid & (z >= self.min_range_m) & (z <= self.max_range_m) & (out > 0)
        if self.dropout_prob > 0:
            keep &= rng.random(z.shape, dtype=np.float32) >= self.dropout_prob
        out[~keep] = 0.0
        return out

    def _flying_pixels(self, z: np.ndarray, valid: np.ndarray, out: np.ndarray, rng: np.random.Generator) -> None:
        """Replace, in ``out``, the far-side pixel of each depth edge by a mixed depth."""
        mix = rng.random(z.shape, dtype=np.float32)
        for axis in (0, 1):
            a = z[:-1, :] if axis == 0 else z[:, :-1]
            b = z[1:, :] if axis == 0 else z[:, 1:]
            va = valid[:-1, :] if axis == 0 else valid[:, :-1]
            vb = valid[1:, :] if axis == 0 else valid[:, 1:]
            near = np.minimum(a, b)
            far = np.maximum(a, b)
            edge = va & vb & ((far - near) > self.edge_jump_ratio * near)
            if not edge.any():
                continue
            i, j = np.nonzero(edge)
            b_far = b[i, j] >= a[i, j]
            # the far-side pixel of the pair
            fi = np.where(b_far, i + (axis == 0), i)
            fj = np.where(b_far, j + (axis == 1), j)
            n, f = near[i, j], far[i, j]
            out[fi, fj] = n + mix[fi, fj] * (f - n)


# -- odometry -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class OdometryModel:
    """Pose estimate of a LiDAR-inertial odometry (LIO) without loop closure.

    - **Drift**: ``drift_fraction`` of the distance flown, along one random unit direction per
      episode (LIO error grows with the path: state-of-the-art LIO reports 0.22 % relative
      translation error on long drives, more in degenerate corridors; 1 % is our conservative
      figure for a small-FoV LiDAR on a quadrotor, docs/realism.md).
    - **Noise**: white Gaussian position noise ``noise_m`` per axis and yaw noise
      ``yaw_noise_rad`` on every pose the pilot reads (centimetre-level LiDAR registration).
    """

    drift_fraction: float = 0.01
    noise_m: float = 0.02
    yaw_noise_rad: float = 0.0035

    def __post_init__(self) -> None:
        _check_nonneg(self, "drift_fraction", "noise_m", "yaw_noise_rad")


class OdometryDrift:
    """Stateful drift of one episode: the offset estimate - truth grows with the path length.

    ``direction`` (3,) is a unit vector drawn once from the seed; :meth:`advance` adds the
    length of a swept path; :attr:`offset_m` is ``drift_fraction * distance * direction``.
    """

    def __init__(self, model: OdometryModel, seed: int, start_m: np.ndarray) -> None:
        self.model = model
        self.seed = int(seed)
        d = np.random.default_rng([self.seed, STREAM_ODOMETRY, 0]).standard_normal(3)
        self.direction = d / np.linalg.norm(d)
        self.distance_m = 0.0
        self._last = np.asarray(start_m, dtype=float).copy()

    def advance(self, positions_m: np.ndarray) -> None:
        """Add the length of the polyline from the last position through ``positions_m`` (k, 3)."""
        P = np.vstack([self._last[None], np.asarray(positions_m, dtype=float)])
        self.distance_m += float(np.linalg.norm(np.diff(P, axis=0), axis=1).sum())
        self._last = P[-1].copy()

    @property
    def offset_m(self) -> np.ndarray:
        """Slow drift of the estimate, (3,) metres, world ENU (estimate = truth + offset)."""
        return self.model.drift_fraction * self.distance_m * self.direction

    def noise(self, key: int) -> tuple[np.ndarray, float]:
        """White position noise (3,) metres and yaw noise (rad) of the read with key ``key``."""
        rng = np.random.default_rng([self.seed, STREAM_ODOMETRY, 1, int(key)])
        n = rng.standard_normal(4)
        return n[:3] * self.model.noise_m, float(n[3] * self.model.yaw_noise_rad)


# -- vehicle ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ControllerModel:
    """PX4 multicopter position controller (``mc_pos_control``) in its default tuning.

    Cascade: ``v_sp = v_ref + K_pos (p_ref - p_est)``, ``e = v_sp - v``,
    ``a_sp = a_ref + K_vel e + K_int integral(e)``, clipped to ``accel_limit_mps2``; the
    vehicle's acceleration follows ``a_sp`` through a first-order lag ``tau_s`` (the attitude
    loop: 1 / MC_ROLL_P = 1 / 6.5 s). Gains are PX4's defaults: MPC_XY_P 0.95,
    MPC_XY_VEL_P_ACC 1.8, MPC_XY_VEL_I_ACC 0.4, MPC_Z_P 1.0, MPC_Z_VEL_P_ACC 4.0,
    MPC_Z_VEL_I_ACC 2.0 (the velocity-loop derivative terms are left out).
    The position feedback uses the odometry estimate, so drift moves the executed path.
    ``accel_limit_mps2`` is ``g tan(MPC_TILTMAX_AIR = 45 deg)``.
    """

    k_pos_xy_per_s: float = 0.95
    k_vel_xy_per_s: float = 1.8
    k_pos_z_per_s: float = 1.0
    k_vel_z_per_s: float = 4.0
    k_int_xy_per_s2: float = 0.4
    k_int_z_per_s2: float = 2.0
    tau_s: float = 1.0 / 6.5
    accel_limit_mps2: float = 9.81

    def __post_init__(self) -> None:
        _check_nonneg(self, "k_pos_xy_per_s", "k_vel_xy_per_s", "k_pos_z_per_s", "k_vel_z_per_s", "k_int_xy_per_s2",
                      "k_int_z_per_s2", "tau_s")
        if not (math.isfinite(self.accel_limit_mps2) and self.accel_limit_mps2 > 0):
            raise RealismError(f"ControllerModel.accel_limit_mps2 must be positive, got {self.accel_limit_mps2!r}")

    @property
    def k_pos(self) -> np.ndarray:
        return np.array([self.k_pos_xy_per_s, self.k_pos_xy_per_s, self.k_pos_z_per_s])

    @property
    def k_vel(self) -> np.ndarray:
        return np.array([self.k_vel_xy_per_s, self.k_vel_xy_per_s, self.k_vel_z_per_s])

    @property
    def k_int(self) -> np.ndarray:
        return np.array([self.k_int_xy_per_s2, self.k_int_xy_per_s2, self.k_int_z_per_s2])


@dataclass(frozen=True)
class WindModel:
    """Gusts: the Dryden turbulence of MIL-F-8785C at low altitude, as a first-order
    Gauss-Markov (coloured-noise) velocity per axis, pushing the vehicle through rotor drag.

    Low-altitude Dryden (altitude ``h`` in feet): ``sigma_w = 0.1 W20``,
    ``sigma_u = sigma_v = sigma_w / (0.177 + 0.000823 h)^0.4``, ``L_w = h``,
    ``L_u = L_v = h / (0.177 + 0.000823 h)^1.2``; a frozen field carried past the drone by the
    mean wind ``W(h) = W20 ln(h / 0.15) / ln(20 / 0.15)`` gives correlation times ``L / W``.
    ``W20`` (wind speed at 20 ft) 7.7 m/s (15 kt) is the standard's *light* turbulence.
    The gust acceleration is ``drag_per_s * w`` (linear rotor drag of a 0.5 kg quadrotor:
    4 k_d omega_hover / m = 0.45 1/s with RotorPy's AscTec Hummingbird parameters). The mean
    wind itself is left to the controller's integrator (not modelled: zero-mean gusts only).
    """

    sigma_xy_mps: float = 1.52
    sigma_z_mps: float = 0.77
    tau_xy_s: float = 2.1
    tau_z_s: float = 0.27
    drag_per_s: float = 0.45

    def __post_init__(self) -> None:
        _check_nonneg(self, "sigma_xy_mps", "sigma_z_mps", "drag_per_s")
        for name in ("tau_xy_s", "tau_z_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise RealismError(f"WindModel.{name} must be positive, got {v!r}")

    @classmethod
    def dryden(cls, w20_mps: float, altitude_m: float, drag_per_s: float = 0.45) -> "WindModel":
        """The low-altitude Dryden figures for wind ``w20_mps`` at 20 ft and ``altitude_m``."""
        h_ft = max(float(altitude_m) / 0.3048, 1.0)
        sigma_w = 0.1 * w20_mps
        base = 0.177 + 0.000823 * h_ft
        sigma_u = sigma_w / base**0.4
        L_u_m = h_ft / base**1.2 * 0.3048
        L_w_m = h_ft * 0.3048
        mean_mps = w20_mps * math.log(h_ft / 0.15) / math.log(20.0 / 0.15)
        return cls(sigma_u, sigma_w, L_u_m / mean_mps, L_w_m / mean_mps, drag_per_s)


class GustProcess:
    """Seeded gust velocity (3,) m/s: per axis ``w' = -w / tau + sigma sqrt(2 / tau) n(t)``,
    sampled exactly at any step ``h`` (``w <- a w + sigma sqrt(1 - a^2) n``, ``a = e^{-h/tau}``),
    starting from its stationary distribution."""

    def __init__(self, model: WindModel, seed: int) -> None:
        self.model = model
        self._rng = np.random.default_rng([int(seed), STREAM_WIND])
        self._sigma = np.array([model.sigma_xy_mps, model.sigma_xy_mps, model.sigma_z_mps])
        self._tau = np.array([model.tau_xy_s, model.tau_xy_s, model.tau_z_s])
        self.w_mps = self._sigma * self._rng.standard_normal(3)

    def step(self, h_s: float) -> np.ndarray:
        """Advance by ``h_s`` seconds; returns the new gust velocity (3,) m/s."""
        a = np.exp(-h_s / self._tau)
        self.w_mps = a * self.w_mps + self._sigma * np.sqrt(1.0 - a * a) * self._rng.standard_normal(3)
        return self.w_mps

    def acceleration(self) -> np.ndarray:
        """Gust acceleration (3,) m/s^2 on the vehicle (rotor drag times gust velocity)."""
        return self.model.drag_per_s * self.w_mps


# -- frames -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FrameModel:
    """Camera frame delivery: each frame is lost with ``drop_prob`` and otherwise arrives
    ``latency`` seconds after capture, uniform in ``[latency_min_s, latency_max_s]``.

    Latency: Intel measured 60-70 ms for D400 depth streams (librealsense issue #1242); users
    measured 85-133 ms at 30 fps with the SDK's latency tool (issue #4955). Drops: the D435 on
    a Jetson drops frames under load (issues #12551, #1730); 5 % is our figure.
    """

    drop_prob: float = 0.05
    latency_min_s: float = 0.060
    latency_max_s: float = 0.133

    def __post_init__(self) -> None:
        _check_nonneg(self, "drop_prob", "latency_min_s", "latency_max_s")
        if not self.drop_prob < 1.0:
            raise RealismError(f"FrameModel.drop_prob must be < 1, got {self.drop_prob}")
        if self.latency_max_s < self.latency_min_s:
            raise RealismError("FrameModel.latency_max_s must be >= latency_min_s")

    def draw(self, seed: int, key: int) -> tuple[bool, float]:
        """(dropped, latency_s) of frame ``key``."""
        rng = np.random.default_rng([int(seed), STREAM_FRAMES, int(key)])
        u = rng.random(2)
        return bool(u[0] < self.drop_prob), float(self.latency_min_s + u[1] * (self.latency_max_s - self.latency_min_s))


# -- profiles -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class RealismProfile:
    """A named set of world imperfections; a part left None is ideal.

    depth : DepthModel or None (exact depth)
    odometry : OdometryModel or None (the pilot reads the true pose)
    controller : ControllerModel or None (the ideal PD tracking of VehicleConfig)
    wind : WindModel or None (still air); never applied in scenes marked ``indoor``
    frames : FrameModel or None (every frame arrives at capture time)
    """

    name: str
    depth: DepthModel | None = None
    odometry: OdometryModel | None = None
    controller: ControllerModel | None = None
    wind: WindModel | None = None
    frames: FrameModel | None = None
    description: str = field(default="", compare=False)

    @property
    def is_ideal(self) -> bool:
        return all(getattr(self, k) is None for k in ("depth", "odometry", "controller", "wind", "frames"))


#: Flight altitude the benchmark's wind figures are computed for (the drone flies ~1.5 m up).
_ALTITUDE_M = 1.5

PROFILES: dict[str, RealismProfile] = {
    "ideal": RealismProfile("ideal", description="exact depth, odometry, tracking and frames (the world before realism profiles)"),
    "realistic": RealismProfile(
        "realistic",
        depth=DepthModel(),
        odometry=OdometryModel(),
        controller=ControllerModel(),
        wind=WindModel.dryden(7.7, _ALTITUDE_M),
        frames=FrameModel(),
        description="RealSense D435 depth, LiDAR-inertial odometry, PX4 position control, light Dryden turbulence outdoors",
    ),
    "realistic_calm": RealismProfile(
        "realistic_calm",
        depth=DepthModel(),
        odometry=OdometryModel(),
        controller=ControllerModel(),
        wind=None,
        frames=FrameModel(),
        description="the realistic profile in still air (separates the gusts' effect from the sensors' and the controller's)",
    ),
}


def realism_profile(name: str | RealismProfile | None) -> RealismProfile:
    """The profile of a name (``None`` = ideal); a RealismProfile passes through.

    Raises RealismError naming the valid profiles.
    """
    if name is None:
        return PROFILES["ideal"]
    if isinstance(name, RealismProfile):
        return name
    if not isinstance(name, str) or name not in PROFILES:
        raise RealismError(f"unknown realism profile {name!r}; valid: {', '.join(PROFILES)}")
    return PROFILES[name]
