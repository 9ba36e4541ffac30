"""Pictures people look at (``renders/``): input | fit overlay video, skeleton overlay, loss curves."""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import matplotlib
import numpy as np
import torch
import trimesh
from matplotlib.figure import Figure
from tqdm import tqdm

from s3o_warp import interrupt
from s3o_warp.config import DataConfig
from s3o_warp.data.io import atomic_path, write_image, write_video
from s3o_warp.data.sequence import open_sequence
from s3o_warp.geometry import project_np
from s3o_warp.ops import interpolate, rasterize

log = logging.getLogger(__name__)

TURNTABLE_FRAMES = 36
"""Frames of the turntable video (one turn)."""


_STOPPED = "the renders (the fit is done; --resume writes them)"


def _each(items, bar: tqdm | None):
    """``items`` one by one, each counted on ``bar``, stopping at a stop request (:mod:`s3o_warp.interrupt`)."""
    for x in items:
        interrupt.check(_STOPPED)
        yield x
        if bar is not None:
            bar.update(1)


def render_fit_frames(rig, chunk: int = 8):
    """Yield (face_index (H,W), colour (H,W,3) float) of the fitted mesh for every frame, full-frame size."""
    verts = torch.as_tensor(rig.posed_camera(), dtype=torch.float32)
    faces = torch.as_tensor(rig.faces, dtype=torch.int64)
    K = torch.as_tensor(rig.K, dtype=torch.float32)
    colors = torch.as_tensor(rig.colors, dtype=torch.float32)
    H, W = rig.image_size
    for s in range(0, verts.shape[0], chunk):
        with torch.no_grad():
            fi, bary, _ = rasterize(verts[s : s + chunk], faces, K[s : s + chunk], (H, W))
            col = interpolate(colors, faces, fi, bary)
        for k in range(fi.shape[0]):
            yield fi[k].numpy(), col[k].numpy()


def overlay_video(run: Path, rig, sequence, fps: float, bar: tqdm | None = None) -> Path:
    """Side by side input | input with the fitted mesh (rendered colours, outlined) at the input rate."""
    out = []
    for k, (fi, col) in enumerate(_each(render_fit_frames(rig), bar)):
        img = sequence.image(k)
        fg = fi >= 0
        over = img.astype(np.float32).copy()
        tint = (0.35 * over + 0.65 * (col * 255.0)).clip(0, 255)
        over[fg] = tint[fg]
        edge = cv2.morphologyEx(fg.astype(np.uint8), cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8)) > 0
        over[edge] = (255, 64, 32)
        out.append(np.concatenate([img, over.astype(np.uint8)], 1))
    return write_video(out, run / "renders" / "overlay.mp4", fps)


def posed_bone_centres(rig, t: int) -> np.ndarray:
    """Camera-space position of every bone centre at frame t, ``(B, 3)`` (each moved by its own bone)."""
    c = rig.centres if rig.centres is not None else rig.bind[:, :3, 3]
    ch = np.concatenate([c, np.ones((len(c), 1))], 1)
    obj = np.einsum("bij,bj->bi", rig.bone_motion[t], ch)
    return (obj @ rig.root[t].T)[:, :3]


def draw_skeleton(img: np.ndarray, rig, frame: int) -> np.ndarray:
    """The fit's bones (centre-to-joint segments), bone centres and joints drawn over an RGB frame."""
    img = np.ascontiguousarray(img.copy())
    K = rig.K[frame]

    def px(p3):
        x, y = project_np(p3, K)
        return int(round(x)), int(round(y))

    jc = rig.joints_camera()[frame]
    bc = posed_bone_centres(rig, frame)
    for j, (a, b) in enumerate(rig.joint_pairs):
        for bone in (a, b):
            cv2.line(img, px(jc[j]), px(bc[bone]), (255, 200, 0), 2, cv2.LINE_AA)
    for p3 in bc:
        cv2.circle(img, px(p3), 3, (0, 160, 255), -1, cv2.LINE_AA)
    for p3 in jc:
        cv2.circle(img, px(p3), 4, (255, 0, 0), -1, cv2.LINE_AA)
    return img


