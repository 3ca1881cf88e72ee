"""RGB, z-depth, semantic and instance images of a scene by CPU ray casting (Open3D Embree).

Shading model (per pixel, vectorized):

``rgb = 255 * colour * texture * (ambient + (1 - ambient) * max(0, n . l))``

``colour`` is the hit triangle's object (or part) colour, ``n`` the triangle's face normal
turned towards the camera (flat shading, so it is computed once per triangle per frame), ``l`` the scene's light direction (towards the light) and ``texture`` the
object's procedural pattern evaluated at the world hit point (``1 - contrast * value`` with
``value`` in [0, 1]). Rays that hit nothing get the scene's sky colour, depth 0 (no reading)
and ids 0.

Depth sensor-noise model (:class:`DepthNoise`, off by default), applied to depth only:
axial Gaussian noise with ``sigma(z) = sigma_base_m + sigma_quadratic_per_m * z**2`` (the
quadratic growth of stereo / structured-light RMS error), independent per-pixel dropout with
probability ``dropout_prob``, and readings outside ``[min_range_m, max_range_m]`` set to 0
(no reading). Each frame draws from ``default_rng([seed, noise_key])`` so a frame's noise
depends only on the seed and the caller's frame key, never on render order.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from onfly.world.geometry import SceneGeometry
from planning.camera import PinholeCamera
from planning.frames import check_transform
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
    """

    threads: int = 1
    depth_noise: DepthNoise = DepthNoise()
    textures: bool = True

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
    """

    rgb: np.ndarray
    depth_m: np.ndarray
    instance_ids: np.ndarray
    semantic_ids: np.ndarray
    T_world_cam: np.ndarray


def _rotate_into(cols: tuple[np.ndarray, np.ndarray, np.ndarray], R: np.ndarray, out: np.ndarray) -> None:
    """``out[:, i] = sum_k R[i, k] * cols[k]`` for float32 column vectors (n,), no BLAS."""
    R = R.astype(np.float32)
    tmp = np.empty_like(cols[0])
    for i in range(3):
        col = out[:, i]
        np.multiply(cols[0], R[i, 0], out=tmp)
        tmp += cols[1] * R[i, 1]
        tmp += cols[2] * R[i, 2]
        col[...] = tmp


#: Value noise: one random brightness per cubic cell, from a fixed table of 32^3 cells (the
#: pattern repeats every 32 cells); each texture seed shifts the table by its own offset.
_NOISE_N = 32


class Renderer:
    """Renders a scene from a pinhole camera.

    Build once per scene (the ray-casting structure and the camera rays are precomputed);
    :meth:`render` only rotates the rays, casts them and shades the hits.

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
        rays = self.camera.rays(normalize=True).reshape(-1, 3)
        self._rays_cols = tuple(np.ascontiguousarray(rays[:, k], dtype=np.float32) for k in range(3))  # unit rays, optical frame
        self._ray_z = rays[:, 2].astype(np.float32)  # z-depth = ray length * ray_z
        self._buf = np.empty((rays.shape[0], 6), dtype=np.float32)
        scene = geometry.scene
        self._light = scene.light.direction.astype(np.float32)
        self._ambient = np.float32(scene.light.ambient)
        self._sky = scene.sky_color.astype(np.uint8)
        # per-triangle tables with one extra "sky" row at index triangle_count
        self._tri_instance = np.append(geometry.tri_instance, 0).astype(np.int32)
        self._tri_label = np.append(geometry.tri_label, 0).astype(np.int32)
        self._tri_texture = np.append(geometry.tri_texture, 0).astype(np.int8)
        prm = geometry.tri_tex_params
        self._tex_inv_period = np.where(prm[:, 0] > 0, 1.0 / np.where(prm[:, 0] > 0, prm[:, 0], 1.0), 0.0).astype(np.float32)
        self._tex_contrast = prm[:, 1].astype(np.float32)
        self._tex_axis = np.argmax(np.abs(prm[:, 2:5]), axis=1).astype(np.intp)
        seeds = prm[:, 5].astype(np.int64)
        offsets = {int(sd): np.random.default_rng([0x5EED, int(sd)]).integers(0, _NOISE_N, 3) for sd in np.unique(seeds)}
        self._tex_offset = np.array([offsets[int(sd)] for sd in seeds], dtype=np.int32).reshape(-1, 3)
        self._noise = np.random.default_rng(0x5EED).random(_NOISE_N**3).astype(np.float32)
        self._objects = {o.instance_id: VisibleObject(o.instance_id, o.name, o.label, o.aliases) for o in scene.objects}

    def world_rays(self, T_world_cam) -> np.ndarray:
        """Camera rays in the world, float32 (H * W, 6) ``[origin, unit direction]`` in row-major
        pixel order. The array is a buffer reused by the next call (copy it to keep it)."""
        T = np.asarray(T_world_cam, dtype=float)
        buf = self._buf
        buf[:, :3] = T[:3, 3].astype(np.float32)
        # Rotate without BLAS: a (n, 3) @ (3, 3) product through a threaded BLAS stalls when the
        # cores are shared; three fused passes per axis are cheap and predictable.
        _rotate_into(self._rays_cols, T[:3, :3], buf[:, 3:])
        return buf

    def render(self, T_world_cam, *, noise_key: int = 0) -> RenderResult:
        """Render RGB, z-depth and id images.

        Parameters
        ----------
        T_world_cam : (4, 4), camera optical frame -> world ENU
        noise_key : int, frame key for the depth-noise draw (ignored when noise is off)
        """
        T = check_transform(T_world_cam, "T_world_cam")
        H, W = self.camera.height, self.camera.width
        buf = self.world_rays(T)
        hits = self.geometry.cast(buf, threads=self.config.threads)
        g = self.geometry
        m = g.triangle_count
        # Misses carry primitive id 2^32 - 1: clamp them onto the sky row (index m) of the
        # per-triangle tables so every per-pixel lookup is one gather, without boolean masks.
        tri = np.minimum(hits["primitive_ids"], m).astype(np.intp)
        t_hit = hits["t_hit"]
        depth = t_hit * self._ray_z
        depth[tri == m] = 0.0
        inst = np.take(self._tri_instance, tri)
        sem = np.take(self._tri_label, tri)
        # Flat shading is per triangle: shade the m triangles once, then gather per pixel.
        color_tri = self._shade_triangles(T[:3, 3])
        rgb = np.take((color_tri * 255.0 + 0.5).astype(np.uint8), tri, axis=0)
        textured = np.flatnonzero(np.take(self._tri_texture, tri)) if self.config.textures else ()
        if len(textured):
            ti = tri[textured]
            # hit points pulled 1 mm towards the camera, so faces on a cell boundary never flicker
            rows = np.take(buf, textured, axis=0)
            P = rows[:, 3:] * (np.take(t_hit, textured) - np.float32(1e-3))[:, None]
            P += rows[:, :3]
            shaded = color_tri[ti] * self._texture(self._tri_texture[ti], ti, P)[:, None]
            rgb[textured] = (shaded * 255.0 + 0.5).astype(np.uint8)

        depth = depth.reshape(H, W)
        if self.config.depth_noise.enabled:
            depth = self.config.depth_noise.apply(depth, noise_key)
        return RenderResult(rgb.reshape(H, W, 3), depth, inst.reshape(H, W), sem.reshape(H, W), T)

    def _shade_triangles(self, camera_m: np.ndarray) -> np.ndarray:
        """Lambert colour in [0, 1] of every triangle seen from ``camera_m`` (3,), float32
        (m + 1, 3); the last row is the sky. Normals are turned towards the camera."""
        g = self.geometry
        facing = np.sign(np.einsum("ij,ij->i", g.tri_normal, camera_m.astype(np.float32) - g.tri_v0))
        lam = self._ambient + (1.0 - self._ambient) * np.maximum(facing * np.einsum("ij,j->i", g.tri_normal, self._light), 0.0)
        out = np.empty((g.triangle_count + 1, 3), dtype=np.float32)
        out[:-1] = g.tri_color * lam[:, None]
        out[-1] = self._sky.astype(np.float32) / 255.0
        return out

    def _texture(self, code: np.ndarray, tri: np.ndarray, P: np.ndarray) -> np.ndarray:
        """Brightness factor in [1 - contrast, 1] per hit (n,) of triangles ``tri`` with pattern
        ``code``; P (n, 3) the hit points, metres, world ENU."""
        Q = P * np.take(self._tex_inv_period, tri)[:, None]  # position in cells
        val = np.empty(len(code), dtype=np.float32)
        present = np.flatnonzero(np.bincount(code, minlength=4))
        for c in present:
            sel = slice(None) if len(present) == 1 else np.flatnonzero(code == c)
            q = Q[sel]
            t = tri[sel]
            if c == 1:  # stripes across the axis
                val[sel] = np.floor(np.take_along_axis(q, np.take(self._tex_axis, t)[:, None], axis=1)[:, 0]) % 2.0
            elif c == 2:  # 3D checker
                val[sel] = np.floor(q).sum(axis=1) % 2.0
            else:  # value noise: a fixed random value per cell, periodic over 32 cells, shifted per seed
                cells = np.floor(q).astype(np.int32) + np.take(self._tex_offset, t, axis=0)
                cells &= _NOISE_N - 1
                val[sel] = np.take(self._noise, (cells[:, 0] * _NOISE_N + cells[:, 1]) * _NOISE_N + cells[:, 2])
        return 1.0 - np.take(self._tex_contrast, tri) * val

    def annotate(self, result: RenderResult) -> FrameAnnotation:
        """Ground truth for the simulated VLM: ids, depth and the instances present in the image."""
        ids = result.instance_ids
        present = np.flatnonzero(np.bincount(ids.ravel()))
        objects = {int(i): self._objects[int(i)] for i in present if i != 0}
        return FrameAnnotation(instance_ids=ids, depth_m=result.depth_m, objects=objects, semantic_ids=result.semantic_ids)
