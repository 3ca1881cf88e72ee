"""Synthetic patch features of the simulated VLM, derived only from what a frame shows.

Each pixel gets the embedding ``e = normalize(a * l + b * i)`` where ``l`` is a fixed seeded
random unit vector of its semantic label and ``i`` one of its instance (``a = 0.8``,
``b = 0.6``). Background (instance 0, or an id not in the annotation) uses the label
``"background"`` where depth has a reading and ``"sky"`` where it has none, with instance
vectors of their own. A patch of ``patch_px x patch_px`` pixels (the last row/column of patches
may be partial) holds the mean of its pixels' embeddings plus seeded Gaussian noise
(std ``noise_std`` per component), normalised to unit length.

This is the ``perfect`` feature model (a ground-truth segmentation in feature form).
:func:`degraded_features` is the benchmark's default: it degrades the same construction the way
real ViT patch features are imperfect (see its docstring and the sources cited there).

Consequences the verifier relies on (``perfect``): inside one object, cosine similarity is ~1 (noise only);
between two instances of one label it is about ``a**2 = 0.64``; between labels it is about 0
(random unit vectors in ``dim`` dimensions, std ``1 / sqrt(dim)``); mixed boundary patches lie
in between. Vectors come from ``hashlib`` (not Python's salted ``hash``), so they are the same
in every process for one seed.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np

from vlm.types import FrameAnnotation, VisionFeatures

__all__ = [
    "FEATURE_MODELS",
    "INSTANCE_WEIGHT",
    "LABEL_WEIGHT",
    "DegradedFeatureModel",
    "degraded_features",
    "keyed_rng",
    "synthetic_features",
    "unit_vector",
]

#: Names accepted by :class:`vlm.sim.SimulatedVlm` ``feature_model``.
FEATURE_MODELS = ("degraded", "perfect")

LABEL_WEIGHT = 0.8
INSTANCE_WEIGHT = 0.6


def keyed_rng(seed: int, *key: object) -> np.random.Generator:
    """A generator seeded by ``seed`` and a stable hash of ``key`` (reproducible across runs)."""
    digest = hashlib.blake2b(repr(key).encode("utf-8"), digest_size=16).digest()
    words = [int.from_bytes(digest[k : k + 4], "little") for k in range(0, 16, 4)]
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, *words])


def unit_vector(seed: int, kind: str, key: object, dim: int) -> np.ndarray:
    """Fixed random unit vector, shape (dim,), for a label or an instance."""
    v = keyed_rng(seed, "feature-vector", kind, key).standard_normal(dim)
    return v / np.linalg.norm(v)


def synthetic_features(
    annotation: FrameAnnotation,
    frame_id: str,
    *,
    seed: int = 0,
    dim: int = 64,
    patch_px: int = 16,
    noise_std: float = 0.02,
) -> VisionFeatures:
    """Patch features of an annotated frame (construction in the module docstring).

    Returns
    -------
    VisionFeatures with ``grid`` float32 (ceil(H / patch_px), ceil(W / patch_px), dim), unit
    rows, ``patch_px`` as given, ``source = "sim:labels"``.
    """
    grid3 = _class_patch_grid(annotation, seed, dim, patch_px, LABEL_WEIGHT, INSTANCE_WEIGHT)
    hp, wp = grid3.shape[:2]
    h, w = np.asarray(annotation.instance_ids).shape
    grid = grid3.reshape(hp * wp, dim)
    grid += noise_std * keyed_rng(seed, "feature-noise", frame_id).standard_normal(grid.shape)
    grid /= np.linalg.norm(grid, axis=1, keepdims=True)
    return VisionFeatures(grid=grid.reshape(hp, wp, dim).astype(np.float32), patch_px=float(patch_px), image_size=(w, h), source="sim:labels")


@dataclass(frozen=True)
class DegradedFeatureModel:
    """Parameters of :func:`degraded_features` (documented choices, fixed before any comparison).

    Attributes
    ----------
    label_weight, instance_weight : float
        Semantic part of a pixel's embedding, ``normalize(a l + b i)``. 0.85 / 0.53 puts two
        instances of one label at cos ~0.72 (look-alikes, above the paper's tau = 0.5), where the
        perfect model has 0.64. Dense ViT descriptors match semantically corresponding parts of
        different instances of one class (Amir et al., "Deep ViT Features as Dense Visual
        Descriptors", ECCV-W 2022, Sec. 3): instances are near each other in feature space.
    texture_weight : float
        Weight of the appearance part (a fixed seeded projection of the patch's mean colour and
        of its mean gradient magnitude) against the unit semantic part: 0.5 gives two patches
        of identical colour and texture on different labels a cosine of about 0.2 and pushes
        same-colour look-alikes above 0.8. ImageNet-trained networks rely on texture
        (Geirhos et al., "ImageNet-trained CNNs are biased towards texture", ICLR 2019); ViTs
        less so but measurably (Naseer et al., "Intriguing Properties of Vision Transformers",
        NeurIPS 2021, Sec. 3).
    blur_patches : float
        Std of a Gaussian over the patch grid, in patches: each patch mixes its neighbours, so
        boundary patches of an object look partly like what surrounds it (token mixing by
        attention, plus the 14-16 px patch grid itself; Yang et al., "Denoising Vision
        Transformers", ECCV 2024, Fig. 1, show patch features spreading across boundaries).
    noise_std : float
        Seeded Gaussian noise per component before normalization (64 dims: norm ~0.24).
    """

    label_weight: float = 0.85
    instance_weight: float = 0.53
    texture_weight: float = 0.5
    blur_patches: float = 0.75
    noise_std: float = 0.03


def degraded_features(
    annotation: FrameAnnotation,
    rgb: np.ndarray,
    frame_id: str,
    *,
    seed: int = 0,
    dim: int = 64,
    patch_px: int = 16,
    model: DegradedFeatureModel = DegradedFeatureModel(),
) -> VisionFeatures:
    """Patch features that err like real ones (seeded; the parameters in :class:`DegradedFeatureModel`).

    1. The semantic part: :func:`synthetic_features`' construction with look-alike weights,
       averaged per patch.
    2. The appearance part: per patch, a fixed seeded projection (dim x 4) of the mean colour
       (RGB in [-0.5, 0.5]) and the mean gradient magnitude of the grey image, normalized;
       added with ``texture_weight``.
    3. Blur over the patch grid (``blur_patches``), seeded noise, normalization.

    Parameters
    ----------
    annotation : FrameAnnotation of the frame (ids and depth, shape (H, W))
    rgb : uint8 array (H, W, 3), the frame's image

    Returns
    -------
    VisionFeatures with ``grid`` float32 (ceil(H / patch_px), ceil(W / patch_px), dim), unit
    rows, ``source = "sim:degraded"``.
    """
    from scipy.ndimage import gaussian_filter

    img = np.asarray(rgb)
    ids = np.asarray(annotation.instance_ids)
    if img.shape[:2] != ids.shape:
        raise ValueError(f"rgb {img.shape[:2]} and annotation instance_ids {ids.shape} must be the same (H, W)")
    semantic = _class_patch_grid(annotation, seed, dim, patch_px, model.label_weight, model.instance_weight)
    h, w = ids.shape
    hp, wp = semantic.shape[:2]
    colour = img.astype(np.float64) / 255.0 - 0.5
    grey = colour.mean(axis=2)
    gy, gx = np.gradient(grey)
    appearance = np.concatenate([colour, np.hypot(gx, gy)[..., None] * 4.0], axis=2)  # (H, W, 4)
    rows = np.arange(h)[:, None] // patch_px
    cols = np.arange(w)[None, :] // patch_px
    patch = (rows * wp + cols).ravel()
    counts = np.bincount(patch, minlength=hp * wp).astype(np.float64)
    app = np.stack([np.bincount(patch, weights=appearance[..., k].ravel(), minlength=hp * wp) for k in range(4)], axis=1)
    app /= counts[:, None]
    proj = keyed_rng(seed, "feature-appearance").standard_normal((4, dim))
    tex = app @ proj
    tex /= np.maximum(np.linalg.norm(tex, axis=1, keepdims=True), 1e-9)
    grid = semantic.reshape(hp * wp, dim) + model.texture_weight * tex
    grid = grid.reshape(hp, wp, dim)
    if model.blur_patches > 0:
        grid = gaussian_filter(grid, sigma=(model.blur_patches, model.blur_patches, 0.0), mode="nearest")
    grid = grid.reshape(hp * wp, dim)
    grid /= np.linalg.norm(grid, axis=1, keepdims=True)
    grid += model.noise_std * keyed_rng(seed, "feature-noise-degraded", frame_id).standard_normal(grid.shape)
    grid /= np.linalg.norm(grid, axis=1, keepdims=True)
    return VisionFeatures(grid=grid.reshape(hp, wp, dim).astype(np.float32), patch_px=float(patch_px), image_size=(w, h), source="sim:degraded")


def _class_patch_grid(annotation, seed, dim, patch_px, label_weight, instance_weight) -> np.ndarray:
    """Per-patch mean of the unit class embeddings (label + instance), shape (Hp, Wp, dim)."""
    ids = np.asarray(annotation.instance_ids)
    depth = np.asarray(annotation.depth_m, dtype=np.float32)
    if ids.ndim != 2 or depth.shape != ids.shape:
        raise ValueError(f"annotation instance_ids {ids.shape} and depth_m {depth.shape} must be equal (H, W)")
    h, w = ids.shape
    hp, wp = -(-h // patch_px), -(-w // patch_px)
    known = np.isin(ids, np.fromiter(annotation.objects.keys(), dtype=np.int64, count=len(annotation.objects)))
    known &= ids != 0
    with np.errstate(invalid="ignore"):
        sky = ~known & ~(np.isfinite(depth) & (depth > 0))
    keys = np.where(known, ids.astype(np.int64), np.where(sky, -2, -1))
    uniq, inv = np.unique(keys, return_inverse=True)
    inv = inv.reshape(h, w)
    emb = np.empty((uniq.size, dim))
    for k, key in enumerate(uniq.tolist()):
        if key == -1:
            label, inst = "background", "background"
        elif key == -2:
            label, inst = "sky", "sky"
        else:
            label, inst = annotation.objects[key].label, key
        e = label_weight * unit_vector(seed, "label", label, dim) + instance_weight * unit_vector(seed, "instance", inst, dim)
        emb[k] = e / np.linalg.norm(e)
    rows = np.arange(h)[:, None] // patch_px
    cols = np.arange(w)[None, :] // patch_px
    patch = (rows * wp + cols).ravel()
    counts = np.bincount(patch * uniq.size + inv.ravel(), minlength=hp * wp * uniq.size).reshape(hp * wp, uniq.size)
    return ((counts / counts.sum(axis=1, keepdims=True)) @ emb).reshape(hp, wp, dim)