def _has_skeleton(rig) -> bool:
    return rig.joints is not None and rig.joint_pairs is not None and len(rig.joints) > 0


def skeleton_overlay(run: Path, rig, sequence, fps: float = 24.0, bar: tqdm | None = None) -> list[Path]:
    """The skeleton over every input frame (``skeleton.mp4``, GIF fallback) and over frame 0 (``skeleton.png``)."""
    if not _has_skeleton(rig):
        return []
    frames = [draw_skeleton(sequence.image(k), rig, k) for k in _each(range(rig.num_frames), bar)]
    path = write_image(run / "renders" / "skeleton.png", frames[0])
    return [path, write_video(frames, run / "renders" / "skeleton.mp4", fps)]


def loss_plot(run: Path, history: list[dict]) -> Path | None:
    """Total loss and mask IoU per logged step, one colour per phase (PNG)."""
    history = [h for h in history if "loss" in h]
    if not history:
        return None
    fig = Figure(figsize=(10, 3.5))  # no pyplot: no GUI backend, no global figure state
    a1, a2 = fig.subplots(1, 2)
    x = 0
    for phase in dict.fromkeys(h["phase"] for h in history):
        hs = [h for h in history if h["phase"] == phase]
        xs = [x + h["step"] for h in hs]
        a1.plot(xs, [h["loss"] for h in hs], label=phase)
        a2.plot(xs, [h["iou"] for h in hs], label=phase)
        x = xs[-1]
    a1.set_yscale("log")
    a1.set_xlabel("step")
    a1.set_title("total loss")
    a2.set_xlabel("step")
    a2.set_title("mask IoU (crop)")
    a1.legend()
    fig.tight_layout()
    path = run / "renders" / "loss.png"
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=90)
    return path


def write_renders(run: Path, rig, data, history, data_cfg=None) -> list[Path]:
    """All pictures of a run, with a progress bar over their frames; returns their paths."""
    (Path(run) / "renders").mkdir(parents=True, exist_ok=True)
    seq = open_sequence(data.sequence_dir, cfg=data_cfg or DataConfig(), **(data.open_kwargs or {}))
    T = rig.num_frames
    total = T * (1 + _has_skeleton(rig)) + TURNTABLE_FRAMES + 4  # + side, top, front, bones
    with tqdm(total=total, desc="renders", unit="frame", dynamic_ncols=True, leave=False) as bar:
        paths = [overlay_video(Path(run), rig, seq, data.fps, bar), loss_plot(Path(run), history)]
        paths += skeleton_overlay(Path(run), rig, seq, data.fps, bar)
        paths += canonical_views(Path(run), rig, fps=data.fps, bar=bar)
    paths = [p for p in paths if p is not None]
    for p in paths:
        log.info("render: %s", p)
    return paths


