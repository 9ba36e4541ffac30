"""Write a synthetic sequence (input contract plus ground truth) from a procedural model (the quadruped, the
lizard) or a glTF model.

Folder layout (``out_dir``)::

    images/000000.png ...   RGB frames (8-bit PNG)
    masks/000000.png ...    foreground masks, 0 / 255 (single channel)
    keypoints.json          {"names": [K names], "frames": {"000000": [[x, y, visible], ...], ...}}
                            x, y full-frame pixels (OpenCV: pixel (c, r) centre at (c, r)); visible
                            is 1 when the keypoint's surface point passes a depth test against the
                            z-buffer (its camera z within ``tol`` of the rendered depth at any pixel
                            of the 3x3 neighbourhood of its rounded position) and lies in the image
    ground_truth/ground_truth.npz
                            verts (T, V, 3) float32, camera coordinates (OpenCV), metres (glTF: file units)
                            faces (F, 3) int32
                            K (T, 3, 3) float32 intrinsics
                            cam_from_world (T, 4, 4) float32, world = the model's object frame
                            image_size (2,) int32 = (H, W);  fps () float32
                            joints (T, J, 3) float32, deforming joints in camera coordinates
                            joint_parents (J,) int32 (nearest deforming ancestor, -1 = root)
                            joint_names (J,) str
                            keypoint_names (K,) str;  keypoint_vertex (K,) int64, a rest vertex index
                            per keypoint (the keypoint is that surface vertex in every frame)
                            rest_verts (V, 3) float32 object frame;  colors (V, 3) float32 sRGB
                            source () str;  clip () str;  seed () int64
    ground_truth/README.txt a copy of this layout description

The fit never reads ``keypoints.json`` or ``ground_truth/``; they exist to score it. Everything is
written into a temporary folder beside ``out_dir`` and renamed into place at the end
(:func:`s3o_warp.data.io.atomic_dir`).
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image
from tqdm import tqdm

from .. import interrupt
from ..data.io import atomic_dir, imwrite, read_json
from ..data.sequence import IMAGE_EXTENSIONS
from ..errors import InputError
from ..geometry import project_np
from .camera import camera_path
from .gltf import gltf_keypoints, load_gltf
from .model import AnimatedMesh
from .lizard import build_lizard, lizard_keypoints
from .quadruped import build_quadruped, keypoint_vertices
from .render import SolidTexture, shade_chunk

log = logging.getLogger(__name__)

PROCEDURAL = {"quadruped": (build_quadruped, keypoint_vertices, "walk"), "lizard": (build_lizard, lizard_keypoints, "crawl")}
"""The built-in models by source name: (builder, keypoints, the one clip)."""


@dataclass
class Shot:
    """How a sequence is filmed."""

    frames: int = 48
    """T, number of frames."""
    fps: float = 24.0
    """Frame rate, frames per second."""
    size: tuple[int, int] = (320, 240)
    """Image (W, H) in pixels."""
    azim: tuple[float, float] = (-30.0, 30.0)
    """Orbit azimuth range A0 -> A1, degrees (0 = the animal's right flank, 90 = its face)."""
    elev: float = 10.0
    """Camera elevation above the target, degrees."""
    path: str = "orbit"
    """Camera path: "orbit" or "pan" (see :func:`s3o_warp.synth.camera.camera_path`)."""
    fov_deg: float = 45.0
    """Horizontal field of view, degrees."""
    fill: float = 0.9
    """Fraction of the shorter image half-side the animal's bounding sphere spans."""
    visibility_tol: float = 0.02
    """Keypoint depth-test tolerance as a fraction of the model's rest bounding-box diagonal."""
    chunk: int = 8
    """Frames rasterised at once (bounds memory)."""


def load_source(source: str | os.PathLike, frames: int, fps: float, seed: int, clip: str | None = None
                ) -> tuple[AnimatedMesh, list[str], np.ndarray]:
    """The animated model and its keypoints (names, rest vertex indices) for ``source``.

    ``source`` is "quadruped" or "lizard" (the procedural models) or a path to a ``.glb``/``.gltf`` file.
    """
    if str(source) in PROCEDURAL:
        build, keypoints, only = PROCEDURAL[str(source)]
        if clip not in (None, only):
            raise InputError(f"synthetic {source}: it has only the clip {only!r}, got --clip {clip!r}")
        mesh = build(frames=frames, fps=fps, seed=seed)
        names, idx = keypoints(mesh)
    else:
        mesh = load_gltf(source, clip=clip, fps=fps, frames=frames)
        names, idx = gltf_keypoints(mesh)
        log.info("%s: %d keypoints: %s", Path(source).name, len(names), ", ".join(names))
    return mesh, names, idx


def _deforming_skeleton(mesh: AnimatedMesh) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Indices of deforming joints, their parents re-indexed (nearest deforming ancestor), names."""
    keep = np.where(mesh.deforming)[0]
    new_of = {int(j): k for k, j in enumerate(keep)}
    parents = []
    for j in keep:
        p = int(mesh.parents[j])
        while p >= 0 and p not in new_of:
            p = int(mesh.parents[p])
        parents.append(new_of.get(p, -1))
    return keep, np.asarray(parents, dtype=np.int32), [mesh.joint_names[j] for j in keep]


def keypoint_visibility(kp_cam: np.ndarray, k: np.ndarray, face_index: np.ndarray, depth: np.ndarray,
                        tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Project keypoints and depth-test them against the z-buffer.

    Args:
        kp_cam: (T, K, 3) keypoints in camera coordinates.
        k: (3, 3) intrinsics.
        face_index: (T, H, W) int, -1 on background.
        depth: (T, H, W) rendered camera z (0 on background).
        tol: depth tolerance (same units as ``kp_cam``).

    Returns:
        xy (T, K, 2) float64 pixel coordinates and visible (T, K) bool: in front of the camera,
        inside the image, and some pixel of the 3x3 neighbourhood of its rounded position covered
        with |depth - z| <= tol.
    """
    z = kp_cam[..., 2]
    off_plane = np.concatenate([kp_cam[..., :2], np.where(np.abs(z) > 1e-12, z, 1e-12)[..., None]], -1)
    xy = project_np(off_plane, k)  # a keypoint on the camera plane (z = 0) is moved off it: finite, and not visible
    num_t, h, w = face_index.shape
    c = np.rint(xy[..., 0]).astype(np.int64)
    r = np.rint(xy[..., 1]).astype(np.int64)
    inside = (z > 0) & (xy[..., 0] >= -0.5) & (xy[..., 0] < w - 0.5) & (xy[..., 1] >= -0.5) & (xy[..., 1] < h - 0.5)
    vis = np.zeros(z.shape, dtype=bool)
    t_idx = np.arange(num_t)[:, None].repeat(z.shape[1], 1)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            rr, cc = np.clip(r + dr, 0, h - 1), np.clip(c + dc, 0, w - 1)
            hit = (face_index[t_idx, rr, cc] >= 0) & (np.abs(depth[t_idx, rr, cc] - z) <= tol)
            vis |= hit
    return xy, vis & inside


def make_sequence(out_dir: str | os.PathLike, source: str | os.PathLike = "quadruped", clip: str | None = None,
                  frames: int = 48, fps: float = 24.0, size: tuple[int, int] = (320, 240),
                  azim: tuple[float, float] = (-30.0, 30.0), elev: float = 10.0, seed: int = 0,
                  path: str = "orbit", device: str = "cpu", overwrite: bool = False,
                  shot: Shot | None = None, progress: bool = True) -> Path:
    """Render a synthetic sequence with ground truth into ``out_dir`` (layout in the module docstring).

    Args:
        out_dir: the sequence folder to create.
        source: "quadruped" or "lizard" (built in, no download) or a ``.glb``/``.gltf`` path.
        clip: glTF animation name (None = the first).
        frames, fps, size (W, H), azim (A0, A1) degrees, elev degrees, path: the shot (see :class:`Shot`).
        seed: fixes the quadruped, its texture and the background.
        device: torch device the rasteriser runs on ("cpu" or "cuda:0").
        overwrite: replace an existing ``out_dir``.
        shot: full shot settings; when given it overrides frames/fps/size/azim/elev/path.
        progress: show a tqdm bar while rendering.

    Returns:
        The sequence folder.

    Raises:
        InputError: bad sizes or counts, an existing ``out_dir`` without ``overwrite``, a bad source.
    """
    out = Path(out_dir)
    if shot is None:
        shot = Shot(frames=frames, fps=fps, size=tuple(size), azim=tuple(azim), elev=elev, path=path)
    w, h = (int(s) for s in shot.size)
    if w < 8 or h < 8:
        raise InputError(f"synthetic sequence: image size {w}x{h} is too small; pass --size WxH with both >= 8")
    if shot.chunk < 1:
        raise InputError(f"synthetic sequence: chunk must be >= 1, got {shot.chunk}")
    if out.exists() and not overwrite:
        raise InputError(f"{out}: already exists; choose another --out or pass --overwrite")
    mesh, kp_names, kp_vertex = load_source(source, shot.frames, shot.fps, seed, clip)
    num_t = mesh.num_frames
    colors = mesh.colors if mesh.colors is not None else np.full((mesh.rest_verts.shape[0], 3), 0.7, np.float32)
    k, cam_from_world = camera_path(mesh.verts, (h, w), shot.path, shot.azim, shot.elev, shot.fov_deg, shot.fill)
    rot, trans = cam_from_world[:, :3, :3], cam_from_world[:, :3, 3]
    verts_cam = (np.einsum("tab,tvb->tva", rot, mesh.verts) + trans[:, None]).astype(np.float32)
    joint_keep, joint_parents, joint_names = _deforming_skeleton(mesh)
    joints_cam = np.einsum("tab,tjb->tja", rot, mesh.joints[:, joint_keep]) + trans[:, None]
    scale = float(np.linalg.norm(mesh.rest_verts.max(0) - mesh.rest_verts.min(0)))
    texture = SolidTexture(scale, seed)
    tol = shot.visibility_tol * scale

    with atomic_dir(out) as tmp:
        (tmp / "images").mkdir()
        (tmp / "masks").mkdir()
        (tmp / "ground_truth").mkdir()
        kp_frames: dict[str, list] = {}
        bar = tqdm(total=num_t, desc="render", unit="frame", disable=not progress)
        for t0 in range(0, num_t, shot.chunk):
            interrupt.check(f"the rendering of {out} (nothing written)")
            t1 = min(num_t, t0 + shot.chunk)
            image, mask, face_index, depth = shade_chunk(
                verts_cam[t0:t1], mesh.faces, k, cam_from_world[t0:t1], mesh.rest_verts, colors, texture,
                (h, w), seed, device)
            xy, vis = keypoint_visibility(verts_cam[t0:t1][:, kp_vertex].astype(np.float64), k, face_index, depth, tol)
            for i in range(t1 - t0):
                name = f"{t0 + i:06d}"
                imwrite(tmp / "images" / f"{name}.png", image[i])  # the folder is renamed into place as a whole
                imwrite(tmp / "masks" / f"{name}.png", mask[i].astype(np.uint8) * 255)
                kp_frames[name] = [[round(float(x), 3), round(float(y), 3), int(v)]
                                   for (x, y), v in zip(xy[i], vis[i])]
            bar.update(t1 - t0)
        bar.close()
        (tmp / "keypoints.json").write_text(json.dumps({"names": kp_names, "frames": kp_frames}))
        np.savez_compressed(
            tmp / "ground_truth" / "ground_truth.npz",
            verts=verts_cam, faces=mesh.faces.astype(np.int32),
            K=np.repeat(k[None], num_t, 0).astype(np.float32),
            cam_from_world=cam_from_world.astype(np.float32),
            image_size=np.array([h, w], dtype=np.int32), fps=np.float32(mesh.fps),
            joints=joints_cam.astype(np.float32), joint_parents=joint_parents, joint_names=np.array(joint_names),
            keypoint_names=np.array(kp_names), keypoint_vertex=kp_vertex.astype(np.int64),
            rest_verts=mesh.rest_verts, colors=colors.astype(np.float32),
            source=np.array(mesh.source), clip=np.array(mesh.clip), seed=np.int64(seed))
        (tmp / "ground_truth" / "README.txt").write_text(__doc__ or "")
    log.info("wrote %s: %d frames %dx%d of %s (%d keypoints)", out, num_t, w, h, mesh.source, len(kp_names))
    return out


def mirror_sequence(src: str | os.PathLike, dst: str | os.PathLike, overwrite: bool = False) -> Path:
    """A copy of the sequence folder ``src`` seen in a mirror: every image and mask flipped left-right, and each
    keypoint of ``keypoints.json`` (when present) moved to x' = W - 1 - x (OpenCV pixel centres), its name and
    visibility kept.

    Any folder with ``images/`` and ``masks/`` will do (a synthetic sequence, DAVIS frames...). Each file keeps its
    name, format and mode (a palette mask its palette); lossless formats (PNG) are flipped bit for bit, JPEG is
    encoded again at quality 95. ``ground_truth/`` is not copied: the mirrored animal is not the model's (its left
    and right change places), so the copy is scored by its masks and keypoints only. Written into a temporary folder
    and renamed into place (:func:`s3o_warp.data.io.atomic_dir`).

    Returns:
        ``dst``.

    Raises:
        InputError: ``src`` without ``images/`` or ``masks/``, an image that cannot be read, an existing ``dst``
        without ``overwrite``.
    """
    src, out = Path(src), Path(dst)
    if out.exists() and not overwrite:
        raise InputError(f"{out}: already exists; choose another folder or pass overwrite=True")
    for sub in ("images", "masks"):
        if not (src / sub).is_dir():
            raise InputError(f"{src / sub}: not found; pass a sequence folder with images/ and masks/")
    widths: dict[str, int] = {}
    with atomic_dir(out) as tmp:
        for sub in ("images", "masks"):
            (tmp / sub).mkdir()
            for p in sorted((src / sub).iterdir()):
                if not p.is_file() or p.name.startswith(".") or p.suffix.lower() not in IMAGE_EXTENSIONS:
                    continue
                try:
                    with Image.open(p) as im:
                        im.load()
                        flipped = im.transpose(Image.Transpose.FLIP_LEFT_RIGHT)
                        fmt, info = im.format, {k: v for k, v in im.info.items() if k in ("transparency", "dpi")}
                except OSError as exc:
                    raise InputError(f"{p}: cannot read this image ({exc.__class__.__name__}); "
                                     "replace or remove it") from None
                flipped.save(tmp / sub / p.name, format=fmt, **info, **({"quality": 95} if fmt == "JPEG" else {}))
                if sub == "images":
                    widths[p.stem] = flipped.width
        if (src / "keypoints.json").is_file():
            kp = read_json(src / "keypoints.json", "keypoints file", "fix or remove it")
            first = next(iter(widths.values()), 0)
            kp["frames"] = {name: [[round(widths.get(name, first) - 1 - x, 6), *rest] for x, *rest in rows]
                            for name, rows in kp["frames"].items()}
            (tmp / "keypoints.json").write_text(json.dumps(kp))
    log.info("wrote %s: %s mirrored (%d frames)", out, src, len(widths))
    return out
