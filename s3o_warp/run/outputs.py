"""What a finished fit leaves in the run directory: rig files, USD/glTF, metrics and pictures.

Every file is written to a temporary name and renamed (the writers used here all do that).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch

from s3o_warp.data.io import copy_file, write_json
from s3o_warp.evaluation.report import evaluate_run
from s3o_warp.export.gltf import export_gltf, export_gltf_videos
from s3o_warp.export.rig import Rig, save_rig
from s3o_warp.export.usd import export_usd
from s3o_warp.geometry import quat_to_matrix, to_numpy
from s3o_warp.run import pictures
from s3o_warp.skeleton.joints import bone_endpoints
from s3o_warp.skeleton.measures import bone_lengths
from s3o_warp.skeleton.mstep import joint_samples

log = logging.getLogger(__name__)


def _h(rt: np.ndarray) -> np.ndarray:
    out = np.zeros(rt.shape[:-2] + (4, 4))
    out[..., :3, :] = rt
    out[..., 3, 3] = 1
    return out


@torch.no_grad()
def rig_from_model(fitter, video=None):
    """The fitted model as an ``export.rig.Rig`` (object frame = the coarse phase's canonical frame); ``video`` (a
    :class:`~s3o_warp.data.store.Video`): that video's frames, camera and motion on the shared mesh and skeleton."""
    m, d = fitter.model, fitter.data
    B = m.num_bones
    span = (0, m.num_frames) if video is None else (video.start, video.stop)
    src = d if video is None else video
    frames = torch.arange(*span, device=m.verts.device)
    W = m.skinning()
    V = quat_to_matrix(m.bone_quat)  # rows = axes
    bind = np.tile(np.eye(4), (B, 1, 1))
    bind[:, :3, :3] = to_numpy(V.transpose(-1, -2))
    bind[:, :3, 3] = to_numpy(m.bone_centers)
    precisions = to_numpy(m.precisions())
    joints, pairs = None, None
    sk = fitter.skel
    if len(sk.joints):
        pairs = np.asarray(sk.joints, dtype=np.int64)
        joints = np.asarray(sk.joint_positions, dtype=np.float64)
    lengths = None
    if pairs is not None:
        X, Wn = to_numpy(m.verts), to_numpy(W)
        lengths = bone_lengths(bone_endpoints(X, Wn, pairs, t_r=fitter.cfg.skeleton.t_r, samples=joint_samples(m)), X)
    return Rig(
        verts=to_numpy(m.verts).astype(np.float32),
        faces=m.faces.cpu().numpy().astype(np.int32),
        colors=to_numpy(m.colors()).astype(np.float32),
        weights=to_numpy(W).astype(np.float32),
        bone_names=[f"bone_{b:02d}" for b in range(B)],
        parents=np.asarray(fitter.skel.parents, dtype=np.int64),
        bind=bind,
        bone_motion=_h(to_numpy(m.bone_rt(frames))),
        root=_h(to_numpy(m.root_rt(frames))),
        K=to_numpy(m.intrinsics_frame(frames)),
        image_size=tuple(int(x) for x in src.frame_size),
        fps=float(src.fps),
        frame_names=list(src.frame_names),
        joints=joints,
        joint_pairs=pairs,
        centres=to_numpy(m.bone_centers),
        precisions=precisions,
        lengths=lengths,
    )


def write_run(fitter) -> dict:
    """Write rig files, USD + glb, metrics.json and renders/ for a finished fit; return the metrics."""
    if fitter.data.num_videos > 1:
        return write_videos(fitter)
    run = Path(fitter.run_dir)
    rig = rig_from_model(fitter)
    save_rig(run, rig)
    name = fitter.data.name
    try:
        export_usd(rig, run / f"{name}.usdc")
        export_gltf(rig, run / f"{name}.glb")
    except ImportError as e:  # pragma: no cover - the exporter is part of the package
        log.warning("export skipped: %s", e)
    d = fitter.data
    metrics = evaluate_run(run, None, masks=d.mask_dir, keypoints=d.keypoints_file, ground_truth=d.ground_truth_dir,
                           object_id=fitter.cfg.data.object_id)
    metrics["sequence"] = str(d.sequence_dir)
    metrics["seconds"] = round(fitter.history[-1]["seconds"], 2) if fitter.history else None
    write_json(run / "metrics.json", metrics)
    if fitter.cfg.output.render_video:
        pictures.write_renders(run, rig, fitter.data, fitter.history, fitter.cfg.data)
    return metrics


def write_videos(fitter) -> dict:
    """A fit of several videos: the shared ``canonical.ply`` and ``skeleton.json``, one ``<video>.usdc`` per video
    (its camera and animation on the shared rig), one ``.glb`` with an animation per video, ``videos/<video>/`` a
    whole one-video run directory each (rig files, ``metrics.json``, ``renders/``), ``videos.json`` (their names in
    order) and ``metrics.json`` with every video's figures, their mean and each video's registration."""
    run = Path(fitter.run_dir)
    d = fitter.data
    registration = registrations(fitter.history)
    rigs, per_video = [], {}
    for v in d.videos:
        rig = rig_from_model(fitter, v)
        rigs.append(rig)
        sub = run / "videos" / v.name
        save_rig(sub, rig)
        export_usd(rig, run / f"{v.name}.usdc")
        m = evaluate_run(sub, None, masks=v.mask_dir, keypoints=v.keypoints_file, ground_truth=v.ground_truth_dir,
                         object_id=fitter.cfg.data.object_id)
        m["sequence"] = str(v.sequence_dir)
        if v.name in registration:
            m["registration"] = registration[v.name]
        write_json(sub / "metrics.json", m)
        per_video[v.name] = m
    for f in ("canonical.ply", "skeleton.json"):  # the shared mesh and skeleton; each video's motion is its own
        copy_file(run / "videos" / d.videos[0].name / f, run / f)
    export_gltf_videos(rigs, [v.name for v in d.videos], run / f"{d.name}.glb")
    write_json(run / "videos.json", {"videos": [v.name for v in d.videos], "synchronized": fitter.cfg.motion.synchronized})
    metrics = {"videos": per_video, "mean": mean_metrics(list(per_video.values())), "registration": registration,
               "sequence": [str(v.sequence_dir) for v in d.videos],
               "seconds": round(fitter.history[-1]["seconds"], 2) if fitter.history else None}
    write_json(run / "metrics.json", metrics)
    if fitter.cfg.output.render_video:
        for v, rig in zip(d.videos, rigs):
            pictures.write_renders(run / "videos" / v.name, rig, v, fitter.history, fitter.cfg.data)
    return metrics


def registrations(history: list[dict]) -> dict:
    """Each video's orientation and turn rate by name, from the camera hypotheses' records of the log (a resumed
    fit reads its log back, so they survive a stop)."""
    return {r["video"]: r["orientation"] for r in history if r.get("what") == "hypotheses" and "orientation" in r}


def mean_metrics(items: list[dict]) -> dict:
    """The mean of every number that all of ``items`` hold at the same place (nested dicts; lists left out)."""
    out = {}
    for k, first in items[0].items():
        vals = [it.get(k) for it in items]
        if isinstance(first, dict) and all(isinstance(x, dict) for x in vals):
            sub = mean_metrics(vals)
            if sub:
                out[k] = sub
        elif all(isinstance(x, (int, float)) and not isinstance(x, bool) and x is not None for x in vals):
            out[k] = float(np.mean(vals))
    return out