def _look_from(direction: np.ndarray, centre: np.ndarray, dist: float, up: np.ndarray) -> np.ndarray:
    """4x4 object -> OpenCV camera transform for a camera at ``centre - dist * direction`` looking along it."""
    z = direction / np.linalg.norm(direction)
    x = np.cross(-up, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    M = np.eye(4)
    M[:3, :3] = R
    M[:3, 3] = -R @ (centre - dist * z)
    return M


def bone_colors(weights: np.ndarray) -> np.ndarray:
    """Each vertex coloured by its dominant bone (argmax of the skinning weights), like the paper's Fig. 3."""
    cmap = matplotlib.colormaps["tab20"]
    B = weights.shape[1]
    pal = np.array([cmap(i % 20)[:3] for i in range(B)])
    return pal[np.argmax(weights, 1)].astype(np.float32)


def render_canonical(rig, view: np.ndarray, size: int = 256, draw_skeleton: bool = True,
                     colors: np.ndarray | None = None) -> np.ndarray:
    """The canonical (rest) mesh with vertex colours, Lambert-shaded, from an object->camera ``view`` (RGB)."""
    v = rig.verts.astype(np.float64)
    cam = v @ view[:3, :3].T + view[:3, 3]
    ext = np.abs(cam[:, :2] / cam[:, 2:3]).max()
    f = 0.45 * size / max(ext, 1e-6)
    K = np.array([[f, 0, (size - 1) / 2], [0, f, (size - 1) / 2], [0, 0, 1]])
    normals = trimesh.Trimesh(v, rig.faces, process=False).vertex_normals @ view[:3, :3].T
    shade = np.clip(-normals[:, 2], 0, 1) * 0.7 + 0.3
    col = np.clip((rig.colors if colors is None else colors) * shade[:, None], 0, 1)
    vt = torch.as_tensor(cam[None], dtype=torch.float32)
    ft = torch.as_tensor(rig.faces, dtype=torch.int64)
    with torch.no_grad():
        fi, bary, _ = rasterize(vt, ft, torch.as_tensor(K, dtype=torch.float32), (size, size))
        img = interpolate(torch.as_tensor(col, dtype=torch.float32), ft, fi, bary)[0].numpy()
    bg = np.full((size, size, 3), 0.93)
    fg = (fi[0] >= 0).numpy()
    out = np.where(fg[..., None], img, bg)
    out = (out * 255).astype(np.uint8)
    if draw_skeleton and rig.centres is not None:
        def px(p):
            x, y = project_np(view[:3, :3] @ p + view[:3, 3], K)
            return int(round(x)), int(round(y))

        if rig.joints is not None and rig.joint_pairs is not None:
            for j, (a, b) in enumerate(rig.joint_pairs):
                for bone in (a, b):
                    cv2.line(out, px(rig.joints[j]), px(rig.centres[bone]), (30, 30, 200), 2, cv2.LINE_AA)
            for p in rig.joints:
                cv2.circle(out, px(p), 4, (220, 20, 20), -1, cv2.LINE_AA)
        for p in rig.centres:
            cv2.circle(out, px(p), 3, (20, 140, 255), -1, cv2.LINE_AA)
    return out


def canonical_views(run: Path, rig, fps: float = 24.0, turntable_frames: int = TURNTABLE_FRAMES,
                    bar: tqdm | None = None) -> list[Path]:
    """Side, top and front views of the canonical mesh with its skeleton (PNG; ``canonical_views.png`` puts the
    three over the same views in plain grey, shaded, where the shape's width and surface show), and a turntable
    (mp4/GIF) of the coloured mesh beside the plain one."""
    v = rig.verts.astype(np.float64)
    centre = 0.5 * (v.min(0) + v.max(0))
    dist = 3.0 * np.linalg.norm(v.max(0) - v.min(0))
    # object frame: the canonical camera's axes (x along the image's rows, y down, z away from the canonical camera)
    down = np.array([0.0, 1.0, 0.0])
    across = np.array([0.0, 0.0, 1.0])
    paths = []
    grey = np.full((v.shape[0], 3), 0.8, np.float32)
    coloured, plain = [], []
    for name, direction, up in _each((("side", across, -down), ("top", down, across),
                                      ("front", np.array([-1.0, 0.0, 0.0]), -down)), bar):
        view = _look_from(direction, centre, dist, up)
        coloured.append(render_canonical(rig, view))
        plain.append(render_canonical(rig, view, draw_skeleton=False, colors=grey))
        paths.append(write_image(run / "renders" / f"canonical_{name}.png", coloured[-1]))
    # one picture to judge the shape at a glance: side, top and front, coloured with the skeleton over plain grey
    paths.append(write_image(run / "renders" / "canonical_views.png",
                             np.concatenate([np.concatenate(coloured, 1), np.concatenate(plain, 1)], 0)))
    frames = []
    for k in _each(range(turntable_frames), bar):
        a = 2 * np.pi * k / turntable_frames
        view = _look_from(np.array([np.sin(a), 0.35, np.cos(a)]), centre, dist, -down)
        frames.append(np.concatenate([render_canonical(rig, view),
                                      render_canonical(rig, view, draw_skeleton=False, colors=grey)], 1))
    paths.append(write_video(frames, run / "renders" / "turntable.mp4", fps))
    interrupt.check(_STOPPED)
    img = render_canonical(rig, _look_from(across, centre, dist, -down), colors=bone_colors(rig.weights))
    if bar is not None:
        bar.update(1)
    paths.append(write_image(run / "renders" / "bones.png", img))
    return paths
