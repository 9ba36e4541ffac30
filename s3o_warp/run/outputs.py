"""What a finished fit leaves in the run directory: rig files, USD/glTF, metrics and pictures.

Every file is written to a temporary name and renamed (the writers used here all do that).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch

from s3o_warp.data.io import write_json
from s3o_warp.evaluation.report import evaluate_run
from s3o_warp.export.gltf import export_gltf
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
def rig_from_model(fitter):
    """The fitted model as an ``export.rig.Rig`` (object frame = the coarse phase's canonical frame)."""
    m, d = fitter.model, fitter.data
    T, B = m.num_frames, m.num_bones
    frames = torch.arange(T, device=m.verts.device)
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
        image_size=tuple(int(x) for x in d.frame_size),
        fps=float(d.fps),
        frame_names=list(d.frame_names),
        joints=joints,
        joint_pairs=pairs,
        centres=to_numpy(m.bone_centers),
        precisions=precisions,
        lengths=lengths,
    )


def write_run(fitter) -> dict:
    """Write rig files, USD + glb, metrics.json and renders/ for a finished fit; return the metrics."""
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
