"""The result from every side: silhouettes from views the video never shows, and the quality of the surface.

* :func:`novel_view_iou`: the prediction (aligned to the ground truth by the sequence's similarity, or by each
  frame's own) and the ground truth, both projected orthographically along the ground truth's body axes (from
  above, from the front and from the side) on a few frames, and the IoU of the two silhouettes per view.
  Orthographic silhouettes from opposite directions are mirror images of each other, so "from below" scores as
  "from above", "from the back" as "from the front" and the left side as the right: three views are all there is.
* :func:`surface_quality`: F-score at 1 % and 2 % of the diagonal, normal consistency (mean ``|n_p . n_g|`` of
  each sample's normal against its nearest neighbour's on the other surface, both directions) and roughness
  (:func:`roughness`: the share of edges whose dihedral angle is sharper than 60 degrees; a smooth surface
  scores near zero, a crumpled one does not).

The body axes come from the ground truth's world (``cam_from_world``: the model's object frame, +y up): up is
world +y; the side axis is the mean horizontal direction from the right to the left joint of the skeleton's named
pairs (``Foot.L`` / ``Foot.R``, ``b_LeftLeg01`` / ``b_RightLeg01``, :func:`left_right_pairs`) over the clip, and
forward is across it. A skeleton without such pairs takes forward as the principal horizontal direction of the
posed vertices (a robot walking with its arms out would be taken side-on that way: its arms span the clip).
"""

from __future__ import annotations

import math
import re

import cv2
import numpy as np
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from .shape import Similarity, bbox_diagonal, chamfer_fscore, sample_surface_faces

VIEWS = ("top", "front", "side")
ROUGH_ANGLE_DEG = 60.0


_LR = (("(?<=[._])L(?=$|[._0-9])", "R"), ("(?<=[._])l(?=$|[._0-9])", "r"), ("(?<=_[fbh])l$", "r"),
       ("Left", "Right"), ("left", "right"))


def left_right_pairs(names) -> list[tuple[int, int]]:
    """Indices ``(left, right)`` of the joints whose names differ only in a side marker (``.L``/``.R``, ``_l``/``_r``,
    ``_fl``/``_fr`` (front, back, hind), ``Left``/``Right``, ``left``/``right``; a trailing ``_NNN`` node number ignored)."""
    index: dict[str, int] = {}
    for i, n in enumerate(names):  # a trailing node number is not part of the name (b_LeftLeg01_015, b_RightLeg01_019)
        index.setdefault(re.sub(r"_\d+_?$", "", str(n)), i)
    pairs = []
    for n, i in index.items():
        for pat, rep in _LR:
            other = re.sub(pat, rep, n)
            if other != n and other in index:
                pairs.append((i, index[other]))
                break
    return pairs


def body_axes(gt_verts_cam: np.ndarray, cam_from_world: np.ndarray, joints_cam: np.ndarray | None = None,
              joint_names=None) -> dict[str, np.ndarray]:
    """Per-frame orthographic projections (2 x 3, camera space) along the body's axes.

    Args:
        gt_verts_cam: float (T, V, 3) ground-truth vertices, camera space of each frame.
        cam_from_world: float (T, 4, 4) world -> camera transforms of those frames (world +y up).
        joints_cam, joint_names: the ground truth's (T, J, 3) joints (camera space) and their J names: the side
            axis from their left/right pairs (module docstring). Without them, or without pairs, forward is the
            vertices' principal horizontal direction.

    Returns:
        ``{view: (T, 2, 3)}`` rows = the image axes of each view, expressed in each frame's camera space.
    """
    R = np.asarray(cam_from_world, np.float64)[:, :3, :3]
    t = np.asarray(cam_from_world, np.float64)[:, :3, 3]

    def to_world(x):  # R^T (x - t)
        return np.einsum("tba,tvb->tva", R, np.asarray(x, np.float64) - t[:, None])

    up = np.array([0.0, 1.0, 0.0])
    pairs = left_right_pairs(joint_names) if joints_cam is not None and joint_names is not None else []
    side = None
    if pairs:
        j = to_world(joints_cam)
        li, ri = np.array(pairs).T
        d = (j[:, li] - j[:, ri]).reshape(-1, 3)[:, [0, 2]].mean(0)
        if np.linalg.norm(d) > 1e-9:
            side = np.array([d[0], 0.0, d[1]]) / np.linalg.norm(d)
            fwd = np.cross(up, side)
    if side is None:
        world = to_world(gt_verts_cam)
        horiz = (world - world.mean(1, keepdims=True))[..., [0, 2]].reshape(-1, 2)
        _, _, vt = np.linalg.svd(horiz - horiz.mean(0), full_matrices=False)
        fwd = np.array([vt[0, 0], 0.0, vt[0, 1]])
        side = np.cross(fwd, up)
    axes_world = {"top": np.stack([fwd, side]), "front": np.stack([side, up]), "side": np.stack([fwd, up])}
    # a world direction d is R d in camera space: rows (2, 3) @ R^T
    return {k: np.einsum("ab,tcb->tac", a, R) for k, a in axes_world.items()}


