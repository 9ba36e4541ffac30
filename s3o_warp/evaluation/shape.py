"""3D shape scores against synthetic ground truth: one similarity aligns the prediction to the ground truth, then
Chamfer distance and F-score per frame.

The alignment (:func:`align_similarity`) is one similarity (scale, rotation, translation) for the whole sequence:
median-depth scale, then symmetric ICP with Umeyama steps (:func:`umeyama`); :func:`frame_similarities` adds one
per frame on top of it. :func:`shape_metrics` scores per-frame Chamfer distance (mean of both directions, not
squared) and F-score at 2% of the ground truth's bounding-box diagonal (:func:`bbox_diagonal`), on area-weighted
surface samples (:func:`sample_surface`); both normalised per frame, then averaged.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree


def sample_surface(verts: np.ndarray, faces: np.ndarray, n: int, seed=0) -> np.ndarray:
    """Area-weighted uniform samples on a triangle mesh.

    Args:
        verts: float (V, 3).
        faces: int (F, 3).
        n: number of samples.
        seed: anything ``np.random.default_rng`` accepts; the same seed on meshes with the same
            topology and proportional face areas gives corresponding points.

    Returns:
        float64 (n, 3) points (the vertices themselves when every face is degenerate).
    """
    return sample_surface_faces(verts, faces, n, seed)[0]


def sample_surface_faces(verts: np.ndarray, faces: np.ndarray, n: int, seed=0) -> tuple[np.ndarray, np.ndarray]:
    """:func:`sample_surface`'s points (the same ones for the same seed) and the index of each one's face
    (int64 (n,); 0 when every face is degenerate)."""
    v = np.asarray(verts, dtype=np.float64)
    tri = v[np.asarray(faces, dtype=np.int64)]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=-1)
    rng = np.random.default_rng(seed)
    if not np.isfinite(area).all() or area.sum() <= 0:
        return v[rng.integers(0, v.shape[0], n)], np.zeros(n, np.int64)
    cdf = np.cumsum(area)
    f = np.minimum(np.searchsorted(cdf, rng.random(n) * cdf[-1], side="right"), len(area) - 1)
    r1, r2 = np.sqrt(rng.random(n)), rng.random(n)
    w = np.stack([1.0 - r1, r1 * (1.0 - r2), r1 * r2], axis=1)
    return np.einsum("nk,nkc->nc", w, tri[f]), f.astype(np.int64)


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity with ``dst ~ s * R @ src + t`` (Umeyama 1991).

    Args:
        src, dst: float (N, 3) corresponding points.
        with_scale: estimate s (else s = 1).

    Returns:
        ``(s, R, t)``: scale, float64 (3, 3) rotation (det +1), float64 (3,) translation.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / src.shape[0]
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    var_s = (xs**2).sum() / src.shape[0]
    s = float((D * np.diag(S)).sum() / var_s) if with_scale and var_s > 0 else 1.0
    return s, R, mu_d - s * R @ mu_s


@dataclass(frozen=True)
class Similarity:
    """``x -> scale * rotation @ x + translation`` (applied to predictions, camera space)."""

    scale: float
    rotation: np.ndarray
    translation: np.ndarray

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """Apply to float (..., 3) points."""
        return self.scale * np.asarray(x, dtype=np.float64) @ self.rotation.T + self.translation


def align_similarity(pred_points: list[np.ndarray], gt_points: list[np.ndarray], iters: int = 50,
                     init_scale: float | None = None) -> tuple[Similarity, dict]:
    """One similarity for a whole sequence: median-depth scale, then symmetric ICP (Umeyama steps).

    Nearest neighbours are searched within the same frame only, over all frames jointly.

    Args:
        pred_points: T float (n_t, 3) predicted surface samples per frame, camera space.
        gt_points: T float (m_t, 3) ground-truth samples of the same frames.
        iters: ICP iterations after the initial scale.
        init_scale: starting scale about the camera centre; default median GT depth / median
            predicted depth.

    Returns:
        ``(similarity, info)``: the transform with the lowest symmetric mean nearest distance seen
        (the initial guess included), and ``{"init_scale", "iterations", "cost_init", "cost"}``.
    """
    P = np.concatenate(pred_points)
    G = np.concatenate(gt_points)
    if init_scale is None:
        zp, zg = np.median(P[:, 2]), np.median(G[:, 2])
        init_scale = float(zg / zp) if zp > 0 and zg > 0 else 1.0
    sim = Similarity(float(init_scale), np.eye(3), np.zeros(3))
    gt_trees = [cKDTree(g) for g in gt_points]
    p_off = np.cumsum([0] + [len(p) for p in pred_points])
    g_off = np.cumsum([0] + [len(g) for g in gt_points])
    best, best_cost, cost0, done = sim, math.inf, None, 0
    for it in range(iters + 1):
        Pa = sim(P)
        d1, i1, d2, i2 = [], [], [], []
        for t, tree in enumerate(gt_trees):  # nearest neighbours within the same frame only
            pa = Pa[p_off[t]:p_off[t + 1]]
            d, i = tree.query(pa)
            d1.append(d)
            i1.append(i + g_off[t])
            d, i = cKDTree(pa).query(gt_points[t])
            d2.append(d)
            i2.append(i + p_off[t])
        d1, i1, d2, i2 = (np.concatenate(x) for x in (d1, i1, d2, i2))
        cost = 0.5 * (d1.mean() + d2.mean())
        if cost0 is None:
            cost0 = cost
        improved = cost < best_cost * (1.0 - 1e-6)
        if cost < best_cost:
            best, best_cost = sim, cost
        if (not improved and it > 0) or it == iters:
            break
        s, R, t = umeyama(np.concatenate([P, P[i2]]), np.concatenate([G[i1], G]))
        sim = Similarity(s, R, t)
        done = it + 1
    info = {"init_scale": float(init_scale), "iterations": done, "cost_init": float(cost0), "cost": float(best_cost)}
    return best, info


def frame_similarities(pred_verts: np.ndarray, pred_faces: np.ndarray, gt_verts: np.ndarray, gt_faces: np.ndarray,
                       sim: Similarity, n_points: int = 3000, iters: int = 30, seed: int = 0) -> list[Similarity]:
    """One similarity per frame: the sequence's ``sim``, then ICP on that frame alone (:func:`align_similarity`
    from scale 1). It takes out what one sequence-wide alignment cannot: each frame's own error of the fitted
    root pose, depth and scale (monocular depth and the camera's path), so what is left is the articulation.

    Args:
        pred_verts: float (T, N, 3) predicted camera-space vertices.
        pred_faces: int (F, 3).
        gt_verts: float (T, V, 3) ground-truth vertices of the same frames.
        gt_faces: int (G, 3).
        sim: the sequence's alignment (from :func:`shape_metrics`), applied first.
        n_points: surface samples per frame and mesh.
        iters: ICP iterations per frame.
        seed: sampling seed (frame t uses ``[seed, t, 2]``).

    Returns:
        T similarities, each mapping the frame's predictions (camera space) onto the ground truth.
    """
    out = []
    for t in range(pred_verts.shape[0]):
        p = sim(sample_surface(pred_verts[t], pred_faces, n_points, [seed, t, 2]))
        g = sample_surface(gt_verts[t], gt_faces, n_points, [seed, t, 2])
        f, _ = align_similarity([p], [g], iters=iters, init_scale=1.0)
        # f(sim(x)) = f.s R_f (sim.s R x + sim.t) + f.t
        out.append(Similarity(f.scale * sim.scale, f.rotation @ sim.rotation,
                              f.scale * f.rotation @ sim.translation + f.translation))
    return out


def chamfer_fscore(pred: np.ndarray, gt: np.ndarray, threshold: float) -> dict:
    """Symmetric Chamfer distance and F-score between two point sets (same units, not normalised).

    Args:
        pred: float (n, 3) predicted points.
        gt: float (m, 3) ground-truth points.
        threshold: F-score distance threshold.

    Returns:
        ``{"chamfer": 0.5 * (mean_p min_g |p - g| + mean_g min_p |g - p|), "precision", "recall",
        "fscore"}`` (precision: fraction of pred within threshold of gt; recall the reverse).
    """
    d_pg, _ = cKDTree(gt).query(pred)
    d_gp, _ = cKDTree(pred).query(gt)
    prec = float((d_pg < threshold).mean())
    rec = float((d_gp < threshold).mean())
    f = 2 * prec * rec / (prec + rec) if prec + rec > 0 else 0.0
    return {"chamfer": float(0.5 * (d_pg.mean() + d_gp.mean())), "precision": prec, "recall": rec, "fscore": f}


def bbox_diagonal(verts: np.ndarray) -> np.ndarray:
    """Bounding-box diagonal per frame: float (T, V, 3) -> float64 (T,)."""
    v = np.asarray(verts, dtype=np.float64)
    return np.linalg.norm(v.max(axis=1) - v.min(axis=1), axis=-1)


def shape_metrics(pred_verts: np.ndarray, pred_faces: np.ndarray, gt_verts: np.ndarray, gt_faces: np.ndarray,
                  n_points: int = 5000, fscore_ratio: float = 0.02, icp_iters: int = 50,
                  icp_points: int = 10000, seed: int = 0) -> tuple[dict, Similarity]:
    """Chamfer and F-score per frame after one sequence-wide similarity alignment.

    Args:
        pred_verts: float (T, N, 3) predicted camera-space vertices.
        pred_faces: int (F, 3).
        gt_verts: float (T, V, 3) ground-truth camera-space vertices of the same frames.
        gt_faces: int (G, 3).
        n_points: surface samples per frame and mesh for the scores.
        fscore_ratio: F-score threshold as a fraction of the ground truth's bbox diagonal.
        icp_iters: ICP iterations.
        icp_points: samples per mesh over all frames together used to fit the alignment.
        seed: sampling seed (frame t uses ``[seed, t]``).

    Returns:
        ``(metrics, similarity)``: metrics has ``chamfer`` and ``fscore`` (means over frames,
        Chamfer over the per-frame bbox diagonal), ``precision``, ``recall``, per-frame lists
        ``chamfer_per_frame`` and ``fscore_per_frame``, ``fscore_ratio`` and ``alignment``
        (scale, rotation, translation and ICP info).
    """
    T = pred_verts.shape[0]
    if gt_verts.shape[0] != T:
        raise ValueError(f"shape_metrics(): {T} predicted frames but {gt_verts.shape[0]} ground-truth frames")
    n_icp = max(100, int(icp_points) // T)
    pp = [sample_surface(pred_verts[t], pred_faces, n_icp, [seed, t, 1]) for t in range(T)]
    gp = [sample_surface(gt_verts[t], gt_faces, n_icp, [seed, t, 1]) for t in range(T)]
    sim, info = align_similarity(pp, gp, iters=icp_iters)
    diag = bbox_diagonal(gt_verts)
    rows = []
    for t in range(T):
        p = sim(sample_surface(pred_verts[t], pred_faces, n_points, [seed, t]))
        g = sample_surface(gt_verts[t], gt_faces, n_points, [seed, t])
        r = chamfer_fscore(p, g, fscore_ratio * diag[t])
        r["chamfer"] /= diag[t]
        rows.append(r)
    out = {k: float(np.mean([r[k] for r in rows])) for k in ("chamfer", "fscore", "precision", "recall")}
    out["chamfer_per_frame"] = [r["chamfer"] for r in rows]
    out["fscore_per_frame"] = [r["fscore"] for r in rows]
    out["fscore_ratio"] = fscore_ratio
    out["alignment"] = {"scale": sim.scale, "rotation": sim.rotation.tolist(),
                        "translation": sim.translation.tolist(), **info}
    return out, sim

