"""RGB, z-depth, semantic and instance images of a scene by CPU ray casting (Open3D Embree).

Shading model (per pixel, vectorized):

``rgb = 255 * colour * texture * (ambient + (1 - ambient) * max(0, n . l))``

``colour`` is the hit triangle's object (or part) colour, ``n`` the triangle's face normal
turned towards the camera (flat shading, so it is computed once per triangle per frame), ``l``
the scene's light direction (towards the light) and ``texture`` the object's procedural
pattern evaluated at the world hit point: ``1 - contrast * level / 15`` with the level 0 or 15
for stripes and checker and one of 16 random levels per cell for noise. Rays that hit nothing
get the scene's sky colour, depth 0 (no reading) and ids 0.

Actors (objects with a motion, :mod:`onfly.world.actors`) are not part of the static
ray-casting structure: each has its own, built once in its own frame. Per frame, the rays that
pass its bounding sphere are moved into the actor frame at its pose at ``t_s`` (a rigid
transform, so hit distances are unchanged) and cast; the nearer of the static and actor hits
wins per pixel (depth, ids, shading). Nothing is rebuilt when actors move.

Depth sensor-noise model (:class:`DepthNoise`, off by default), applied to depth only:
axial Gaussian noise with ``sigma(z) = sigma_base_m + sigma_quadratic_per_m * z**2`` (the
quadratic growth of stereo / structured-light RMS error), independent per-pixel dropout with
probability ``dropout_prob``, and readings outside ``[min_range_m, max_range_m]`` set to 0
(no reading). Each frame draws from ``default_rng([seed, noise_key])`` so a frame's noise
depends only on the seed and the caller's frame key, never on render order.

Depth sensor of a realism profile (``RenderConfig.sensor``, a
:class:`onfly.world.realism.DepthModel`, None by default): the RealSense D435 model (quadratic
noise, flying pixels at edges, minimum and maximum range, no readings on glass / mirror / dark
materials), drawn from ``default_rng([sensor_seed, STREAM_DEPTH, noise_key])``. The VLM
annotation keeps the exact depth (what the image shows), the depth image is the sensor's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from onfly.world.geometry import SceneGeometry
from onfly.world.realism import STREAM_DEPTH, DepthModel
from planning.camera import PinholeCamera
from planning.frames import check_transform, invert_transform
from vlm.types import FrameAnnotation, VisibleObject

__all__ = ["RenderConfig", "DepthNoise", "RenderResult", "Renderer", "default_camera"]


def default_camera() -> PinholeCamera:
    """The benchmark camera: 640 x 427, 90 x 60 deg field of view."""
    return PinholeCamera.from_fov(640, 427, 90.0, 60.0)


@dataclass(frozen=True)
class DepthNoise:
    """Seeded depth sensor-noise model (see the module docstring). ``enabled=False`` = exact."""

    enabled: bool = False
    seed: int = 0
    sigma_base_m: float = 0.002
    sigma_quadratic_per_m: float = 0.0025
    dropout_prob: float = 0.01
    min_range_m: float = 0.1
    max_range_m: float = 10.0

    def __post_init__(self) -> None:
        for name in ("sigma_base_m", "sigma_quadratic_per_m", "min_range_m"):
            if not (getattr(self, name) >= 0.0 and np.isfinite(getattr(self, name))):
                raise ValueError(f"DepthNoise.{name} must be finite and >= 0, got {getattr(self, name)}")
        if not (0.0 <= self.dropout_prob < 1.0):
            raise ValueError(f"DepthNoise.dropout_prob must be in [0, 1), got {self.dropout_prob}")
        if not (self.max_range_m > self.min_range_m):
            raise ValueError(f"DepthNoise.max_range_m must exceed min_range_m, got {self.max_range_m} <= {self.min_range_m}")

    def apply(self, depth_m: np.ndarray, noise_key: int) -> np.ndarray:
        """Noisy copy of a float32 (H, W) z-depth image (0 = no reading stays 0)."""
        rng = np.random.default_rng([self.seed, int(noise_key)])
        z = depth_m.astype(np.float32, copy=True)
        valid = z > 0
        sigma = self.sigma_base_m + self.sigma_quadratic_per_m * z * z
        z = z + (rng.standard_normal(z.shape).astype(np.float32) * sigma)
        drop = rng.random(z.shape) < self.dropout_prob
        z[~valid | drop | (z < self.min_range_m) | (z > self.max_range_m)] = 0.0
        return z


@dataclass(frozen=True)
class RenderConfig:
    """Renderer settings.

    threads : Embree threads for ray casting (1 = one core, as the benchmark budgets; 0 = all)
    depth_noise : DepthNoise model (off by default)
    textures : evaluate texture patterns (False: flat shaded colours only, about a quarter less
        time per frame in textured scenes; depth and ids are unaffected)
    sensor : DepthModel of a realism profile, or None (exact depth)
    sensor_seed : seed of the sensor's draws (the episode seed)
    """

    threads: int = 1
    depth_noise: DepthNoise = DepthNoise()
    textures: bool = True
    sensor: DepthModel | None = None
    sensor_seed: int = 0

    def __post_init__(self) -> None:
        if int(self.threads) < 0:
            raise ValueError(f"RenderConfig.threads must be >= 0, got {self.threads}")


@dataclass(frozen=True, eq=False)
class RenderResult:
    """One rendered frame.

    rgb : uint8 (H, W, 3)
    depth_m : float32 (H, W), z-depth in metres along the optical axis; 0 = no reading
    instance_ids : int32 (H, W), 0 = background (sky)
    semantic_ids : int32 (H, W), ``scene.label_ids`` values, 0 = background
    T_world_cam : (4, 4), camera optical frame -> world ENU
    exact_depth_m : float32 (H, W), the exact z-depth when a sensor model changed ``depth_m``
        (what the VLM annotation uses), else None
    """

    rgb: np.ndarray
    depth_m: np.ndarray
    instance_ids: np.ndarray
    semantic_ids: np.ndarray
    T_world_cam: np.ndarray
    exact_depth_m: np.ndarray | None = None


#: Value noise: one random brightness level per cubic cell, from a fixed table of 32^3 cells
#: (the pattern repeats every 32 cells along each axis); each seed rolls the table by its own
#: shift.
_NOISE_BITS = 5
_NOISE_N = 1 << _NOISE_BITS
#: Texture brightness levels: stripes and checker use the two ends, noise all of them.
_LEVELS = 16


class Renderer:
    """Renders a scene from a pinhole camera.

    Build once per scene (the ray-casting structure is built with the SceneGeometry); per
    frame :meth:`render` makes the camera rays (Open3D, in C++), casts them and shades the hits.

    Parameters
    ----------
    geometry : SceneGeometry (shared with the collision checker)
    camera : PinholeCamera, default :func:`default_camera`
    config : RenderConfig
    """

    def __init__(self, geometry: SceneGeometry, camera: PinholeCamera | None = None, config: RenderConfig | None = None) -> None:
        self.geometry = geometry
        self.camera = camera if camera is not None else default_camera()
        self.config = config if config is not None else RenderConfig()
        # Open3D samples pixel (u, v) at (u + 0.5, v + 0.5); our pixel centres are integers.
        K = self.camera.K
        K[0, 2] += 0.5
        K[1, 2] += 0.5
        self._K_o3d = o3d.core.Tensor(K)
        scene = geometry.scene
        self._light = scene.light.direction.astype(np.float32)
        self._ambient = np.float32(scene.light.ambient)
        self._sky = scene.sky_color.astype(np.uint8)
        # per-triangle tables over the static triangles then each actor's (SceneGeometry.
        # combined_table), with one extra "sky" row at index m (the total triangle count)
        g = geometry
        self._m = g.total_triangle_count
        self._tri_instance = np.append(g.combined_table("tri_instance"), 0).astype(np.int32)
        self._tri_label = np.append(g.combined_table("tri_label"), 0).astype(np.int32)
        self._tri_texture = np.append(g.combined_table("tri_texture"), 0).astype(np.int8)
        self._tri_material = np.append(g.combined_table("tri_material"), 0).astype(np.uint8)
        self._tri_color = g.combined_table("tri_color").astype(np.float32)
        # normals and first vertices: static ones in the world; actor ones in their own frames,
        # moved to the pose of the frame being rendered (render() never mutates the renderer,
        # so threads may share it)
        self._tri_normal = g.combined_table("tri_normal").astype(np.float32)
        self._tri_v0 = g.combined_table("tri_v0").astype(np.float32)
        prm = g.combined_table("tri_tex_params")
        self._tex_inv_period = np.where(prm[:, 0] > 0, 1.0 / np.where(prm[:, 0] > 0, prm[:, 0], 1.0), 0.0).astype(np.float32)
        self._tex_contrast = np.append(prm[:, 1], 0.0).astype(np.float32)  # sky row: no texture
        self._tex_axis = np.argmax(np.abs(prm[:, 2:5]), axis=1).astype(np.intp)
        seeds = prm[:, 5].astype(np.int64)
        shifts = {int(sd): int(np.random.default_rng([0x5EED, int(sd)]).integers(0, _NOISE_N**3)) for sd in np.unique(seeds)}
        self._tex_shift = np.array([shifts[int(sd)] for sd in seeds], dtype=np.int32)
        self._noise = np.random.default_rng(0x5EED).integers(0, _LEVELS, _NOISE_N**3).astype(np.int32)
        self._objects = {o.instance_id: VisibleObject(o.instance_id, o.name, o.label, o.aliases, o.target) for o in scene.objects}

    def world_rays(self, T_world_cam) -> np.ndarray:
        """Camera rays in the world, float32 (H * W, 6) ``[origin, direction]`` in row-major
        pixel order. Directions are ``R_world_cam @ K^-1 [u, v, 1]``: their optical-z component
        is 1, so a hit at ray parameter ``t`` lies at z-depth ``t`` (ray length ``t * |d|``)."""
        T = np.asarray(T_world_cam, dtype=float)
        rays = o3d.t.geometry.RaycastingScene.create_rays_pinhole(
            self._K_o3d, o3d.core.Tensor(invert_transform(T)), self.camera.width, self.camera.height
        )
        return rays.numpy().reshape(-1, 6)

    def render(self, T_world_cam, *, noise_key: int = 0, t_s: float = 0.0) -> RenderResult:
        """Render RGB, z-depth and id images.

        Parameters
        ----------
        T_world_cam : (4, 4), camera optical frame -> world ENU
        noise_key : int, frame key for the depth-noise draw (ignored when noise is off)
        t_s : float, world-clock time that places the actors (scenes without actors ignore it)
        """
        T = check_transform(T_world_cam, "T_world_cam")
        H, W = self.camera.height, self.camera.width
        buf = self.world_rays(T)
        hits = self.geometry.cast(buf, threads=self.config.threads)
        m = self._m
        # Misses carry primitive id 2^32 - 1: clamp them onto the sky row (index m) of the
        # per-triangle tables so every per-pixel lookup is one gather, without boolean masks.
        tri = np.minimum(hits["primitive_ids"], m).astype(np.intp)
        t_hit = hits["t_hit"]
        if self.geometry.actors:
            # each actor is cast in its own frame against its own structure; nearest hit wins
            self.geometry.cast_actors(buf, t_hit, tri, float(t_s), threads=self.config.threads,
                                      candidates=self._sphere_pixels(T))
        depth = t_hit.copy()  # rays have unit optical z: t is the z-depth
        depth[tri == m] = 0.0
        inst = np.take(self._tri_instance, tri)
        sem = np.take(self._tri_label, tri)
        # Flat shading is per triangle and texture brightness is quantized to _LEVELS levels,
        # so the colour of every (triangle, level) pair is tabulated once per frame and the
        # image is one gather.
        lut = self._colour_table(T[:3, 3], float(t_s))
        index = tri * _LEVELS
        textured = np.flatnonzero(np.take(self._tri_texture, tri)) if self.config.textures else ()
        if len(textured):
            ti = tri[textured]
            # cell coordinates of the hit points, pulled 1 mm towards the camera so faces on a
            # cell boundary never flicker; one contiguous pass per world axis
            t_tex = np.take(t_hit, textured) - np.float32(1e-3)
            inv = np.take(self._tex_inv_period, ti)
            cells = []
            for k in range(3):
                q = np.take(buf[:, 3 + k], textured)
                q *= t_tex
                q += buf[0, k]
                q *= inv
                cells.append(np.floor(q, out=q).astype(np.int32))
            index[textured] += self._texture_level(self._tri_texture[ti], ti, tuple(cells))
        rgb = np.take(lut, index, axis=0)

        depth = depth.reshape(H, W)
        exact = None
        sensor = self.config.sensor
        if sensor is not None:
            exact = depth
            material = np.take(self._tri_material, tri).reshape(H, W)
            rng = np.random.default_rng([int(self.config.sensor_seed), STREAM_DEPTH, int(noise_key)])
            depth = sensor.apply(depth, material, rng, fx_px=float(self.camera.K[0, 0]))
        if self.config.depth_noise.enabled:
            depth = self.config.depth_noise.apply(depth, noise_key)
        return RenderResult(rgb.reshape(H, W, 3), depth, inst.reshape(H, W), sem.reshape(H, W), T, exact)

    def _sphere_pixels(self, T_world_cam: np.ndarray):
        """``f(centre_m, radius_m)`` -> row-major pixel indices of a rectangle that holds the
        image of a world sphere: the range of ``x / z`` and ``y / z`` (optical frame) over the
        sphere's bounding cube cut to ``z > 0`` (every camera ray has optical ``z`` = 1), one
        pixel of margin; empty when the sphere is behind the camera or outside the image."""
        cam = self.camera
        R, p = T_world_cam[:3, :3], T_world_cam[:3, 3]
        H, W = cam.height, cam.width
        fx, fy, cx, cy = cam.fx, cam.fy, cam.cx, cam.cy
        empty = np.zeros(0, dtype=np.intp)

        def pixels(centre_m: np.ndarray, radius_m: float):
            c = R.T @ (np.asarray(centre_m, float) - p)  # camera optical frame
            z1 = c[2] + radius_m
            if z1 <= 0:
                return empty
            z0 = max(c[2] - radius_m, 1e-6)
            # x / z and y / z are monotonic in each variable on the cube: extremes at its corners
            xs = ((c[0] - radius_m) / z0, (c[0] - radius_m) / z1, (c[0] + radius_m) / z0, (c[0] + radius_m) / z1)
            ys = ((c[1] - radius_m) / z0, (c[1] - radius_m) / z1, (c[1] + radius_m) / z0, (c[1] + radius_m) / z1)
            u_lo, u_hi = fx * min(xs) + cx, fx * max(xs) + cx
            v_lo, v_hi = fy * min(ys) + cy, fy * max(ys) + cy
            if u_hi < -1 or v_hi < -1 or u_lo > W or v_lo > H:
                return empty
            u0, u1 = max(int(np.floor(u_lo)) - 1, 0), min(int(np.ceil(u_hi)) + 1, W - 1)
            v0, v1 = max(int(np.floor(v_lo)) - 1, 0), min(int(np.ceil(v_hi)) + 1, H - 1)
            if u0 > u1 or v0 > v1:
                return empty
            return (np.arange(v0, v1 + 1, dtype=np.intp)[:, None] * W + np.arange(u0, u1 + 1, dtype=np.intp)[None, :]).ravel()

        return pixels

    def _colour_table(self, camera_m: np.ndarray, t_s: float = 0.0) -> np.ndarray:
        """uint8 RGB of every triangle at every texture level seen from ``camera_m`` (3,):
        shape ((m + 1) * _LEVELS, 3), row ``tri * _LEVELS + level``; the last block is the sky.
        Actor rows use the actors' poses at ``t_s``.

        Lambert shading with the face normal turned towards the camera; level ``l`` scales the
        colour by ``1 - contrast * l / (_LEVELS - 1)``.
        """
        nrm, v0 = self._tri_normal, self._tri_v0
        if self.geometry.actors:
            nrm, v0 = nrm.copy(), v0.copy()
            for a in self.geometry.actors:
                T = a.pose(t_s).T_world_actor.astype(np.float32)
                rows = slice(a.tri_offset, a.tri_offset + len(a.triangles))
                nrm[rows] = a.tables["tri_normal"] @ T[:3, :3].T
                v0[rows] = a.tables["tri_v0"] @ T[:3, :3].T + T[:3, 3]
        facing = np.sign(np.einsum("ij,ij->i", nrm, camera_m.astype(np.float32) - v0))
        lam = self._ambient + (1.0 - self._ambient) * np.maximum(facing * np.einsum("ij,j->i", nrm, self._light), 0.0)
        colour = np.empty((self._m + 1, 3), dtype=np.float32)
        colour[:-1] = self._tri_color * lam[:, None]
        colour[-1] = self._sky.astype(np.float32) / 255.0
        factor = 1.0 - self._tex_contrast[:, None] * np.linspace(0.0, 1.0, _LEVELS, dtype=np.float32)
        table = colour[:, None, :] * factor[:, :, None] * 255.0 + 0.5
        return table.astype(np.uint8).reshape(-1, 3)

    def _texture_level(self, code: np.ndarray, tri: np.ndarray, cells: tuple[np.ndarray, np.ndarray, np.ndarray]) -> np.ndarray:
        """Texture level in 0.._LEVELS - 1 per hit (n,) of triangles ``tri`` with pattern
        ``code``; ``cells`` are the integer cell coordinates (int32 (n,) per world axis) of the
        hit points, ``floor(p / period_m)``."""
        ix, iy, iz = cells
        top = _LEVELS - 1
        present = [c for c in np.flatnonzero(np.bincount(code, minlength=4)) if c != 0]
        levels = {}
        for c in present:
            if c == 1:  # stripes across the axis
                levels[c] = (np.choose(np.take(self._tex_axis, tri), (ix, iy, iz)) & 1) * top
            elif c == 2:  # 3D checker
                levels[c] = ((ix + iy + iz) & 1) * top
            else:  # value noise: a fixed random level per cell, periodic over 32 cells, shifted per seed
                mask = _NOISE_N - 1
                idx = ((ix & mask) << (2 * _NOISE_BITS)) | ((iy & mask) << _NOISE_BITS) | (iz & mask)
                idx += np.take(self._tex_shift, tri)
                idx &= _NOISE_N**3 - 1
                levels[c] = np.take(self._noise, idx)
        if len(levels) == 1:
            return next(iter(levels.values()))
        return np.choose(code - 1, [levels.get(c, levels[present[0]]) for c in (1, 2, 3)])

    def annotate(self, result: RenderResult) -> FrameAnnotation:
        """Ground truth for the simulated VLM: ids, depth and the instances present in the image."""
        ids = result.instance_ids
        present = np.flatnonzero(np.bincount(ids.ravel()))
        objects = {int(i): self._objects[int(i)] for i in present if i != 0}
        depth = result.depth_m if result.exact_depth_m is None else result.exact_depth_m
        return FrameAnnotation(instance_ids=ids, depth_m=depth, objects=objects, semantic_ids=result.semantic_ids)