def silhouette(points2d: np.ndarray, faces: np.ndarray, origin: np.ndarray, pixel: float, size: int) -> np.ndarray:
    """Filled silhouette of a triangle mesh's 2D projection on a ``size`` x ``size`` grid (uint8 0/1).

    Pixel (c, r) covers ``origin + (c, r) * pixel``; triangles are filled with 1/16-pixel precision.
    """
    shift = 4
    p = np.round((points2d - origin) / pixel * (1 << shift)).astype(np.int32)
    tri = p[np.asarray(faces, np.int64)]
    img = np.zeros((size, size), np.uint8)
    for tr in tri:
        cv2.fillConvexPoly(img, tr, 1, cv2.LINE_8, shift)
    return img


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 1.0


def novel_view_iou(pred_verts: np.ndarray, pred_faces: np.ndarray, gt_verts: np.ndarray, gt_faces: np.ndarray,
                   cam_from_world: np.ndarray, sims: list[Similarity], frames: np.ndarray | None = None,
                   size: int = 160, num_frames: int = 8, joints: np.ndarray | None = None, joint_names=None) -> dict:
    """Silhouette IoU of the aligned prediction and the ground truth from above, the front and the side.

    Args:
        pred_verts: float (T, N, 3) predicted camera-space vertices.
        pred_faces: int (F, 3).
        gt_verts: float (T, V, 3) ground-truth camera-space vertices of the same frames.
        gt_faces: int (G, 3).
        cam_from_world: float (T, 4, 4) the ground truth's world -> camera transforms.
        sims: T similarities mapping each frame's prediction onto the ground truth (the sequence's one repeated,
            or :func:`~s3o_warp.evaluation.shape.frame_similarities`).
        frames: indices to score (default ``num_frames`` evenly spaced over the clip).
        size: pixels of each square picture; both silhouettes share its frame (their joint extent plus 5 %).
        num_frames: frames scored when ``frames`` is None.
        joints, joint_names: the ground truth's (T, J, 3) camera-space joints and names, for its side axis
            (:func:`body_axes`).

    Returns:
        ``{"mean", "per_view": {view: mean IoU}, "frames": [indices], "per_frame": {view: [IoU per frame]}}``.
    """
    T = gt_verts.shape[0]
    if frames is None:
        frames = np.unique(np.linspace(0, T - 1, min(num_frames, T)).round().astype(int))
    axes = body_axes(gt_verts, cam_from_world, joints, joint_names)
    per_frame: dict[str, list[float]] = {v: [] for v in VIEWS}
    for t in frames:
        p = sims[t](pred_verts[t])
        g = np.asarray(gt_verts[t], np.float64)
        for view in VIEWS:
            a = axes[view][t]
            p2, g2 = p @ a.T, g @ a.T
            both = np.concatenate([p2, g2])
            lo, hi = both.min(0), both.max(0)
            extent = float((hi - lo).max()) * 1.05
            pixel = extent / (size - 1)
            origin = 0.5 * (lo + hi) - 0.5 * extent
            per_frame[view].append(_iou(silhouette(p2, pred_faces, origin, pixel, size),
                                        silhouette(g2, gt_faces, origin, pixel, size)))
    per_view = {v: float(np.mean(per_frame[v])) for v in VIEWS}
    return {"mean": float(np.mean(list(per_view.values()))), "per_view": per_view,
            "frames": [int(t) for t in frames], "per_frame": per_frame}


