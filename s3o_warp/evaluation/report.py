"""A whole run scored against its sequence: :func:`evaluate_run` ties the readers
(:mod:`s3o_warp.evaluation.loaders`) and the scores (:mod:`~s3o_warp.evaluation.image`,
:mod:`~s3o_warp.evaluation.shape`, :mod:`~s3o_warp.evaluation.views`, :mod:`~s3o_warp.evaluation.skeleton`) together, whatever inputs are there;
:func:`write_metrics` writes its result as ``metrics.json`` and :func:`format_table` prints it
(``scripts/evaluate.py`` is the command line).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from pathlib import Path
from typing import Literal

import numpy as np

from s3o_warp.data.io import write_json
from s3o_warp.errors import InputError
from s3o_warp.evaluation.image import (
    mask_iou,
    pck_transfer,
    render_frames,
    surface_under_keypoints,
)
from s3o_warp.evaluation.loaders import (
    GroundTruth,
    load_ground_truth,
    load_keypoints,
    load_masks,
    load_predictions,
)
from s3o_warp.evaluation.keypoints import facing_sides, pck_groups
from s3o_warp.evaluation.shape import bbox_diagonal, frame_similarities, shape_metrics
from s3o_warp.evaluation.views import novel_view_iou, surface_quality, turn_error, width_ratios
from s3o_warp.evaluation.skeleton import (
    empty_bones,
    joints_inside,
    limb_coverage,
    limb_identity,
    skeleton_distance,
)

log = logging.getLogger(__name__)


def _pair_frames(pred_names: list[str], gt: GroundTruth, where: Path) -> tuple[np.ndarray, np.ndarray]:
    """Indices (pred, gt) of the frames both hold: by name when the ground truth names them, else by order."""
    if gt.frame_names is not None:
        pos = {n: i for i, n in enumerate(gt.frame_names)}
        pi = [i for i, n in enumerate(pred_names) if n in pos]
        if not pi:
            raise InputError(f"{gt.source}: none of the run's frames ({pred_names[0]}...) are in the ground truth's "
                             f"frame_names ({gt.frame_names[0]}...); score against the sequence the run was fitted on")
        return np.array(pi), np.array([pos[pred_names[i]] for i in pi])
    if gt.verts.shape[0] != len(pred_names):
        raise InputError(f"{gt.source}: has {gt.verts.shape[0]} frames and no frame_names, but {where} has "
                         f"{len(pred_names)}; add frame_names to the ground-truth file or score the full sequence")
    idx = np.arange(len(pred_names))
    return idx, idx


def _keypoint_depth(gt: GroundTruth | None, names: list[str], pred_names: list[str], ann: list[int],
                    where: Path) -> np.ndarray | None:
    """float (A, P) the true camera-space depth of each keypoint at the annotated frames ``ann`` (indices into the
    run's ``pred_names``, paired with the ground truth's frames by :func:`_pair_frames`), or None where the ground
    truth lacks a keypoint or a frame."""
    if gt is None or not gt.keypoints or any(n not in gt.keypoints for n in names):
        return None
    pos = dict(zip(*_pair_frames(pred_names, gt, where)))
    if any(t not in pos for t in ann):
        return None
    gi = np.array([pos[t] for t in ann])
    return np.stack([gt.keypoints[n][gi, 2] for n in names], axis=1).astype(np.float64)


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(float(x)) else None
    if isinstance(x, Path):
        return str(x)
    return x


def evaluate_run(run, sequence=None, *, keypoints=None, ground_truth=None, masks=None,
                 object_id: int | None = None, alpha: float = 0.2,
                 threshold_frame: Literal["reference", "target"] = "reference",
                 n_points: int = 5000, fscore_ratio: float = 0.02, icp_iters: int = 50, seed: int = 0,
                 chunk: int = 8, device: str = "cpu", progress: bool = True, rasterizer=None,
                 chain_separation: float = 0.15, framewise_limbs: bool = True, limb_tips: bool = True) -> dict:
    """Score a run against a sequence: mask IoU, PCK-T, 3D shape and skeleton, whatever is available.

    Args:
        run: run directory (with ``motion.npz``) or the ``.npz`` itself.
        sequence: sequence folder; supplies ``masks/``, ``keypoints.json`` and ``ground_truth/``
            unless given explicitly.
        keypoints: a keypoints.json (default ``<sequence>/keypoints.json`` when present).
        ground_truth: ``ground_truth/`` folder or its ``.npz`` (default ``<sequence>/ground_truth``).
        masks: masks folder (default ``<sequence>/masks``).
        object_id: palette index of the object in palette masks.
        alpha: PCK-T threshold as a fraction of sqrt(mask area).
        threshold_frame: whose mask area sets the PCK-T threshold (see :func:`pck_transfer`).
        n_points: surface samples per frame for Chamfer / F-score.
        fscore_ratio: F-score threshold as a fraction of the bbox diagonal.
        icp_iters: ICP iterations of the 3D alignment.
        seed: surface-sampling seed.
        chain_separation: ``skeleton.limbs_distinct`` counts joints closer than this fraction of the limb's
            length along it to a nearer one once (:func:`limb_coverage` with ``branch=False``);
            ``skeleton.limbs`` counts every joint.
        framewise_limbs: also ``skeleton.limbs_framewise``: ``limbs_distinct`` with every frame aligned on its
            own (:func:`frame_similarities`), the rig's joints apart from each frame's root pose and depth error;
            ``frame_scale`` lists each frame's scale over the sequence's.
        limb_tips: the limb counts follow each limb on to its end joint's tip where the ground truth has one
            (:attr:`GroundTruth.tips`, :func:`limb_coverage`'s ``tips``); false: they stop at the end joint.
        chunk: frames per render call.
        device: torch device of the renders.
        progress: tqdm bars.
        rasterizer: z-buffer op override (see :func:`render_frames`); default the Warp kernel.

    Returns:
        A JSON-ready dict: ``run``, ``sequence``, ``frames``, then ``mask_iou`` (``mean``,
        ``per_frame`` {stem: IoU}), ``pck_t`` (``pck`` %, ``correct``, ``total``, ``pairs``,
        ``frames``, ``alpha``, ``threshold_frame``, ``per_keypoint``, ``groups``: the limbs' ends against the
        rest and the side facing the camera against the far side, :func:`~s3o_warp.evaluation.keypoints.pck_groups`,
        with ``facing_from`` the ground truth's depths or the image), ``shape_3d`` (see
        :func:`shape_metrics`), ``views`` (``sequence`` and ``framewise``: :func:`novel_view_iou` with the
        sequence's alignment and with each frame's own; ``width_ratio``, :func:`width_ratios`; ``turn_error``,
        :func:`turn_error`: each frame's own alignment against the sequence's, in degrees), ``surface``
        (:func:`surface_quality`, each frame aligned on its own), ``skeleton`` (see :func:`skeleton_distance`),
        ``limb_identity`` (see :func:`limb_identity`), each present only when its inputs are, and ``skipped``
        {metric: reason} for the others.

    Raises:
        InputError: unreadable or inconsistent inputs (one line naming the file and the fix).
    """
    pred = load_predictions(run)
    seq = Path(sequence) if sequence is not None else None
    if seq is not None and not seq.is_dir():
        raise InputError(f"{seq}: sequence folder not found; pass --sequence DIR with masks/ inside")
    masks_dir = Path(masks) if masks is not None else (seq / "masks" if seq is not None else None)
    if keypoints is None and seq is not None and (seq / "keypoints.json").exists():
        keypoints = seq / "keypoints.json"
    if ground_truth is None and seq is not None and (seq / "ground_truth").is_dir():
        ground_truth = seq / "ground_truth"

    T = len(pred.frame_names)
    H, W = pred.image_size
    gt = load_ground_truth(ground_truth) if ground_truth is not None else None
    if gt is not None and gt.frame_names is None and masks_dir is not None and masks_dir.is_dir():
        stems = sorted(p.stem for p in masks_dir.iterdir() if p.suffix.lower() == ".png")
        if len(stems) == gt.verts.shape[0]:
            gt = dataclasses.replace(gt, frame_names=stems)
    result: dict = {"run": str(pred.source), "sequence": str(seq) if seq else None, "frames": T, "image_size": [H, W]}
    skipped: dict[str, str] = {}

    # ---- masks: IoU, and PCK-T (which needs the renders and the mask areas) ----
    kps = load_keypoints(keypoints) if keypoints is not None else None
    if masks_dir is not None and masks_dir.is_dir():
        gt_masks = load_masks(masks_dir, pred.frame_names, (H, W), object_id)
        ann: list[int] = []
        if kps is not None:
            pos = {n: i for i, n in enumerate(pred.frame_names)}
            ann = sorted(pos[s] for s in kps.frames if s in pos)
            missing = [s for s in kps.frames if s not in pos]
            if missing:
                log.info("PCK-T: %d annotated frames are not in the run (%s...), skipped", len(missing), missing[0])
        ann_set = {t: a for a, t in enumerate(ann)}
        P = len(kps.names) if kps is not None else 0
        kp_face = np.full((len(ann), P), -1, np.int64)
        kp_bary = np.zeros((len(ann), P, 3))
        iou = np.zeros(T)
        for s, fi, bary in render_frames(pred.verts_cam, pred.faces, pred.K, (H, W), chunk, device, progress,
                                             rasterizer):
            c = fi.shape[0]
            iou[s:s + c] = mask_iou(fi >= 0, gt_masks[s:s + c])
            for k in range(c):
                a = ann_set.get(s + k)
                if a is not None:
                    xy = kps.frames[pred.frame_names[s + k]][:, :2]
                    kp_face[a], kp_bary[a], _ = surface_under_keypoints(fi[k], bary[k], xy)
        result["mask_iou"] = {"mean": float(iou.mean()), "frames": T,
                              "per_frame": dict(zip(pred.frame_names, iou.tolist()))}
        if kps is None:
            skipped["pck_t"] = "no keypoints.json"
        elif len(ann) < 2:
            skipped["pck_t"] = f"{len(ann)} annotated frame(s) in the run; PCK-T needs at least 2"
        else:
            ann_a = np.array(ann)
            kp_arr = np.stack([kps.frames[pred.frame_names[t]] for t in ann])
            area = gt_masks[ann_a].reshape(len(ann), -1).sum(1)
            r = pck_transfer(kp_arr, pred.verts_cam[ann_a], pred.faces, pred.K[ann_a], kp_face, kp_bary, area,
                             alpha, threshold_frame, frame_index=ann_a)
            result["pck_t"] = {
                "pck": r["pck"], "correct": r["correct"], "total": r["total"], "pairs": r["pairs"],
                "frames": len(ann), "alpha": alpha, "threshold_frame": threshold_frame, "by_gap": r["by_gap"],
                "per_keypoint": {n: {"pck": (100.0 * c / t if t else None), "correct": int(c), "total": int(t)}
                                 for n, c, t in zip(kps.names, r["per_keypoint_correct"], r["per_keypoint_total"])},
            }
            depth = _keypoint_depth(gt, kps.names, pred.frame_names, ann, pred.source)
            facing = facing_sides(kps.names, kp_arr, depth)
            result["pck_t"]["groups"] = {
                **pck_groups(kps.names, r["per_frame_keypoint_correct"], r["per_frame_keypoint_total"], facing),
                "facing_from": "ground truth" if depth is not None else "image"}
    else:
        skipped["mask_iou"] = f"no masks folder ({masks_dir})"
        if kps is not None:
            skipped["pck_t"] = "PCK-T needs the masks (for the threshold)"
    if "pck_t" not in result and "pck_t" not in skipped:
        skipped["pck_t"] = "no keypoints.json"

    # ---- the skeleton inside the body (no ground truth needed) ----
    if pred.joints_cam is not None and pred.joints_cam.shape[1] > 0:
        result["joints_inside"] = joints_inside(pred.joints_cam, pred.verts_cam, pred.faces)
    else:
        skipped["joints_inside"] = f"{pred.source} has no joints_cam"
    if pred.weights is not None:
        result["bones"] = empty_bones(pred.weights)
    else:
        skipped["bones"] = f"{pred.source} has no weights"

    # ---- 3D shape and skeleton against synthetic ground truth ----
    if gt is not None:
        pi, gi = _pair_frames(pred.frame_names, gt, pred.source)
        shape, sim = shape_metrics(pred.verts_cam[pi], pred.faces, gt.verts[gi], gt.faces, n_points=n_points,
                                   fscore_ratio=fscore_ratio, icp_iters=icp_iters, seed=seed)
        shape["frames"] = int(len(pi))
        result["shape_3d"] = shape
        # each frame aligned on its own: the shape and articulation apart from the path (root pose, depth, scale)
        sims = frame_similarities(pred.verts_cam[pi], pred.faces, gt.verts[gi], gt.faces, sim, seed=seed)
        if gt.cam_from_world is not None:
            c2w = gt.cam_from_world[gi]
            side = dict(joints=None if gt.joints is None else gt.joints[gi], joint_names=gt.joint_names)
            result["views"] = {
                "sequence": novel_view_iou(pred.verts_cam[pi], pred.faces, gt.verts[gi], gt.faces, c2w, [sim] * len(pi),
                                           **side),
                "framewise": novel_view_iou(pred.verts_cam[pi], pred.faces, gt.verts[gi], gt.faces, c2w, sims, **side),
                "width_ratio": width_ratios(pred.verts_cam[pi], gt.verts[gi], c2w, sims, **side),
                "turn_error": turn_error(sim, sims, c2w)}
        else:
            skipped["views"] = f"{gt.source} has no cam_from_world (the model's up axis)"
        result["surface"] = surface_quality(pred.verts_cam[pi], pred.faces, gt.verts[gi], gt.faces, sims, seed=seed)
        if gt.joints is None:
            skipped["skeleton"] = f"{gt.source} has no joints"
        elif pred.joints_cam is None:
            skipped["skeleton"] = f"{pred.source} has no joints_cam"
        else:
            diag = bbox_diagonal(gt.verts[gi])
            result["skeleton"] = skeleton_distance(pred.joints_cam[pi], gt.joints[gi], diag, sim)
            if gt.joint_parents is not None and len(gt.joint_parents) == gt.joints.shape[1]:
                tips = ({gt.joint_names.index(n): p[gi] for n, p in gt.tips.items() if n in gt.joint_names}
                        if limb_tips else None)
                result["skeleton"]["limbs"] = limb_coverage(pred.joints_cam[pi], gt.joints[gi], gt.joint_parents, diag,
                                                            sim, gt.joint_names, tips=tips)
                # the stricter reading: the limb's own joints, joints at one place along it (a knot) counted once
                result["skeleton"]["limbs_distinct"] = limb_coverage(
                    pred.joints_cam[pi], gt.joints[gi], gt.joint_parents, diag, sim, gt.joint_names, branch=False,
                    min_separation=chain_separation, tips=tips)
                if framewise_limbs:  # the same count on the rig alone: each frame aligned on its own
                    aligned = np.stack([f(j) for f, j in zip(sims, pred.joints_cam[pi])])
                    result["skeleton"]["limbs_framewise"] = {
                        **limb_coverage(aligned, gt.joints[gi], gt.joint_parents, diag, None, gt.joint_names,
                                        branch=False, min_separation=chain_separation, tips=tips),
                        "frame_scale": [float(f.scale / sim.scale) for f in sims]}
        if gt.joints is not None and gt.joint_parents is not None and len(gt.joint_parents) == gt.joints.shape[1]:
            if pred.weights is not None:
                result["limb_identity"] = limb_identity(pred.verts_cam[pi], pred.weights, gt.joints[gi],
                                                        gt.joint_parents, sim, gt.joint_names)
            else:
                skipped["limb_identity"] = f"{pred.source} has no weights"
    else:
        skipped["shape_3d"] = skipped["skeleton"] = "no ground_truth/ (synthetic sequences only)"
    result["skipped"] = skipped
    return _jsonable(result)


def write_metrics(metrics: dict, path) -> Path:
    """Write an :func:`evaluate_run` result as JSON to ``path`` atomically (temporary name, then rename)."""
    return write_json(path, _jsonable(metrics), indent=1)


def format_table(metrics: dict) -> str:
    """A short human-readable table of an :func:`evaluate_run` result."""

    def f(v, spec):
        return "n/a" if v is None else format(v, spec)

    rows = [("metric", "value", "detail")]
    if "mask_iou" in metrics:
        m = metrics["mask_iou"]
        rows.append(("mask IoU", f(m["mean"], ".4f"), f"mean over {m['frames']} frames"))
    if "pck_t" in metrics:
        m = metrics["pck_t"]
        rows.append((f"PCK-T@{m['alpha']:g} (%)", f(m["pck"], ".2f"),
                     f"{m['correct']}/{m['total']} keypoints, {m['pairs']} pairs of {m['frames']} frames"))
        if m.get("by_gap"):
            rows.append(("PCK-T by frame gap (%)", " / ".join(f(g["pck"], ".1f") for g in m["by_gap"]),
                         "pairs " + ", ".join(f"{g['frames']} ({g['total']})" for g in m["by_gap"]) + " frames apart"))
        g = m.get("groups")
        if g:
            rows.append(("PCK-T limbs' ends / rest (%)", f"{f(g['ends']['pck'], '.1f')} / {f(g['rest']['pck'], '.1f')}",
                         f"{len(g['ends']['keypoints'])} keypoints on the limbs' ends"
                         + (f"; worst {g['worst']['keypoint']} {g['worst']['pck']:.1f}" if g.get("worst") else "")))
            rows.append(("PCK-T near / far side (%)", f"{f(g['near']['pck'], '.1f')} / {f(g['far']['pck'], '.1f')}",
                         f"side facing the camera from the {g['facing_from']}, known in {g['frames_with_side']} "
                         f"of {m['frames']} frames"))
    if "joints_inside" in metrics:
        m = metrics["joints_inside"]
        rows.append(("joints inside the body", f(m["fraction"], ".3f"),
                     f"fraction of (frame, joint) pairs; farthest outside {f(m['max_outside'], '.4g')}"))
    if "bones" in metrics:
        m = metrics["bones"]
        rows.append(("bones owning no vertex", f"{len(m['empty'])}/{m['count']}",
                     "bones that are no vertex's largest weight" + (f": {m['empty']}" if m["empty"] else "")))
    if "shape_3d" in metrics:
        m = metrics["shape_3d"]
        rows.append(("Chamfer / bbox diag", f(m["chamfer"], ".5f"),
                     f"mean over {m['frames']} frames, scale {m['alignment']['scale']:.4g}"))
        rows.append((f"F-score@{100 * m['fscore_ratio']:g}%", f(m["fscore"], ".4f"),
                     f"precision {f(m['precision'], '.3f')}, recall {f(m['recall'], '.3f')}"))
    if "views" in metrics:
        for k, what in (("sequence", "the sequence's alignment"), ("framewise", "each frame aligned alone")):
            m = metrics["views"][k]
            rows.append((f"novel-view IoU ({k})", f(m["mean"], ".4f"),
                         ", ".join(f"{v} {x:.3f}" for v, x in m["per_view"].items()) + f"; {what}"))
        if "width_ratio" in metrics["views"]:
            w = metrics["views"]["width_ratio"]
            rows.append(("width ratio", f(w["pred"], ".3f"), f"truth {f(w['truth'], '.3f')}; the middle of the body, "
                         "across its side axis over along its other, each frame aligned alone"))
        if "turn_error" in metrics["views"]:
            t = metrics["views"]["turn_error"]
            rows.append(("turn error (deg)", " / ".join(f(t[k], ".1f") for k in ("mean_deg", "max_deg", "end_deg")),
                         "mean / max / last frame: each frame's own alignment against the sequence's"
                         + (f"; about the vertical {t['end_vertical_deg']:+.1f} at the end, "
                            f"{t['drift_vertical_deg']:+.1f} from the first frame"
                            if t.get("end_vertical_deg") is not None else "")))
    if "surface" in metrics:
        m = metrics["surface"]
        rows.append(("F-score (each frame)", " / ".join(f"{x:.3f}" for x in m["fscore"].values()),
                     "at " + " / ".join(m["fscore"]) + " of the diagonal, each frame aligned alone"))
        rows.append(("normal consistency", f(m["normal_consistency"], ".4f"), "mean |n . n'| to the nearest point, both ways"))
        r = m["roughness"]
        rows.append(("roughness", f(r["pred"], ".4f"),
                     f"edges sharper than {r['angle_deg']:g} degrees; the truth {r['truth']:.4f}"))
    if "skeleton" in metrics:
        m = metrics["skeleton"]
        rows.append(("joint dist / bbox diag", f(m["distance"], ".5f"),
                     f"GT {m['gt_joints']} deforming joints, predicted {m['pred_joints']}"))
        if "limbs" in m:
            c = m["limbs"]
            rows.append(("limbs with a joint chain", f"{c['covered']}/{c['total']}",
                         f"{c['min_joints']}+ joints within {100 * c['tol']:g} % of the diagonal in half the frames"
                         + (", each limb on to its end's tip" if c.get("to_tip") else "")))
        if "limbs_distinct" in m:
            c = m["limbs_distinct"]
            rows.append(("... of distinct joints", f"{c['covered']}/{c['total']}",
                         f"the limb's own chain, joints {100 * c['min_separation']:g} % of its length apart along it"))
        if "limbs_framewise" in m:
            c = m["limbs_framewise"]
            rows.append(("... each frame aligned alone", f"{c['covered']}/{c['total']}",
                         "the same count after a similarity per frame (the rig, apart from root pose and depth)"))
    if "limb_identity" in metrics:
        m = metrics["limb_identity"]
        worst = max(m["limbs"], key=lambda o: o["swapped"], default=None)
        rows.append(("limb frames swapped", f(m["mean_swapped"], ".3f"),
                     "mean over GT limbs" + (f"; most: {worst['limb']} {worst['swapped']:.2f}" if worst else "")))
    for k, why in metrics.get("skipped", {}).items():
        rows.append((k, "skipped", why))
    w0 = max(len(r[0]) for r in rows)
    w1 = max(len(r[1]) for r in rows)
    return "\n".join(f"{a:<{w0}}  {b:>{w1}}  {c}" for a, b, c in rows)

