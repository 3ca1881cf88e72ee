"""Synthetic patch features of the simulated VLM, derived only from what a frame shows.

Each pixel gets the embedding ``e = normalize(a * l + b * i)`` where ``l`` is a fixed seeded
random unit vector of its semantic label and ``i`` one of its instance (``a = 0.8``,
``b = 0.6``). Background (instance 0, or an id not in the annotation) uses the label
``"background"`` where depth has a reading and ``"sky"`` where it has none, with instance
vectors of their own. A patch of ``patch_px x patch_px`` pixels (the last row/column of patches
may be partial) holds the mean of its pixels' embeddings plus seeded Gaussian noise
(std ``noise_std`` per component), normalised to unit length.

Consequences the verifier relies on: inside one object, cosine similarity is ~1 (noise only);
between two instances of one label it is about ``a**2 = 0.64``; between labels it is about 0
(random unit vectors in ``dim`` dimensions, std ``1 / sqrt(dim)``); mixed boundary patches lie
in between. Vectors come from ``hashlib`` (not Python's salted ``hash``), so they are the same
in every process for one seed.
"""

from __future__ import annotations

import hashlib

import numpy as np

from vlm.types import FrameAnnotation, VisionFeatures

__all__ = ["keyed_rng", "unit_vector", "synthetic_features", "LABEL_WEIGHT", "INSTANCE_WEIGHT"]

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
    ids = np.asarray(annotation.instance_ids)
    depth = np.asarray(annotation.depth_m, dtype=np.float32)
    if ids.ndim != 2 or depth.shape != ids.shape:
        raise ValueError(f"annotation instance_ids {ids.shape} and depth_m {depth.shape} must be equal (H, W)")
    h, w = ids.shape
    hp, wp = -(-h // patch_px), -(-w // patch_px)
    known = np.isin(ids, np.fromiter(annotation.objects.keys(), dtype=np.int64, count=len(annotation.objects)))
    known &= ids != 0
    sky = ~known & ~(np.isfinite(depth) & (depth > 0))
    # class index per pixel: objects by id, then background, then sky
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
        e = LABEL_WEIGHT * unit_vector(seed, "label", label, dim) + INSTANCE_WEIGHT * unit_vector(seed, "instance", inst, dim)
        emb[k] = e / np.linalg.norm(e)
    rows = np.arange(h)[:, None] // patch_px
    cols = np.arange(w)[None, :] // patch_px
    patch = (rows * wp + cols).ravel()
    counts = np.bincount(patch * uniq.size + inv.ravel(), minlength=hp * wp * uniq.size).reshape(hp * wp, uniq.size)
    grid = (counts / counts.sum(axis=1, keepdims=True)) @ emb
    grid += noise_std * keyed_rng(seed, "feature-noise", frame_id).standard_normal(grid.shape)
    grid /= np.linalg.norm(grid, axis=1, keepdims=True)
    return VisionFeatures(grid=grid.reshape(hp, wp, dim).astype(np.float32), patch_px=float(patch_px), image_size=(w, h), source="sim:labels")