def turn_error(sim: Similarity, sims: list[Similarity], cam_from_world: np.ndarray | None = None) -> dict:
    """The root's turn error over the clip: each frame's own alignment against the sequence's.

    ``sims[t]`` is the sequence's ``sim`` followed by frame t's own rigid correction
    (:func:`~s3o_warp.evaluation.shape.frame_similarities`: ``R_frame = R_t R_seq``), so the rotation
    ``R_seq R_frame^T`` is how the prediction, placed by the sequence's alignment, is turned against the truth in
    that frame. Its geodesic angle is the frame's turn error. The sequence's alignment is the best single one for
    the clip, so a root turn that drifts steadily over an orbit reads about half its drift at either end;
    ``drift_vertical_deg`` (the last frame's turn about the vertical less the first's) does not depend on where the
    sequence's alignment sits. The per-frame alignment is ICP from the sequence's: it also takes up some of a wrong
    shape or articulation (a fit with the truth's root but another pose reads a few degrees), and a turn of more
    than some 45 degrees may be under-read.

    Args:
        sim: the sequence's similarity (prediction -> ground truth).
        sims: T similarities, each frame's own (the same mapping).
        cam_from_world: float (T, 4, 4) the ground truth's world -> camera transforms (world +y up); given, the
            signed turn about the truth's vertical is added.

    Returns:
        ``{"mean_deg", "max_deg", "end_deg" (the last frame's: the orbit's end), "per_frame_deg", "frames"}``, and
        with ``cam_from_world`` also ``"vertical_deg"`` (per frame, signed: the prediction's turn about the truth's
        up axis, positive counter-clockwise seen from above), ``"end_vertical_deg"`` and ``"drift_vertical_deg"``.
    """
    R_seq = Rotation.from_matrix(np.asarray(sim.rotation, np.float64))
    R_frame = Rotation.from_matrix(np.stack([np.asarray(s.rotation, np.float64) for s in sims]))
    off = R_seq * R_frame.inv()  # per frame: R_seq R_frame^T
    per_frame = np.degrees(off.magnitude())
    out = {"mean_deg": float(per_frame.mean()), "max_deg": float(per_frame.max()), "end_deg": float(per_frame[-1]),
           "per_frame_deg": per_frame.tolist(), "frames": len(sims)}
    if cam_from_world is not None:
        up = np.asarray(cam_from_world, np.float64)[:, :3, :3] @ np.array([0.0, 1.0, 0.0])  # world +y, camera space
        q = off.as_quat(canonical=True)  # (x, y, z, w), w >= 0
        # the twist of each rotation about the vertical (its swing-twist decomposition): 2 atan2(q_xyz . up, w)
        vertical = np.degrees(2.0 * np.arctan2(np.einsum("ta,ta->t", q[:, :3], up), q[:, 3]))
        out["vertical_deg"] = vertical.tolist()
        out["end_vertical_deg"] = float(vertical[-1])
        out["drift_vertical_deg"] = float(vertical[-1] - vertical[0])
    return out


def roughness(verts: np.ndarray, faces: np.ndarray, angle_deg: float = ROUGH_ANGLE_DEG) -> float:
    """Share of a mesh's interior edges whose dihedral angle (between the two faces' normals) exceeds ``angle_deg``.

    Vertices at the same position are merged first, so a model split along its UV seams counts its seams.
    """
    return mesh_smoothness(verts, faces, angle_deg)["roughness"]


def mesh_smoothness(verts: np.ndarray, faces: np.ndarray, angle_deg: float = ROUGH_ANGLE_DEG) -> dict[str, float]:
    """A mesh's own smoothness, no reference needed: ``roughness`` (:func:`roughness`) and ``normal_consistency``,
    the mean cosine of the angle between the normals of the two faces of each interior edge (1 for a plane)."""
    m = trimesh.Trimesh(np.asarray(verts, np.float64), np.asarray(faces, np.int64), process=True)
    angles = m.face_adjacency_angles
    if not len(angles):
        return {"roughness": 0.0, "normal_consistency": 1.0}
    return {"roughness": float((angles > math.radians(angle_deg)).mean()),
            "normal_consistency": float(np.cos(angles).mean())}


def _normal_consistency(p: np.ndarray, pn: np.ndarray, g: np.ndarray, gn: np.ndarray) -> float:
    _, i = cKDTree(g).query(p)
    _, j = cKDTree(p).query(g)
    return float(0.5 * (np.abs((pn * gn[i]).sum(-1)).mean() + np.abs((gn * pn[j]).sum(-1)).mean()))


def _face_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    tri = v[f]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    return n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-30)


