"""Benchmark of the semantic-geometric verifier (planning.verifier).

On seeded synthetic scenes (a 640 x 480 camera with the paper's 90 x 60 deg FOV, ground, a back
wall with sky above it, labelled boxes; features = a random unit vector per label averaged over
16 x 16-pixel patches, i.e. a 40 x 30 grid) it draws candidate goals the way a pointing VLM errs:
the target pixel nearest the region's centroid (``--pointing uniform``: anywhere on it) plus
Gaussian noise whose std follows the simulated VLM's error model (``vlm.sim``, preset
``nominal``: ``W * (0.006 + 0.0015 d)``, about 8 px at 4.5 m) or a fixed ``--noise-px``. It reports

* ``verify_us_median``: wall time per ``Verifier.verify`` call;
* ``unsafe_rate_before`` / ``unsafe_rate_after``: fraction of candidates whose goal is closer
  than r to an obstacle, without the verifier (the noisy pixel lifted to ``min(depth, D_max)``)
  and with it (rejections count as safe). Obstacles follow the documented rule
  (:mod:`planning.verifier_config`) referenced to the *true* target's depth, so a noisy pixel
  that lands on a nearer object counts as unsafe even though the verifier cannot know;
  ``unsafe_rate_after_own_rule`` uses the verifier's own reference (its guarantee: 0);
  the ``path_`` variants measure the straight segment camera -> goal instead of the goal point;
* ``region_kept_rate``: fraction of accepted goals whose refined pixel lies on the target's label;
* per feature source, in one run on the same candidates (``per_source``): ``ground_truth``
  (one random unit vector per box, the perfect segmentation), ``degraded`` (the simulated ViT
  features of :func:`vlm.sim.features.degraded_features`: blurred boundaries, colour/texture
  similarity, look-alike labels shared by several boxes), ``none`` (geometric-only: the target's
  surface). For each: ``unsafe_rate`` (goal closer than r to a true-rule obstacle),
  ``off_target_rate`` (accepted goals whose refined pixel is not on the target box, over all
  candidates), ``moved_off_target_rate`` (the pixel was on the target and refinement moved it
  off), ``accept_rate``;
* a reference in the same run: an exhaustive exact verifier (brute-force ray clearance against
  every obstacle point, scipy labelling) on a subset, for timing and for how much farther the
  fast path's conservative dilation moves the pixel.

Run: ``.venv/bin/python experiments/bench_verifier.py --json out.json``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import time
from collections import Counter

import numpy as np
from scipy import ndimage

from planning.camera import PinholeCamera
from planning.frames import body_transform, cam_transform_from_body, invert_transform, transform_points
from planning.verifier import CandidateGoal, Verifier, VerifierConfig
from vlm.sim.error_model import get_preset


# -- scenes --------------------------------------------------------------------------------------


def render_boxes(camera: PinholeCamera, boxes) -> tuple[np.ndarray, np.ndarray]:
    """Ray-cast axis-aligned boxes (camera optical frame). Returns z-depth (NaN = no hit) and
    labels (box index, -1 = no hit). Rays have z = 1, so the ray parameter is the z-depth."""
    rays = camera.rays()
    depth = np.full(camera.shape, np.inf)
    labels = np.full(camera.shape, -1, dtype=int)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / rays
        for k, (lo, hi) in enumerate(boxes):
            t1 = np.asarray(lo, float) * inv
            t2 = np.asarray(hi, float) * inv
            t_near = np.nanmax(np.minimum(t1, t2), axis=-1)
            t_far = np.nanmin(np.maximum(t1, t2), axis=-1)
            hit = (t_near <= t_far) & (t_near > 0) & (t_near < depth)
            depth[hit] = t_near[hit]
            labels[hit] = k
    depth[~np.isfinite(depth)] = np.nan
    return depth.astype(np.float32), labels


def make_scene(rng: np.random.Generator, camera: PinholeCamera, min_target_px: int):
    """Ground (label 0), back wall (1), 5-9 boxes; a target box 2.5-6.5 m away, well visible."""
    while True:
        h_cam = rng.uniform(1.2, 2.0)
        z_wall = rng.uniform(9.0, 16.0)
        boxes = [
            ((-80.0, h_cam, 0.0), (80.0, h_cam + 1.0, 90.0)),
            ((-80.0, h_cam - rng.uniform(3.0, 9.0), z_wall), (80.0, h_cam, z_wall + 1.0)),
        ]
        for _ in range(rng.integers(5, 10)):
            z = rng.uniform(1.2, 8.5)
            x = rng.uniform(-0.9, 0.9) * z
            w, d, hgt = rng.uniform(0.3, 2.0), rng.uniform(0.3, 2.0), rng.uniform(0.4, 3.0)
            boxes.append(((x - w / 2, h_cam - hgt, z), (x + w / 2, h_cam, z + d)))
        depth, labels = render_boxes(camera, boxes)
        targets = []
        for k in range(2, len(boxes)):
            mask = labels == k
            n = int(mask.sum())
            if n >= min_target_px and 2.5 <= float(np.median(depth[mask])) <= 6.5:
                targets.append(k)
        if targets:
            return depth, labels, targets


#: Look-alike vocabulary and palette of the boxes (several boxes share a label and a colour).
_BOX_LABELS = ("crate", "crate", "van", "bin")
_PALETTE = ((180, 40, 40), (60, 60, 170), (200, 180, 60), (120, 120, 120))


def degraded_scene_features(labels: np.ndarray, depth: np.ndarray, patch: int, dim: int, seed: int, frame: str):
    """:func:`vlm.sim.features.degraded_features` of a bench scene: boxes get a look-alike label
    and a colour from small shared sets (seeded), ground and wall their own."""
    from vlm.sim.features import degraded_features
    from vlm.types import FrameAnnotation, VisibleObject

    rng = np.random.default_rng([seed, 7])
    n = int(labels.max()) + 1
    names = ["ground", "wall"] + [str(rng.choice(_BOX_LABELS)) for _ in range(2, n)]
    colours = [(110, 100, 90), (170, 160, 150)] + [_PALETTE[int(rng.integers(len(_PALETTE)))] for _ in range(2, n)]
    ids = np.where(labels >= 0, labels + 1, 0).astype(np.int32)
    objects = {k + 1: VisibleObject(k + 1, f"{names[k]} {k}", names[k]) for k in range(n)}
    rgb = np.full(labels.shape + (3,), (135, 190, 235), np.uint8)  # sky
    for k in range(n):
        rgb[labels == k] = colours[k]
    ann = FrameAnnotation(ids, depth, objects)
    return degraded_features(ann, rgb, frame, seed=seed, dim=dim, patch_px=patch).grid


def label_features(labels: np.ndarray, patch: int, dim: int, rng: np.random.Generator) -> np.ndarray:
    vec = rng.normal(size=(int(labels.max()) + 2, dim))
    vec /= np.linalg.norm(vec, axis=1, keepdims=True)
    h, w = labels.shape
    return vec[labels + 1].reshape(h // patch, patch, w // patch, patch, dim).mean(axis=(1, 3)).astype(np.float32)


# -- ground truth --------------------------------------------------------------------------------


def obstacle_points(camera: PinholeCamera, depth: np.ndarray, threshold_m: float) -> np.ndarray:
    d = depth.astype(np.float64)
    with np.errstate(invalid="ignore"):
        obst = np.isfinite(d) & (d > 0) & (d < threshold_m)
    return camera.rays()[obst] * d[obst][:, None]


def threshold_for(config: VerifierConfig, depth: np.ndarray, uv) -> float:
    col, row = int(math.floor(uv[0] + 0.5)), int(math.floor(uv[1] + 0.5))
    d = float(depth[row, col])
    ref = min(d, config.d_max_m) if (math.isfinite(d) and d > 0) else config.d_max_m
    return config.obstacle_threshold_m(ref)


def point_clearance(P: np.ndarray, X: np.ndarray) -> float:
    return float(np.min(np.linalg.norm(P - X, axis=1))) if len(P) else math.inf


def segment_clearance(P: np.ndarray, X: np.ndarray) -> float:
    if not len(P):
        return math.inf
    t = np.clip(P @ X / (X @ X), 0.0, 1.0)
    return float(np.min(np.linalg.norm(P - t[:, None] * X[None, :], axis=1)))


def naive_goal_cam(camera: PinholeCamera, depth: np.ndarray, uv, d_max_m: float) -> np.ndarray:
    """No verifier: the pixel lifted at ``min(depth, D_max)`` (D_max without a reading)."""
    col, row = int(math.floor(uv[0] + 0.5)), int(math.floor(uv[1] + 0.5))
    d = float(depth[row, col])
    rng_m = min(d, d_max_m) if (math.isfinite(d) and d > 0) else d_max_m
    return camera.back_project(np.asarray(uv, float), rng_m)


# -- the exhaustive reference --------------------------------------------------------------------


def _rule_points(cam, depth, config: VerifierConfig, surface: np.ndarray, d_m: float) -> tuple[np.ndarray, bool]:
    """Obstacle points of the documented rule referenced to depth ``d_m``: readings closer than
    T(d_m), except the target's surface at or beyond d_ref - margin when the near field reaches
    it. Returns (points (n, 3), whether anything was exempted)."""
    d_ref = min(d_m, config.d_max_m)
    T = config.obstacle_threshold_m(d_ref)
    z = depth.astype(np.float64)
    with np.errstate(invalid="ignore"):
        obst = np.isfinite(z) & (z > 0) & (z < T)
        exempted = False
        if config.obstacle_depth_m > d_ref - config.foreground_margin_m:
            ex = surface & (z >= d_ref - config.foreground_margin_m) & obst
            exempted = bool(ex.any())
            obst &= ~ex
    return cam.rays()[obst] * z[obst][:, None], exempted


def _clear_z(P_all: np.ndarray, direction: np.ndarray, limit_z: float, r: float) -> float:
    """Z-depth where the unit ray ``direction`` first comes within r of a point (brute force)."""
    a = P_all @ direction
    q2 = np.einsum("ij,ij->i", P_all, P_all) - a * a
    hit = q2 < r * r
    entry = float(np.min(a[hit] - np.sqrt(r * r - q2[hit]))) if hit.any() else math.inf
    return min(limit_z, max(entry, 0.0) * direction[2])


def reference_refine(cand: CandidateGoal, config: VerifierConfig):
    """Exact answer of step 1 by brute force: the nearest pixel of the semantic component (ROI,
    pixel-level cosine mask, scipy 4-connected labelling) whose ray clears by r every obstacle
    point of the image under the rule referenced to the target *and* under the rule at its own
    depth (:mod:`planning.verifier_config`), and, when the near field reaches its surface,
    whose clear part of the ray is at least ``min_range_m``. Returns (pixel (u, v) or None,
    seconds). Only for d <= D_max with features; the target's surface comes from
    :func:`planning.verifier.surface_region` over the whole image."""
    from planning.verifier import surface_region

    t0 = time.perf_counter()
    cam, depth = cand.camera, cand.depth_m
    u, v = cand.pixel_uv
    col, row = int(math.floor(u + 0.5)), int(math.floor(v + 0.5))
    half = config.roi_px // 2
    r0, r1 = max(0, row - half), min(cam.height, row - half + config.roi_px)
    c0, c1 = max(0, col - half), min(cam.width, col - half + config.roi_px)
    p = cand.patch_px
    rows, cols = np.arange(r0, r1), np.arange(c0, c1)
    feats = cand.features[np.ix_((rows // p).astype(int), (cols // p).astype(int))].astype(np.float64)
    f_p = cand.features[int(row // p), int(col // p)].astype(np.float64)
    sim = feats @ f_p / (np.linalg.norm(feats, axis=-1) * np.linalg.norm(f_p))
    mask = sim >= config.tau
    mask[row - r0, col - c0] = True
    lab, _ = ndimage.label(mask)
    comp = lab == lab[row - r0, col - c0]
    roi_depth = depth[r0:r1, c0:c1]
    comp &= np.isfinite(roi_depth) & (roi_depth > 0)
    surface = surface_region(depth, row, col, config.surface_jump_ratio, config.foreground_margin_m)
    d = float(depth[row, col])
    r = config.clearance_radius_m
    P, _ = _rule_points(cam, depth, config, surface, d)
    z_all = depth.astype(np.float64)
    with np.errstate(invalid="ignore"):
        readings = np.isfinite(z_all) & (z_all > 0) & (z_all < config.d_max_m + r + 1e-6)
    P_all = cam.rays()[readings] * z_all[readings][:, None]
    own_cache: dict[float, tuple[np.ndarray, bool, float]] = {}

    def own_ok(q_uv, direction) -> bool:
        dq = float(depth[int(q_uv[1]), int(q_uv[0])])
        if dq not in own_cache:
            P_q, ex = _rule_points(cam, depth, config, surface, dq)
            own_cache[dq] = (near_roi(P_q), ex, config.obstacle_threshold_m(min(dq, config.d_max_m)))
        P_q, ex, T_q = own_cache[dq]
        near_reaches = config.obstacle_depth_m > min(dq, config.d_max_m) - config.foreground_margin_m
        is_obstacle = dq < T_q and not (near_reaches and surface[int(q_uv[1]), int(q_uv[0])])
        if is_obstacle or not _ray_ok(P_q, direction[None, :], r)[0]:
            return False
        return not (ex and _clear_z(P_all, direction, min(dq, config.d_max_m), r) < config.min_range_m)

    # Exact, loss-free prefilter: a point farther (in angle) from the ROI's central ray than the
    # ROI's angular radius plus its own asin(r / |Y|) cannot come within r of any ROI ray.
    rr_roi, cc_roi = np.mgrid[r0:r1, c0:c1]
    roi_dirs = np.stack([(cc_roi.ravel() - cam.cx) / cam.fx, (rr_roi.ravel() - cam.cy) / cam.fy, np.ones(rr_roi.size)], axis=1)
    roi_dirs /= np.linalg.norm(roi_dirs, axis=1, keepdims=True)
    centre = roi_dirs.mean(axis=0)
    centre /= np.linalg.norm(centre)
    roi_ang = float(np.max(np.arccos(np.clip(roi_dirs @ centre, -1, 1))))

    def near_roi(points: np.ndarray) -> np.ndarray:
        if not len(points):
            return points
        rng_p = np.linalg.norm(points, axis=1)
        ang = np.arccos(np.clip(points @ centre / rng_p, -1, 1))
        return points[ang - roi_ang <= np.arcsin(np.clip(r / rng_p, 0, 1)) + 1e-9]

    P, P_all = near_roi(P), near_roi(P_all)
    rr, cc = np.nonzero(comp)
    order = np.argsort((cc + c0 - u) ** 2 + (rr + r0 - v) ** 2, kind="stable")
    cand_uv = np.stack([cc[order] + c0, rr[order] + r0], axis=1).astype(float)
    # Candidates must not be obstacles under the target's rule either.
    T_p = config.obstacle_threshold_m(min(d, config.d_max_m))
    zc = depth[cand_uv[:, 1].astype(int), cand_uv[:, 0].astype(int)]
    exempt_c = surface[cand_uv[:, 1].astype(int), cand_uv[:, 0].astype(int)] & (zc >= min(d, config.d_max_m) - config.foreground_margin_m)
    keep = ~((zc < T_p) & ~(exempt_c & (config.obstacle_depth_m > min(d, config.d_max_m) - config.foreground_margin_m)))
    cand_uv = cand_uv[keep]
    d0 = cam.back_project(np.array([u, v]), 1.0)
    d0 /= np.linalg.norm(d0)
    if _ray_ok(P, d0[None, :], r)[0] and own_ok((col, row), d0):
        return (u, v), time.perf_counter() - t0
    dirs = np.stack([(cand_uv[:, 0] - cam.cx) / cam.fx, (cand_uv[:, 1] - cam.cy) / cam.fy, np.ones(len(cand_uv))], axis=1)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    for s in range(0, len(dirs), 64):
        ok = _ray_ok(P, dirs[s : s + 64], r)
        for k in np.flatnonzero(ok):
            if own_ok(cand_uv[s + k], dirs[s + k]):
                return (float(cand_uv[s + k, 0]), float(cand_uv[s + k, 1])), time.perf_counter() - t0
    return None, time.perf_counter() - t0


def _ray_ok(P: np.ndarray, dirs: np.ndarray, r: float) -> np.ndarray:
    """For unit ray directions (m, 3): True where the half-line clears every point by r."""
    if len(P) == 0:
        return np.ones(len(dirs), bool)
    t = np.maximum(P @ dirs.T, 0.0)  # (n, m)
    d2 = np.sum(P * P, axis=1)[:, None] - 2.0 * t * (P @ dirs.T) + t * t
    return np.all(d2 >= r * r - 1e-12, axis=0)


# -- main ----------------------------------------------------------------------------------------


SOURCES = ("ground_truth", "degraded", "none")


def run(args) -> dict:
    rng = np.random.default_rng(args.seed)
    cam = PinholeCamera.from_fov(args.width, args.height, 90.0, 60.0)
    config = VerifierConfig()
    ver = Verifier(config)
    r = config.clearance_radius_m
    times_us: list[float] = []
    moved_us: list[float] = []
    sigmas: list[float] = []
    error_model = get_preset(args.error_model)
    counts = Counter()
    shifts, ref_rows = [], []
    per_source = {name: Counter() for name in SOURCES}
    for _scene in range(args.scenes):
        depth, labels, targets = make_scene(rng, cam, args.min_target_px)
        feats = label_features(labels, args.patch, args.feature_dim, rng)
        source_feats = {
            "ground_truth": feats,
            "degraded": degraded_scene_features(labels, depth, args.patch, args.feature_dim, args.seed, f"scene{_scene}"),
            "none": None,
        }
        T = cam_transform_from_body(body_transform(rng.uniform(-20, 20, 3), rng.uniform(-math.pi, math.pi)))
        T_cam_world = invert_transform(T)
        for _ in range(args.candidates):
            target = int(rng.choice(targets))
            pix = np.argwhere(labels == target)
            if args.pointing == "centroid":  # the simulated VLM's rule: region pixel nearest the centroid
                row_t, col_t = pix[np.argmin(np.sum((pix - pix.mean(axis=0)) ** 2, axis=1))]
            else:  # stress: anywhere on the target, edges included
                row_t, col_t = pix[rng.integers(len(pix))]
            if args.noise_px is None:
                sigma = error_model.pixel_sigma_px(cam.width, float(np.median(depth[labels == target])))
            else:
                sigma = args.noise_px
            sigmas.append(sigma)
            while True:
                uv = (col_t + rng.normal(0, sigma), row_t + rng.normal(0, sigma))
                if -0.5 <= uv[0] < cam.width - 0.5 and -0.5 <= uv[1] < cam.height - 0.5:
                    break
            cand = CandidateGoal(uv, depth, feats, float(args.patch), T, cam)
            t0 = time.perf_counter()
            res = ver.verify(cand)
            times_us.append((time.perf_counter() - t0) * 1e6)

            P_true = obstacle_points(cam, depth, threshold_for(config, depth, (col_t, row_t)))
            on_target_px = labels[int(math.floor(uv[1] + 0.5)), int(math.floor(uv[0] + 0.5))] == target
            for name, f_src in source_feats.items():
                c = per_source[name]
                r_src = res if name == "ground_truth" else ver.verify(CandidateGoal(uv, depth, f_src, float(args.patch), T, cam))
                c["n"] += 1
                if not r_src.accepted:
                    c["rejected"] += 1
                    continue
                c["accepted"] += 1
                X_src = transform_points(T_cam_world, r_src.goal_world)
                c["unsafe"] += point_clearance(P_true, X_src) < r
                c["path_unsafe"] += segment_clearance(P_true, X_src) < r
                u_s, v_s = r_src.record.refined_uv
                kept_src = labels[int(math.floor(v_s + 0.5)), int(math.floor(u_s + 0.5))] == target
                c["off_target"] += not kept_src
                c["moved_off_target"] += bool(on_target_px and not kept_src)
            X_naive = naive_goal_cam(cam, depth, uv, config.d_max_m)
            counts["n"] += 1
            counts["unsafe_before"] += point_clearance(P_true, X_naive) < r
            counts["path_unsafe_before"] += segment_clearance(P_true, X_naive) < r
            counts["on_target_before"] += labels[int(math.floor(uv[1] + 0.5)), int(math.floor(uv[0] + 0.5))] == target
            rec = res.record
            counts[f"note:{rec.refinement_note.value}"] += 1
            if not res.accepted:
                counts[f"rejected:{rec.rejection.value}"] += 1
                if rec.rejection.value == "no_feasible_pixel" and counts["ref_rejections"] < args.reference_samples:
                    counts["ref_rejections"] += 1
                    counts["ref_rejections_exact_found"] += reference_refine(cand, config)[0] is not None
                continue
            counts["accepted"] += 1
            X = transform_points(T_cam_world, res.goal_world)
            P_own = obstacle_points(cam, depth, rec.obstacle_threshold_m)
            unsafe_after = point_clearance(P_true, X) < r
            counts["unsafe_after"] += unsafe_after
            # An unsafe goal after the verifier whose noisy pixel was not on the target at all:
            # the verifier trusted the wrong object (it cannot know the instruction's target).
            on_target = labels[int(math.floor(uv[1] + 0.5)), int(math.floor(uv[0] + 0.5))] == target
            counts["unsafe_after_pixel_off_target"] += unsafe_after and not on_target
            counts["path_unsafe_after"] += segment_clearance(P_true, X) < r
            counts["unsafe_after_own_rule"] += point_clearance(P_own, X) < r
            counts["path_unsafe_after_own_rule"] += segment_clearance(P_own, X) < r
            u2, v2 = rec.refined_uv
            kept = labels[int(math.floor(v2 + 0.5)), int(math.floor(u2 + 0.5))] == target
            counts["region_kept"] += kept
            if rec.pixel_shift_px > 0:
                counts["moved"] += 1
                moved_us.append(times_us[-1])
                shifts.append(rec.pixel_shift_px)
                if labels[int(math.floor(uv[1] + 0.5)), int(math.floor(uv[0] + 0.5))] == target:
                    counts["moved_from_target"] += 1
                    counts["moved_from_target_kept"] += kept
            if rec.refinement_ran and rec.pixel_shift_px > 0 and len(ref_rows) < args.reference_samples:
                ref_uv, ref_s = reference_refine(cand, config)
                t0 = time.perf_counter()
                ver.verify(cand)
                fast_s = time.perf_counter() - t0
                ref_shift = math.hypot(ref_uv[0] - uv[0], ref_uv[1] - uv[1]) if ref_uv else math.nan
                ref_rows.append((fast_s * 1e6, ref_s * 1e6, rec.pixel_shift_px, ref_shift))

    n = counts["n"]
    acc = max(counts["accepted"], 1)
    sources_out = {
        name: {
            "candidates": c["n"],
            "accept_rate": c["accepted"] / max(c["n"], 1),
            "unsafe_rate": c["unsafe"] / max(c["n"], 1),
            "path_unsafe_rate": c["path_unsafe"] / max(c["n"], 1),
            "off_target_rate": c["off_target"] / max(c["n"], 1),
            "moved_off_target_rate": c["moved_off_target"] / max(c["n"], 1),
        }
        for name, c in per_source.items()
    }
    ref = np.array(ref_rows) if ref_rows else np.zeros((0, 4))
    finite = ref[np.isfinite(ref[:, 3])] if len(ref) else ref
    out = {
        "setup": {
            "seed": args.seed,
            "scenes": args.scenes,
            "candidates": n,
            "image": [args.width, args.height],
            "patch_px": args.patch,
            "feature_grid": [args.height // args.patch, args.width // args.patch, args.feature_dim],
            "pointing": args.pointing,
            "noise": f"{args.noise_px} px" if args.noise_px is not None else f"error model {args.error_model}",
            "noise_px_median": statistics.median(sigmas),
            "config": {k: getattr(config, k) for k in config.__dataclass_fields__},
            "loadavg_1min": os.getloadavg()[0],
            "calibration_sqrt_1e6_us": calibration_us(),
            "cpu_count": os.cpu_count(),
        },
        "verify_us_median": statistics.median(times_us),
        "verify_us_p90": float(np.percentile(times_us, 90)),
        "verify_us_max": max(times_us),
        "verify_us_median_when_moved": statistics.median(moved_us) if moved_us else math.nan,
        "unsafe_rate_before": counts["unsafe_before"] / n,
        "unsafe_rate_after": counts["unsafe_after"] / n,
        "unsafe_rate_after_own_rule": counts["unsafe_after_own_rule"] / n,
        "unsafe_after_pixel_off_target": counts["unsafe_after_pixel_off_target"],
        "unsafe_after_count": counts["unsafe_after"],
        "path_unsafe_rate_before": counts["path_unsafe_before"] / n,
        "path_unsafe_rate_after": counts["path_unsafe_after"] / n,
        "path_unsafe_rate_after_own_rule": counts["path_unsafe_after_own_rule"] / n,
        "region_kept_rate": counts["region_kept"] / acc,
        "region_kept_rate_when_moved_from_target": (
            counts["moved_from_target_kept"] / counts["moved_from_target"] if counts["moved_from_target"] else math.nan
        ),
        "on_target_rate_before": counts["on_target_before"] / n,
        "accept_rate": counts["accepted"] / n,
        "moved_rate": counts["moved"] / n,
        "shift_px_median_when_moved": statistics.median(shifts) if shifts else 0.0,
        "per_source": sources_out,
        "notes": {k[5:]: v for k, v in sorted(counts.items()) if k.startswith("note:")},
        "rejections": {k[9:]: v for k, v in sorted(counts.items()) if k.startswith("rejected:")},
        "reference": {
            "samples": len(ref),
            "fast_us_median": float(np.median(ref[:, 0])) if len(ref) else math.nan,
            "exhaustive_us_median": float(np.median(ref[:, 1])) if len(ref) else math.nan,
            "speedup_median": float(np.median(ref[:, 1] / ref[:, 0])) if len(ref) else math.nan,
            "exact_found": len(finite),
            "extra_shift_px_median": float(np.median(finite[:, 2] - finite[:, 3])) if len(finite) else math.nan,
            "extra_shift_px_p90": float(np.percentile(finite[:, 2] - finite[:, 3], 90)) if len(finite) else math.nan,
            "fast_never_closer_than_exact": bool(np.all(finite[:, 2] >= finite[:, 3] - 1e-9)) if len(finite) else True,
            "no_feasible_rejections_checked": counts["ref_rejections"],
            "no_feasible_but_exact_pixel_exists": counts["ref_rejections_exact_found"],
        },
    }
    return out


def calibration_us(reps: int = 20) -> float:
    """Median time of a fixed numpy workload (sqrt of 10^6 floats), to compare machines/loads."""
    x = np.arange(1_000_000, dtype=np.float64)
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        np.sqrt(x)
        times.append((time.perf_counter() - t0) * 1e6)
    return statistics.median(times)


def print_table(out: dict) -> None:
    rows = [
        ("verify_us_median", f"{out['verify_us_median']:.0f}", "< 2000"),
        ("verify_us_p90", f"{out['verify_us_p90']:.0f}", ""),
        ("verify_us_median_when_moved", f"{out['verify_us_median_when_moved']:.0f}", ""),
        ("unsafe_rate_before", f"{out['unsafe_rate_before']:.4f}", ""),
        ("unsafe_rate_after", f"{out['unsafe_rate_after']:.4f}", "= 0"),
        ("  of which noisy pixel was off the target", f"{out['unsafe_after_pixel_off_target']} / {out['unsafe_after_count']}", ""),
        ("unsafe_rate_after_own_rule", f"{out['unsafe_rate_after_own_rule']:.4f}", "= 0 (guarantee)"),
        ("path_unsafe_rate_before", f"{out['path_unsafe_rate_before']:.4f}", ""),
        ("path_unsafe_rate_after", f"{out['path_unsafe_rate_after']:.4f}", ""),
        ("region_kept_rate", f"{out['region_kept_rate']:.4f}", ">= 0.95"),
        ("region_kept_rate_when_moved_from_target", f"{out['region_kept_rate_when_moved_from_target']:.4f}", ""),
        ("on_target_rate_before", f"{out['on_target_rate_before']:.4f}", ""),
        ("accept_rate", f"{out['accept_rate']:.4f}", ""),
        ("moved_rate", f"{out['moved_rate']:.4f}", ""),
        ("shift_px_median_when_moved", f"{out['shift_px_median_when_moved']:.1f}", ""),
    ]
    ref = out["reference"]
    rows += [
        ("reference samples (moved)", str(ref["samples"]), ""),
        ("  fast path us (median)", f"{ref['fast_us_median']:.0f}", ""),
        ("  exhaustive exact us (median)", f"{ref['exhaustive_us_median']:.0f}", ""),
        ("  speed-up (median)", f"{ref['speedup_median']:.1f}x", ""),
        ("  extra shift vs exact px (median / p90)", f"{ref['extra_shift_px_median']:.1f} / {ref['extra_shift_px_p90']:.1f}", ">= 0"),
        (
            "  no_feasible rejections with an exact pixel",
            f"{ref['no_feasible_but_exact_pixel_exists']} / {ref['no_feasible_rejections_checked']}",
            "conservative map",
        ),
    ]
    width = max(len(r[0]) for r in rows)
    s = out["setup"]
    print(
        f"verifier bench: {s['candidates']} candidates in {s['scenes']} scenes, {s['image'][0]}x{s['image'][1]}, "
        f"{s['feature_grid'][1]}x{s['feature_grid'][0]} patches, pointing {s['pointing']}, noise {s['noise']} "
        f"(median {s['noise_px_median']:.1f} px), load {s['loadavg_1min']:.1f}, "
        f"sqrt(1e6 floats) {s['calibration_sqrt_1e6_us']:.0f} us "
        f"on {s['cpu_count']} cpus"
    )
    for name, value, target in rows:
        print(f"  {name:<{width}}  {value:>12}  {target}")
    print(f"  refinement notes: {out['notes']}")
    print("  per feature source (same candidates; rates over all candidates):")
    print(f"    {'source':<13} {'accept':>8} {'unsafe':>8} {'path_unsafe':>12} {'off_target':>11} {'moved_off':>10}")
    for name, m in out["per_source"].items():
        print(f"    {name:<13} {m['accept_rate']:>8.4f} {m['unsafe_rate']:>8.4f} {m['path_unsafe_rate']:>12.4f} "
              f"{m['off_target_rate']:>11.4f} {m['moved_off_target_rate']:>10.4f}")
    print(f"  rejections: {out['rejections']}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--scenes", type=int, default=60)
    ap.add_argument("--candidates", type=int, default=25, help="candidates per scene")
    ap.add_argument("--pointing", choices=("centroid", "uniform"), default="centroid",
                    help="true target pixel: nearest the region centroid (the simulated VLM) or uniform on it")
    ap.add_argument("--error-model", default="nominal", help="vlm.sim error-model preset giving the noise std")
    ap.add_argument("--noise-px", type=float, default=None, help="fixed noise std in pixels (overrides --error-model)")
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--patch", type=int, default=16)
    ap.add_argument("--feature-dim", type=int, default=256)
    ap.add_argument("--min-target-px", type=int, default=1500)
    ap.add_argument("--reference-samples", type=int, default=40)
    ap.add_argument("--json", type=str, default=None, help="write the results here")
    args = ap.parse_args(argv)
    out = run(args)
    print_table(out)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(out, fh, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
