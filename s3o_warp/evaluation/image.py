"""Image-space scores: mask IoU of the hard render, and PCK-T keypoint transfer.

* Mask IoU per frame (:func:`mask_iou`): the hard render (face index >= 0, :func:`render_frames`) of the
  prediction at full-frame size against the ground-truth mask.
* PCK-T (:func:`pck_transfer`) as LASR/ViSER score BADJA (``scripts/eval_badja.py`` / ``eval_pck.py``): every
  ordered pair (i, j), i != j, of annotated frames; every keypoint visible in both; the surface point under the
  keypoint in frame i (z-buffer render; nearest rendered foreground pixel when the keypoint is off the
  silhouette, :func:`surface_under_keypoints`) is carried to frame j: prediction = keypoint_i + proj_j(X) -
  proj_i(X). Correct when closer than ``alpha * sqrt(mask area)`` to the keypoint in frame j; micro-averaged,
  percent.
"""

from __future__ import annotations

from typing import Iterator, Literal

import numpy as np
import torch
from scipy.spatial import cKDTree
from tqdm.auto import tqdm

from s3o_warp import interrupt
from s3o_warp.geometry import project_np
from s3o_warp.ops import rasterize


def render_frames(verts: np.ndarray, faces: np.ndarray, K: np.ndarray, image_size: tuple[int, int],
                  chunk: int = 8, device: str = "cpu", progress: bool = True, rasterizer=None
                  ) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
    """Z-buffer renders of a mesh sequence, ``chunk`` frames at a time (bounded memory).

    Args:
        verts: float32 (T, V, 3) vertices, OpenCV camera frame.
        faces: int32 (F, 3).
        K: float32 (T, 3, 3) full-frame intrinsics, pixels.
        image_size: (H, W).
        chunk: frames per ``rasterize`` call.
        device: torch device of the render (``cpu`` or ``cuda:N``).
        progress: show a tqdm bar.
        rasterizer: the z-buffer op, default ``s3o_warp.kernels.raster.rasterize``; any callable
            with its signature (e.g. ``s3o_warp.reference.raster.rasterize_reference``).

    Yields:
        ``(start, face_index, bary)``: frames ``start .. start + c``; face_index int32 (c, H, W),
        ``face_index[t, r, c] = f`` means face f is nearest at pixel (column c, row r), -1 =
        background; bary float32 (c, H, W, 3) perspective-correct barycentrics of that face's
        vertices ``faces[f]``.
    """
    if rasterizer is None:
        rasterizer = rasterize
    T = verts.shape[0]
    f_t = torch.as_tensor(np.ascontiguousarray(faces, dtype=np.int32), device=device)
    bar = tqdm(total=T, desc="render", unit="frame", leave=False, disable=not progress)
    try:
        for s in range(0, T, max(1, int(chunk))):
            interrupt.check("the evaluation's renders")
            e = min(T, s + max(1, int(chunk)))
            v_t = torch.as_tensor(np.ascontiguousarray(verts[s:e], dtype=np.float32), device=device)
            k_t = torch.as_tensor(np.ascontiguousarray(K[s:e], dtype=np.float32), device=device)
            with torch.no_grad():
                fi, bary, _depth = rasterizer(v_t, f_t, k_t, image_size=tuple(int(x) for x in image_size))
            yield s, fi.cpu().numpy().astype(np.int32, copy=False), bary.cpu().numpy().astype(np.float32, copy=False)
            bar.update(e - s)
    finally:
        bar.close()