def surface_quality(pred_verts: np.ndarray, pred_faces: np.ndarray, gt_verts: np.ndarray, gt_faces: np.ndarray,
                    sims: list[Similarity], frames: np.ndarray | None = None, n_points: int = 5000,
                    ratios: tuple[float, ...] = (0.01, 0.02), num_frames: int = 8, seed: int = 0) -> dict:
    """F-scores, normal consistency and roughness of the aligned prediction against the ground truth.

    Args:
        pred_verts, pred_faces, gt_verts, gt_faces: as in :func:`novel_view_iou`.
        sims: T similarities (prediction -> ground truth) per frame.
        frames: indices to score (default ``num_frames`` evenly spaced).
        n_points: surface samples per frame and mesh.
        ratios: F-score thresholds as fractions of the ground truth's bbox diagonal.
        seed: sampling seed.

    Returns:
        ``{"fscore": {"1%": ..., "2%": ...}, "normal_consistency", "roughness": {"pred", "truth"}, "frames"}``.
    """
    T = gt_verts.shape[0]
    if frames is None:
        frames = np.unique(np.linspace(0, T - 1, min(num_frames, T)).round().astype(int))
    diag = bbox_diagonal(gt_verts)
    pf, gf = np.asarray(pred_faces, np.int64), np.asarray(gt_faces, np.int64)
    fs: dict[str, list[float]] = {f"{100 * r:g}%": [] for r in ratios}
    nc, rp, rg = [], [], []
    for t in frames:
        pv = sims[t](pred_verts[t])
        gv = np.asarray(gt_verts[t], np.float64)
        p, pi = sample_surface_faces(pv, pf, n_points, [seed, int(t), 3])
        g, gi = sample_surface_faces(gv, gf, n_points, [seed, int(t), 3])
        for r in ratios:
            fs[f"{100 * r:g}%"].append(chamfer_fscore(p, g, r * diag[t])["fscore"])
        nc.append(_normal_consistency(p, _face_normals(pv, pf)[pi], g, _face_normals(gv, gf)[gi]))
        rp.append(roughness(pv, pf))
        rg.append(roughness(gv, gf))
    return {"fscore": {k: float(np.mean(v)) for k, v in fs.items()}, "normal_consistency": float(np.mean(nc)),
            "roughness": {"pred": float(np.mean(rp)), "truth": float(np.mean(rg)), "angle_deg": ROUGH_ANGLE_DEG},
            "frames": [int(t) for t in frames]}


WIDTH_SLAB = 0.3
""":func:`body_width_ratio` measures the middle this share of the body's length."""


def body_width_ratio(verts: np.ndarray, normal: np.ndarray, offset: float = 0.0) -> float:
    """How round the body is across its symmetry plane ``{x : n . x = offset}``: in the slab of the middle
    :data:`WIDTH_SLAB` of the body's length (its principal axis within the plane), the extent across the plane over
    the extent along the plane's other axis. A quadruped seen from the side: the torso's width over its height; a
    cut-out of a side view: near 0."""
    v = np.asarray(verts, np.float64)
    n = np.asarray(normal, np.float64)
    n = n / np.linalg.norm(n)
    across = v @ n - offset
    inplane = v - np.outer(v @ n, n)
    inplane -= inplane.mean(0)
    _, _, vt = np.linalg.svd(inplane, full_matrices=False)
    length, other = inplane @ vt[0], inplane @ vt[1]
    lo, hi = length.min(), length.max()
    mid = 0.5 * (lo + hi)
    slab = np.abs(length - mid) <= 0.5 * WIDTH_SLAB * (hi - lo)
    if slab.sum() < 3:
        return float("nan")
    return float(np.ptp(across[slab]) / max(np.ptp(other[slab]), 1e-12))


def width_ratios(pred_verts: np.ndarray, gt_verts: np.ndarray, cam_from_world: np.ndarray, sims: list[Similarity],
                 frames: np.ndarray | None = None, num_frames: int = 8, joints: np.ndarray | None = None,
                 joint_names=None) -> dict:
    """:func:`body_width_ratio` of the aligned prediction and of the ground truth across the truth's vertical plane
    along the body (normal: its ``side`` axis, :func:`body_axes`), mean over ``num_frames`` frames: a prediction
    flattened into a cut-out of its side view scores far below the truth. ``joints``, ``joint_names`` as for
    :func:`novel_view_iou`.

    Returns:
        ``{"pred", "truth", "frames"}``.
    """
    T = gt_verts.shape[0]
    if frames is None:
        frames = np.unique(np.linspace(0, T - 1, min(num_frames, T)).round().astype(int))
    side = body_axes(gt_verts, cam_from_world, joints, joint_names)["front"][:, 0]  # (T, 3) the body's side axis in camera space
    pred, truth = [], []
    for t in frames:
        pred.append(body_width_ratio(sims[t](pred_verts[t]), side[t]))
        truth.append(body_width_ratio(gt_verts[t], side[t]))
    return {"pred": float(np.nanmean(pred)), "truth": float(np.nanmean(truth)), "frames": [int(t) for t in frames]}