def mask_iou(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Intersection over union per frame.

    Args:
        pred: bool (T, H, W) predicted foreground.
        gt: bool (T, H, W) ground-truth foreground.

    Returns:
        float64 (T,) IoU in [0, 1]; a frame where both masks are empty scores 1.
    """
    pred = np.asarray(pred, dtype=bool)
    gt = np.asarray(gt, dtype=bool)
    if pred.shape != gt.shape:
        raise ValueError(f"mask_iou(): pred and gt shapes differ ({pred.shape} vs {gt.shape})")
    inter = np.logical_and(pred, gt).reshape(pred.shape[0], -1).sum(1)
    union = np.logical_or(pred, gt).reshape(pred.shape[0], -1).sum(1)
    return np.where(union > 0, inter / np.maximum(union, 1), 1.0)


def surface_under_keypoints(face_index: np.ndarray, bary: np.ndarray, xy: np.ndarray
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rendered surface point under each keypoint (LASR's nearest-foreground-pixel rule).

    Args:
        face_index: int (H, W) z-buffer face ids, -1 background.
        bary: float (H, W, 3) perspective-correct barycentrics.
        xy: float (P, 2) keypoints (x = column, y = row), full-frame pixels.

    Returns:
        ``(face, w, pixel)``: int64 (P,) face under the keypoint, float64 (P, 3) its barycentrics,
        int64 (P, 2) the (column, row) of the pixel used: the rendered foreground pixel whose centre
        is nearest to the keypoint (the pixel containing it when that pixel is foreground). Every
        face is -1 (and w 0) when the render has no foreground.
    """
    rows, cols = np.nonzero(face_index >= 0)
    P = xy.shape[0]
    if rows.size == 0:
        return np.full(P, -1, np.int64), np.zeros((P, 3)), np.zeros((P, 2), np.int64)
    tree = cKDTree(np.stack([cols, rows], axis=1).astype(np.float64))
    _, k = tree.query(np.asarray(xy, dtype=np.float64).reshape(P, 2))
    r, c = rows[k], cols[k]
    return face_index[r, c].astype(np.int64), bary[r, c].astype(np.float64), np.stack([c, r], axis=1).astype(np.int64)


GAP_BANDS = (1, 4, 12, 24)
"""PCK-T is also counted by how many video frames apart the two frames of a pair are: 1-3, 4-11, 12-23, 24 and more.
A fit whose surface and pose are right only locally scores well on near pairs and falls off with the gap."""


def pck_transfer(keypoints: np.ndarray, verts: np.ndarray, faces: np.ndarray, K: np.ndarray,
                 kp_face: np.ndarray, kp_bary: np.ndarray, mask_area: np.ndarray, alpha: float = 0.2,
                 threshold_frame: Literal["reference", "target"] = "reference", chunk_elements: int = 2_000_000,
                 pair_limit: int = 5_000_000, frame_index: np.ndarray | None = None) -> dict:
    """PCK-T over every ordered pair of annotated frames (vectorised in chunks of reference frames).

    Args:
        keypoints: float (A, P, 3) ``[x, y, visible]`` per annotated frame, full-frame pixels.
        verts: float (A, V, 3) predicted camera-space vertices at those frames.
        faces: int (F, 3).
        K: float (A, 3, 3) intrinsics of those frames.
        kp_face: int (A, P) the face under each keypoint in its own frame's render (-1: the render is
            empty; such a keypoint keeps its position, i.e. zero transfer, as LASR does).
        kp_bary: float (A, P, 3) perspective-correct barycentrics of that point.
        mask_area: (A,) ground-truth foreground pixel counts.
        alpha: correctness threshold as a fraction of sqrt(mask area).
        threshold_frame: whose mask area sets the threshold: ``"reference"`` (frame i, as LASR and
            ViSER's code do) or ``"target"`` (frame j).
        frame_index: int (A,) the video frame of each annotated frame (default 0..A-1), for ``by_gap``.

    Returns:
        dict: ``pck`` (percent, NaN when nothing was scored), ``correct``, ``total`` (pairs x
        keypoints scored), ``pairs`` (ordered frame pairs), ``by_gap`` (per band of :data:`GAP_BANDS`:
        ``frames`` "lo-hi" or "lo+", ``correct``, ``total``, ``pck``), ``per_keypoint_correct`` and
        ``per_keypoint_total`` (P,) int arrays, ``per_frame_keypoint_correct`` and ``per_frame_keypoint_total``
        (A, P) the same per reference frame i, ``pred`` float64 (A, A, P, 2) transferred positions
        ``pred[i, j]`` of frame i's keypoints in frame j, and ``valid`` bool (A, A, P) (both None when
        A * A * P > ``pair_limit``: long fully annotated videos are scored in O(A P) memory).
    """
    if threshold_frame not in ("reference", "target"):
        raise ValueError(f"pck_transfer(): threshold_frame must be 'reference' or 'target', got {threshold_frame!r}")
    kp = np.asarray(keypoints, dtype=np.float64)
    A, P = kp.shape[:2]
    V = np.asarray(verts, dtype=np.float64)
    Kd = np.asarray(K, dtype=np.float64)
    face = np.asarray(kp_face, dtype=np.int64)
    has = face >= 0
    tri_all = np.asarray(faces, dtype=np.int64)[np.where(has, face, 0)]  # (A_i, P, 3)
    w_all = np.where(has[..., None], np.asarray(kp_bary, dtype=np.float64), 1.0 / 3.0)  # any point for the unused
    vis = kp[..., 2] > 0.5
    area = np.asarray(mask_area, dtype=np.float64)
    thr_all = alpha * np.sqrt(area)
    keep_pairs = A * A * P <= pair_limit
    pred_all = np.zeros((A, A, P, 2)) if keep_pairs else None
    valid_all = np.zeros((A, A, P), bool) if keep_pairs else None
    correct_n, total = 0, 0
    kp_correct = np.zeros((A, P), np.int64)  # per reference frame and keypoint
    kp_total = np.zeros((A, P), np.int64)
    fidx = np.arange(A) if frame_index is None else np.asarray(frame_index, np.int64)
    band = np.digitize(np.abs(fidx[:, None] - fidx[None, :]), GAP_BANDS) - 1  # (A, A), -1 on the diagonal
    gap_correct = np.zeros(len(GAP_BANDS), np.int64)
    gap_total = np.zeros(len(GAP_BANDS), np.int64)
    step = max(1, int(chunk_elements // max(1, A * P)))  # reference frames per chunk: memory O(A P), not O(A^2 P)
    for i0 in range(0, A, step):
        sl = slice(i0, min(A, i0 + step))
        ii = np.arange(sl.start, sl.stop)
        corners = V[:, tri_all[sl]]  # (A_j, c, P, 3, 3)
        X = np.einsum("ipk,jipkc->ijpc", w_all[sl], corners)  # (c, A_j, P, 3)
        proj = project_np(X, Kd[None, :, None])  # proj[i, j, p]: frame i's surface point seen in frame j
        proj_self = proj[np.arange(len(ii)), ii]  # (c, P, 2)
        flow = np.where(has[sl][:, None, :, None], proj - proj_self[:, None], 0.0)
        pred = kp[sl][:, None, :, :2] + flow
        valid = vis[sl][:, None, :] & vis[None, :, :]
        valid[np.arange(len(ii)), ii] = False
        err = np.linalg.norm(pred - kp[None, :, :, :2], axis=-1)
        thr = thr_all[sl][:, None, None] if threshold_frame == "reference" else thr_all[None, :, None]
        correct = (err < thr) & valid
        correct_n += int(correct.sum())
        total += int(valid.sum())
        kp_correct[sl] = correct.sum(axis=1)
        kp_total[sl] = valid.sum(axis=1)
        bi = np.broadcast_to(band[sl][..., None], valid.shape)
        gap_correct += np.bincount(bi[correct], minlength=len(GAP_BANDS))
        gap_total += np.bincount(bi[valid], minlength=len(GAP_BANDS))
        if keep_pairs:
            pred_all[sl], valid_all[sl] = pred, valid
    return {
        "pck": 100.0 * correct_n / total if total else float("nan"),
        "correct": correct_n,
        "total": total,
        "pairs": A * (A - 1),
        "by_gap": [{"frames": f"{lo}-{hi - 1}" if hi else f"{lo}+", "correct": int(c), "total": int(t),
                    "pck": 100.0 * c / t if t else None}
                   for lo, hi, c, t in zip(GAP_BANDS, (*GAP_BANDS[1:], None), gap_correct, gap_total)],
        "per_keypoint_correct": kp_correct.sum(0),
        "per_keypoint_total": kp_total.sum(0),
        "per_frame_keypoint_correct": kp_correct,
        "per_frame_keypoint_total": kp_total,
        "pred": pred_all,
        "valid": valid_all,
    }

