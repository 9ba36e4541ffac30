"""Evaluation metrics: mask IoU, PCK-T keypoint transfer, 3D Chamfer / F-score and skeleton distance.

Pure functions on numpy arrays plus thin readers of a run directory and a sequence folder; the one
entry point that ties them together is :func:`evaluate_run` (``scripts/evaluate.py`` is its CLI).

What is scored (DESIGN.md, "Data contracts"):

* **Prediction** (:func:`load_predictions`): ``<run>/motion.npz`` with
  ``verts_cam`` (T, N, 3) float32, posed vertices in the OpenCV camera frame of each full input frame;
  ``faces`` (F, 3) int32; ``K`` (T, 3, 3) or (3, 3) float32 full-frame intrinsics in pixels (pixel
  (c, r) has its centre at (c, r)); ``image_size`` (2,) int (H, W); ``frame_names`` (T,) str, the
  image file stems; optional ``joints_cam`` (T, J, 3) float32 predicted joints in camera space.
* **Sequence**: ``masks/<stem>.png`` (foreground > 127, or palette index), optional
  ``keypoints.json`` ``{"names": [...], "frames": {"<stem>": [[x, y, visible], ...]}}`` in
  full-frame pixels, optional ``ground_truth/ground_truth.npz`` (:func:`load_ground_truth`).

Metrics:

* Mask IoU per frame: the hard render (face index >= 0) of the prediction at full-frame size against
  the ground-truth mask.
* PCK-T as LASR/ViSER score BADJA (``scripts/eval_badja.py`` / ``eval_pck.py``): every ordered pair
  (i, j), i != j, of annotated frames; every keypoint visible in both; the surface point under the
  keypoint in frame i (z-buffer render; nearest rendered foreground pixel when the keypoint is off
  the silhouette) is carried to frame j: prediction = keypoint_i + proj_j(X) - proj_i(X). Correct
  when closer than ``alpha * sqrt(mask area)`` to the keypoint in frame j; micro-averaged, percent.
* 3D: one similarity (scale, rotation, translation) for the whole sequence aligns the prediction to
  the ground truth (median-depth scale, then symmetric ICP with Umeyama steps); per-frame Chamfer
  distance (mean of both directions, not squared) and F-score at 2% of the ground truth's
  bounding-box diagonal, on area-weighted surface samples; both normalised per frame, then averaged.
* Skeleton: mean distance from each ground-truth deforming joint to the nearest predicted joint
  under the same alignment, over the bounding-box diagonal, averaged over frames.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Literal

import numpy as np
from scipy.spatial import cKDTree
from tqdm.auto import tqdm

from s3o_warp.data.io import read_json, write_bytes
from s3o_warp.data.masks import read_mask
from s3o_warp.errors import InputError

log = logging.getLogger(__name__)

_USD_EXTS = (".usd", ".usda", ".usdc", ".usdz")


# --------------------------------------------------------------------------------------------------
# Readers
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Predictions:
    """A fitted run's per-frame geometry, as written to ``motion.npz``.

    Attributes:
        verts_cam: float32 (T, N, 3) posed vertices, OpenCV camera frame of each input frame.
        faces: int32 (F, 3) triangles (one topology for every frame).
        K: float32 (T, 3, 3) full-frame intrinsics in pixels (a (3, 3) file is broadcast).
        image_size: (H, W) of the input frames in pixels.
        frame_names: T image file stems, in the order of ``verts_cam``.
        joints_cam: float32 (T, J, 3) predicted joint positions in camera space, or None.
        source: the file they were read from.
        weights: float32 (N, B) skinning weights of the vertices, or None.
    """

    verts_cam: np.ndarray
    faces: np.ndarray
    K: np.ndarray
    image_size: tuple[int, int]
    frame_names: list[str]
    joints_cam: np.ndarray | None
    source: Path
    weights: np.ndarray | None = None


@dataclass(frozen=True)
class GroundTruth:
    """Synthetic ground truth (``ground_truth/ground_truth.npz``), camera space of each frame.

    Attributes:
        verts: float32 (T, V, 3) vertices.
        faces: int32 (F, 3).
        joints: float32 (T, J, 3) deforming joints (non-deforming ones already dropped), or None.
        joint_names: J names (may be empty).
        joint_parents: int (J,) parent indices into the full joint list of the file, or None.
        frame_names: T frame stems, or None (then frames pair with the prediction by order).
        K: float32 (T, 3, 3) intrinsics, or None (not needed for 3D metrics).
        image_size: (H, W) or None.
        source: the file they were read from.
        tips: per end joint's name, float32 (T, 3): where its bone ends (the ``<joint>_tip`` keypoint's vertex,
            ``s3o_warp.synth``: a hoof's sole, a toe, an ear's tip); empty when the file has none.
    """

    verts: np.ndarray
    faces: np.ndarray
    joints: np.ndarray | None
    joint_names: list[str]
    joint_parents: np.ndarray | None
    frame_names: list[str] | None
    K: np.ndarray | None
    image_size: tuple[int, int] | None
    source: Path
    tips: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)


@dataclass(frozen=True)
class Keypoints:
    """Annotated 2D keypoints of a sequence (``keypoints.json``).

    Attributes:
        names: P keypoint names.
        frames: frame stem -> float64 (P, 3) rows ``[x, y, visible]``, full-frame pixels (OpenCV
            centre convention), ``visible`` 1 or 0.
        source: the file they were read from, or None.
    """

    names: list[str]
    frames: dict[str, np.ndarray]
    source: Path | None = None


def _load_npz(path: Path, what: str, fix: str) -> dict:
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise InputError(f"{path}: {what} not found; {fix}") from None
    except ValueError as e:
        if "Object arrays" in str(e):
            raise InputError(f"{path}: holds object arrays; save strings as np.array(names, dtype=str)") from None
        raise InputError(f"{path}: not a readable .npz ({e}); {fix}") from None
    except (OSError, EOFError) as e:
        raise InputError(f"{path}: not a readable .npz ({e}); {fix}") from None


def _need(d: dict, key: str, path: Path, what: str) -> np.ndarray:
    if key not in d:
        raise InputError(f"{path}: missing key '{key}' ({what}); present keys: {', '.join(sorted(d)) or 'none'}")
    return d[key]


def _intrinsics(K: np.ndarray, T: int, path: Path, key: str = "K") -> np.ndarray:
    K = np.asarray(K, dtype=np.float32)
    if K.shape == (3, 3):
        K = np.broadcast_to(K, (T, 3, 3)).copy()
    if K.shape != (T, 3, 3):
        raise InputError(f"{path}: '{key}' must have shape (3, 3) or ({T}, 3, 3), got {K.shape}")
    return K


def _image_size(v: np.ndarray, path: Path) -> tuple[int, int]:
    v = np.asarray(v).reshape(-1)
    if v.size != 2 or not np.all(v > 0):
        raise InputError(f"{path}: 'image_size' must be (H, W) positive integers, got {v.tolist()}")
    return int(v[0]), int(v[1])


def load_usd_predictions(path: Path) -> Predictions:
    """Per-frame camera-space geometry of an exported USD (UsdSkel or baked) for scoring.

    Posed points come from UsdSkel's own skinning (``UsdSkel.Cache``) or the baked point samples,
    mapped to the world by the mesh's transform and into each frame's OpenCV camera frame by the
    animated camera; intrinsics are recovered from its focal length and apertures (the inverse of
    DESIGN.md's formulas). Frame names and the image size come from the layer's ``s3o:`` custom data.
    """
    from pxr import Usd, UsdGeom, UsdSkel

    stage = Usd.Stage.Open(str(path))
    if stage is None:
        raise InputError(f"{path}: USD cannot open this file; re-export it with scripts/export.py")
    data = stage.GetRootLayer().customLayerData
    if "s3o:imageSize" not in data:
        raise InputError(f"{path}: not an s3o-warp export (no s3o:imageSize layer data); score its run directory instead")
    H, W = (int(x) for x in data["s3o:imageSize"])
    t0, t1 = int(stage.GetStartTimeCode()), int(stage.GetEndTimeCode())
    names = [str(n) for n in data.get("s3o:frameNames", [])] or [f"{k:06d}" for k in range(t1 - t0 + 1)]
    meshes = [p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
    cams = [p for p in stage.Traverse() if p.IsA(UsdGeom.Camera)]
    if not meshes or not cams:
        raise InputError(f"{path}: needs one mesh and one camera; re-export it with scripts/export.py")
    mesh, cam = UsdGeom.Mesh(meshes[0]), UsdGeom.Camera(cams[0])
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get())
    if (counts != 3).any():
        raise InputError(f"{path}: only triangle meshes can be scored")
    faces = np.array(mesh.GetFaceVertexIndicesAttr().Get(), np.int32).reshape(-1, 3)  # a writable copy
    skel_root = UsdSkel.Root.Find(meshes[0])
    cache = skel_query = skin_query = None
    if skel_root:
        cache = UsdSkel.Cache()
        cache.Populate(skel_root, Usd.PrimDefaultPredicate)
        skin_query = cache.GetSkinningQuery(meshes[0])
        skel_query = cache.GetSkelQuery(UsdSkel.BindingAPI(meshes[0]).GetInheritedSkeleton())
    verts, Ks = [], []
    gl_to_cv = np.diag([1.0, -1.0, -1.0])
    for t in range(t0, t1 + 1):
        pts = mesh.GetPointsAttr().Get(t)
        if skin_query is not None and skin_query:
            skin_query.ComputeSkinnedPoints(skel_query.ComputeSkinningTransforms(t), pts, t)
        m = np.array(UsdGeom.Xformable(meshes[0]).ComputeLocalToWorldTransform(t))  # row-vector
        world = np.asarray(pts, np.float64) @ m[:3, :3] + m[3, :3]
        c2w = np.array(cam.ComputeLocalToWorldTransform(t))
        w2c = np.linalg.inv(c2w)
        gl = world @ w2c[:3, :3] + w2c[3, :3]
        verts.append(gl @ gl_to_cv.T)
        f = cam.GetFocalLengthAttr().Get(t)
        hap, vap = cam.GetHorizontalApertureAttr().Get(t), cam.GetVerticalApertureAttr().Get(t)
        hoff, voff = cam.GetHorizontalApertureOffsetAttr().Get(t), cam.GetVerticalApertureOffsetAttr().Get(t)
        fx, fy = f * W / hap, f * H / vap
        cx, cy = W / 2 - 0.5 - hoff * W / hap, H / 2 - 0.5 + voff * H / vap
        Ks.append([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    return Predictions(np.asarray(verts, np.float32), faces, np.asarray(Ks, np.float32), (H, W), names[: len(verts)], None, path)


def load_predictions(run) -> Predictions:
    """Read a run's ``motion.npz`` (the run directory or the file itself).

    Keys read: ``verts_cam`` (T, N, 3), ``faces`` (F, 3), ``K`` (T, 3, 3) or (3, 3), ``image_size``
    (H, W), ``frame_names`` (T,) str; optional ``joints_cam`` (T, J, 3) and ``weights`` (N, B). Other keys
    are ignored.

    Raises:
        InputError: missing file or key, wrong shapes. A ``.usd``/``.usda``/``.usdc`` path is read with
            :func:`load_usd_predictions`.
    """
    path = Path(run)
    if path.suffix.lower() in _USD_EXTS:
        if not path.is_file():
            raise InputError(f"{path}: no such USD file; pass an exported .usd/.usda/.usdc or a run directory")
        return load_usd_predictions(path)
    if path.is_dir():
        path = path / "motion.npz"
    fix = "pass a run directory that holds motion.npz (written by s3o-fit) or the .npz itself"
    d = _load_npz(path, "prediction file", fix)
    what = "posed vertices (T, N, 3) in camera space"
    verts = np.asarray(_need(d, "verts_cam", path, what), dtype=np.float32)
    if verts.ndim != 3 or verts.shape[-1] != 3 or verts.shape[0] == 0:
        raise InputError(f"{path}: 'verts_cam' must have shape (T, N, 3) with T > 0, got {verts.shape}")
    T = verts.shape[0]
    faces = np.asarray(_need(d, "faces", path, "triangles (F, 3)"))
    _check_faces(faces, verts.shape[1], path)
    K = _intrinsics(_need(d, "K", path, "intrinsics (T, 3, 3)"), T, path)
    size = _image_size(_need(d, "image_size", path, "(H, W)"), path)
    names = [str(s) for s in np.asarray(_need(d, "frame_names", path, "frame stems (T,)")).reshape(-1)]
    if len(names) != T:
        raise InputError(f"{path}: 'frame_names' has {len(names)} entries but 'verts_cam' has {T} frames")
    if len(set(names)) != T:
        raise InputError(f"{path}: 'frame_names' has repeated names; each frame must appear once")
    joints = None
    if "joints_cam" in d:
        joints = np.asarray(d["joints_cam"], dtype=np.float32)
        if joints.ndim != 3 or joints.shape[0] != T or joints.shape[-1] != 3:
            raise InputError(f"{path}: 'joints_cam' must have shape ({T}, J, 3), got {joints.shape}")
    weights = None
    if "weights" in d:
        weights = np.asarray(d["weights"], dtype=np.float32)
        if weights.ndim != 2 or weights.shape[0] != verts.shape[1]:
            raise InputError(f"{path}: 'weights' must have shape ({verts.shape[1]}, B), got {weights.shape}")
    if not np.isfinite(verts).all():
        raise InputError(f"{path}: 'verts_cam' holds NaN or inf; the fit diverged, re-run it")
    return Predictions(verts, faces.astype(np.int32), K, size, names, joints, path, weights)


def _check_faces(faces: np.ndarray, num_verts: int, path) -> None:
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.shape[0] == 0:
        raise InputError(f"{path}: 'faces' must have shape (F, 3) with F > 0, got {faces.shape}")
    if not np.issubdtype(faces.dtype, np.integer):
        raise InputError(f"{path}: 'faces' must be integers, got {faces.dtype}")
    if faces.min() < 0 or faces.max() >= num_verts:
        raise InputError(f"{path}: 'faces' index vertices outside [0, {num_verts}) "
                         f"(range {faces.min()}..{faces.max()})")


GT_FILES = ("ground_truth.npz", "gt.npz")
"""Names of the ground-truth file inside ``ground_truth/`` (``s3o_warp.synth`` writes the first)."""


def load_ground_truth(gt) -> GroundTruth:
    """Read synthetic ground truth: ``ground_truth/ground_truth.npz`` or ``gt.npz`` (the folder or file).

    Keys read: ``verts`` (T, V, 3) camera space and ``faces`` (F, 3) (required); optional
    ``joints`` (T, J, 3) camera space, ``joint_parents`` (J,), ``joint_names`` (J,),
    ``joint_deforming`` or ``deforming`` (J,) bool (non-deforming joints are dropped when present),
    ``frame_names`` (T,), ``K`` (T, 3, 3) or (3, 3), ``image_size`` (2,), ``keypoint_names`` (K,) with
    ``keypoint_vertex`` (K,) (each ``<joint>_tip`` of a joint kept becomes that joint's entry of ``tips``).
    Unknown keys are ignored.
    Without ``frame_names``, :func:`evaluate_run` names the frames by the sorted mask stems of the
    sequence when their count matches (``s3o_warp.synth`` writes ``masks/000000.png`` ...), else by
    order.
    """
    path = Path(gt)
    if path.is_dir():
        found = [path / n for n in GT_FILES if (path / n).is_file()]
        path = found[0] if found else path / GT_FILES[0]
    d = _load_npz(path, "ground-truth file", "pass the sequence's ground_truth/ folder (written by s3o_warp.synth)")
    verts = np.asarray(_need(d, "verts", path, "vertices (T, V, 3) camera space"), dtype=np.float32)
    if verts.ndim != 3 or verts.shape[-1] != 3 or verts.shape[0] == 0:
        raise InputError(f"{path}: 'verts' must have shape (T, V, 3) with T > 0, got {verts.shape}")
    T = verts.shape[0]
    faces = np.asarray(_need(d, "faces", path, "triangles (F, 3)"))
    _check_faces(faces, verts.shape[1], path)
    joints = names = parents = None
    if "joints" in d:
        joints = np.asarray(d["joints"], dtype=np.float32)
        if joints.ndim != 3 or joints.shape[0] != T or joints.shape[-1] != 3:
            raise InputError(f"{path}: 'joints' must have shape ({T}, J, 3), got {joints.shape}")
        J = joints.shape[1]
        names = [str(s) for s in d["joint_names"].reshape(-1)] if "joint_names" in d else []
        parents = np.asarray(d["joint_parents"]).reshape(-1) if "joint_parents" in d else None
        deform_key = "joint_deforming" if "joint_deforming" in d else ("deforming" if "deforming" in d else None)
        if deform_key is not None:
            keep = np.asarray(d[deform_key]).reshape(-1).astype(bool)
            if keep.shape != (J,):
                raise InputError(f"{path}: '{deform_key}' must have shape ({J},), got {keep.shape}")
            joints = joints[:, keep]
            names = [n for n, k in zip(names, keep) if k] if len(names) == J else names
            if parents is not None and parents.shape == (J,):
                # re-index the tree onto the kept joints: each joint hangs from its nearest kept ancestor
                new_index = np.cumsum(keep) - 1
                remapped = []
                for j in np.flatnonzero(keep):
                    p = int(parents[j])
                    while p >= 0 and not keep[p]:
                        p = int(parents[p])
                    remapped.append(int(new_index[p]) if p >= 0 else -1)
                parents = np.asarray(remapped, dtype=np.int64)
    fnames = None
    if "frame_names" in d:
        fnames = [str(s) for s in d["frame_names"].reshape(-1)]
        if len(fnames) != T:
            raise InputError(f"{path}: 'frame_names' has {len(fnames)} entries but 'verts' has {T} frames")
    K = _intrinsics(d["K"], T, path) if "K" in d else None
    size = _image_size(d["image_size"], path) if "image_size" in d else None
    tips = {}
    if names and "keypoint_names" in d and "keypoint_vertex" in d:
        kv = np.asarray(d["keypoint_vertex"]).reshape(-1)
        for kn, v in zip((str(s) for s in d["keypoint_names"].reshape(-1)), kv):
            if kn.endswith("_tip") and kn[:-4] in names:
                if not 0 <= int(v) < verts.shape[1]:
                    raise InputError(f"{path}: keypoint {kn!r} names vertex {int(v)}, but there are {verts.shape[1]}")
                tips[kn[:-4]] = verts[:, int(v)]
    return GroundTruth(verts, faces.astype(np.int32), joints, names or [], parents, fnames, K, size, path, tips)


def write_json(obj, path) -> Path:
    """Write ``obj`` as indented JSON to ``path`` atomically (temporary name, fsync, rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_bytes(path, json.dumps(obj, indent=1).encode())


def load_keypoints(path) -> Keypoints:
    """Read ``keypoints.json``: ``{"names": [P], "frames": {stem: [[x, y, visible], ...] (P rows)}}``."""
    path = Path(path)
    data = read_json(path, "keypoints file", "pass a keypoints.json (python -m s3o_warp.data.keypoints converts BADJA files)")
    if not isinstance(data, dict) or not isinstance(data.get("frames"), dict):
        raise InputError(f"{path}: expected {{\"names\": [...], \"frames\": {{stem: [[x, y, visible], ...]}}}}; "
                         "convert BADJA files with python -m s3o_warp.data.keypoints")
    names = [str(n) for n in data.get("names", [])]
    frames = {}
    for stem, rows in data["frames"].items():
        a = np.asarray(rows, dtype=np.float64)
        if a.ndim != 2 or a.shape[1] != 3:
            raise InputError(f"{path}: frame '{stem}' must be a list of [x, y, visible] rows, got shape {a.shape}")
        frames[str(stem)] = a
    counts = {a.shape[0] for a in frames.values()}
    if len(counts) > 1:
        raise InputError(f"{path}: frames have different keypoint counts {sorted(counts)}; "
                         "every frame needs one row per name")
    P = counts.pop() if counts else len(names)
    if names and len(names) != P:
        raise InputError(f"{path}: {len(names)} names but {P} keypoints per frame")
    return Keypoints(names or [f"kp{p}" for p in range(P)], frames, path)


def load_masks(masks_dir, frame_names: list[str], image_size: tuple[int, int] | None = None,
               object_id: int | None = None) -> np.ndarray:
    """Ground-truth masks of the named frames -> bool (T, H, W), read from ``masks_dir/<stem>.png``.

    Raises:
        InputError: missing folder or file, or a mask whose size is not ``image_size``.
    """
    d = Path(masks_dir)
    if not d.is_dir():
        raise InputError(f"{d}: masks folder not found; pass a sequence with masks/ (or --masks DIR)")
    out = None
    for t, stem in enumerate(frame_names):
        p = d / f"{stem}.png"
        if not p.exists():
            alts = [q for q in d.glob(f"{stem}.*")]
            p = alts[0] if alts else p
        if not p.exists():
            raise InputError(f"{p}: mask not found; every predicted frame needs masks/<frame>.png")
        m = read_mask(p, object_id)
        if image_size is not None and m.shape != tuple(image_size):
            raise InputError(f"{p}: mask is {m.shape[1]}x{m.shape[0]} but the prediction's frames are "
                             f"{image_size[1]}x{image_size[0]}; score against the sequence the run was fitted on")
        if out is None:
            out = np.zeros((len(frame_names),) + m.shape, dtype=bool)
        elif m.shape != out.shape[1:]:
            raise InputError(f"{p}: mask size {m.shape} differs from the first mask's {out.shape[1:]}")
        out[t] = m
    if out is None:
        raise InputError(f"{d}: no frames to read")
    return out


# --------------------------------------------------------------------------------------------------
# Rendering
# --------------------------------------------------------------------------------------------------


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
    import torch

    if rasterizer is None:
        from s3o_warp.kernels.raster import rasterize as rasterizer

    T = verts.shape[0]
    f_t = torch.as_tensor(np.ascontiguousarray(faces, dtype=np.int32), device=device)
    bar = tqdm(total=T, desc="render", unit="frame", leave=False, disable=not progress)
    try:
        for s in range(0, T, max(1, int(chunk))):
            e = min(T, s + max(1, int(chunk)))
            v_t = torch.as_tensor(np.ascontiguousarray(verts[s:e], dtype=np.float32), device=device)
            k_t = torch.as_tensor(np.ascontiguousarray(K[s:e], dtype=np.float32), device=device)
            with torch.no_grad():
                fi, bary, _depth = rasterizer(v_t, f_t, k_t, image_size=tuple(int(x) for x in image_size))
            yield s, fi.cpu().numpy().astype(np.int32, copy=False), bary.cpu().numpy().astype(np.float32, copy=False)
            bar.update(e - s)
    finally:
        bar.close()


# --------------------------------------------------------------------------------------------------
# Pure metrics
# --------------------------------------------------------------------------------------------------


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


def project(points: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pinhole projection: (..., 3) camera-space points, K (..., 3, 3) broadcastable -> (..., 2) pixels."""
    p = np.einsum("...ij,...j->...i", K, points)
    return p[..., :2] / p[..., 2:3]


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


def pck_transfer(keypoints: np.ndarray, verts: np.ndarray, faces: np.ndarray, K: np.ndarray,
                 kp_face: np.ndarray, kp_bary: np.ndarray, mask_area: np.ndarray, alpha: float = 0.2,
                 threshold_frame: Literal["reference", "target"] = "reference", chunk_elements: int = 2_000_000,
                 pair_limit: int = 5_000_000) -> dict:
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

    Returns:
        dict: ``pck`` (percent, NaN when nothing was scored), ``correct``, ``total`` (pairs x
        keypoints scored), ``pairs`` (ordered frame pairs), ``per_keypoint_correct`` and
        ``per_keypoint_total`` (P,) int arrays, ``pred`` float64 (A, A, P, 2) transferred positions
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
    kp_correct = np.zeros(P, np.int64)
    kp_total = np.zeros(P, np.int64)
    step = max(1, int(chunk_elements // max(1, A * P)))  # reference frames per chunk: memory O(A P), not O(A^2 P)
    for i0 in range(0, A, step):
        sl = slice(i0, min(A, i0 + step))
        ii = np.arange(sl.start, sl.stop)
        corners = V[:, tri_all[sl]]  # (A_j, c, P, 3, 3)
        X = np.einsum("ipk,jipkc->ijpc", w_all[sl], corners)  # (c, A_j, P, 3)
        proj = project(X, Kd[None, :, None])  # proj[i, j, p]: frame i's surface point seen in frame j
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
        kp_correct += correct.sum(axis=(0, 1))
        kp_total += valid.sum(axis=(0, 1))
        if keep_pairs:
            pred_all[sl], valid_all[sl] = pred, valid
    return {
        "pck": 100.0 * correct_n / total if total else float("nan"),
        "correct": correct_n,
        "total": total,
        "pairs": A * (A - 1),
        "per_keypoint_correct": kp_correct,
        "per_keypoint_total": kp_total,
        "pred": pred_all,
        "valid": valid_all,
    }


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
    v = np.asarray(verts, dtype=np.float64)
    tri = v[np.asarray(faces, dtype=np.int64)]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=-1)
    rng = np.random.default_rng(seed)
    if not np.isfinite(area).all() or area.sum() <= 0:
        return v[rng.integers(0, v.shape[0], n)]
    cdf = np.cumsum(area)
    f = np.minimum(np.searchsorted(cdf, rng.random(n) * cdf[-1], side="right"), len(area) - 1)
    r1, r2 = np.sqrt(rng.random(n)), rng.random(n)
    w = np.stack([1.0 - r1, r1 * (1.0 - r2), r1 * r2], axis=1)
    return np.einsum("nk,nkc->nc", w, tri[f])


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


def skeleton_distance(pred_joints: np.ndarray, gt_joints: np.ndarray, diag: np.ndarray,
                      sim: Similarity | None = None) -> dict:
    """Distance of every ground-truth joint to the nearest predicted joint, per frame.

    Args:
        pred_joints: float (T, Jp, 3) predicted joints, camera space (``sim`` is applied to them).
        gt_joints: float (T, J, 3) ground-truth deforming joints, camera space.
        diag: (T,) normalisers (the ground truth's bbox diagonal per frame).
        sim: the sequence alignment of the prediction (identity when None).

    Returns:
        ``{"distance": mean over frames of mean_j min_k |gt_j - pred_k| / diag,
        "distance_pred_to_gt": the reverse direction, "per_frame": [...], "gt_joints": J,
        "pred_joints": Jp}``.
    """
    T, J = gt_joints.shape[:2]
    Jp = pred_joints.shape[1]
    if pred_joints.shape[0] != T:
        raise ValueError(f"skeleton_distance(): {pred_joints.shape[0]} predicted frames but {T} ground-truth frames")
    if Jp == 0 or J == 0:
        return {"distance": float("nan"), "distance_pred_to_gt": float("nan"), "per_frame": [],
                "gt_joints": J, "pred_joints": Jp}
    pj = sim(pred_joints) if sim is not None else np.asarray(pred_joints, dtype=np.float64)
    d = np.linalg.norm(np.asarray(gt_joints, dtype=np.float64)[:, :, None] - pj[:, None], axis=-1)  # (T, J, Jp)
    norm = np.asarray(diag, dtype=np.float64)
    per_frame = d.min(axis=2).mean(axis=1) / norm
    rev = d.min(axis=1).mean(axis=1) / norm
    return {"distance": float(per_frame.mean()), "distance_pred_to_gt": float(rev.mean()),
            "per_frame": per_frame.tolist(), "gt_joints": int(J), "pred_joints": int(Jp)}


def joints_inside(joints: np.ndarray, verts: np.ndarray, faces: np.ndarray, device: str = "cpu") -> dict:
    """Does the skeleton sit inside the body? Signed distance of each joint to its frame's posed mesh.

    Args:
        joints: float (T, J, 3) joint positions per frame; verts: float (T, N, 3) posed vertices of
            the same frames (same space); faces: int (F, 3).
        device: where the closest-point kernel runs.

    Returns:
        ``{"fraction", "per_joint", "max_outside"}``: the fraction of (frame, joint) pairs inside the
        mesh (winding-number sign), the per-joint fraction over frames, and the largest distance of
        a joint outside (0 when none is), in the units of ``verts``.
    """
    import torch

    from s3o_warp.kernels.sdf import closest_point

    J = np.asarray(joints, np.float64)
    V = np.asarray(verts, np.float64)
    if J.ndim != 3 or J.shape[0] != V.shape[0]:
        raise ValueError(f"joints_inside(): joints {J.shape} and verts {V.shape} must be (T, J, 3) and (T, N, 3)")
    f = torch.as_tensor(np.asarray(faces, np.int64))
    inside = np.zeros(J.shape[:2], bool)
    worst = 0.0
    for t in range(J.shape[0]):
        d, _, _ = closest_point(torch.as_tensor(V[t], dtype=torch.float32), f,
                                torch.as_tensor(J[t], dtype=torch.float32), device=device)
        d = d.cpu().numpy()
        inside[t] = d < 0
        worst = max(worst, float(d.max(initial=0.0)))
    return {"fraction": float(inside.mean()) if inside.size else float("nan"),
            "per_joint": inside.mean(0).tolist(), "max_outside": worst}


def gt_limbs(parents: np.ndarray, names: list[str] | None = None) -> list[dict]:
    """The limbs of a joint tree: from each leaf up to (and including) the nearest branching ancestor.

    Concretely, a limb ``{"name": "foot_fl", "joints": [8, 9, 10]}`` is the chain shoulder -> knee ->
    foot of a quadruped's front-left leg (the shoulder being where the chain meets the body).
    """
    parents = np.asarray(parents, dtype=np.int64)
    J = len(parents)
    children = np.bincount(parents[parents >= 0], minlength=J)
    limbs = []
    for leaf in np.flatnonzero(children == 0):
        chain = [int(leaf)]
        p = int(parents[leaf])
        while p >= 0:
            chain.append(p)
            if children[p] > 1 or parents[p] < 0:
                break
            p = int(parents[p])
        if len(chain) >= 2:
            nm = names[leaf] if names is not None and len(names) == J else f"joint_{leaf}"
            limbs.append({"name": nm, "joints": chain[::-1]})
    return limbs


def _point_polyline_distance(points: np.ndarray, poly: np.ndarray, along: bool = False):
    """Distance of each of ``points (M, 3)`` to the polyline ``poly (K, 3)`` (K = 1: to that point); with
    ``along`` also where the nearest point of the polyline is, as a fraction of its length from its start."""
    if len(poly) == 1:
        d = np.linalg.norm(points - poly[0], axis=-1)
        return (d, np.zeros(len(points))) if along else d
    a, b = poly[:-1], poly[1:]
    ab = b - a
    t = np.clip(np.einsum("mkd,kd->mk", points[:, None] - a[None], ab) / np.maximum((ab * ab).sum(-1), 1e-12), 0, 1)
    q = a[None] + t[..., None] * ab[None]
    dk = np.linalg.norm(points[:, None] - q, axis=-1)
    k = dk.argmin(1)
    if not along:
        return dk[np.arange(len(points)), k]
    seg = np.linalg.norm(ab, axis=-1)
    start = np.concatenate([[0.0], np.cumsum(seg)[:-1]])
    s = (start[k] + t[np.arange(len(points)), k] * seg[k]) / max(seg.sum(), 1e-12)
    return dk[np.arange(len(points)), k], s


def _distinct(pos: np.ndarray, d: np.ndarray, min_separation: float) -> np.ndarray:
    """Per joint, its distance ``d`` to the chain, or inf when a nearer joint's place along the chain ``pos``
    (a fraction of its length) is within ``min_separation`` of its own: joints at one place along a limb (a
    knot, or two side by side at its top) count once, by the nearest of them."""
    out = d.copy()
    kept: list[float] = []
    for j in np.argsort(d, kind="stable"):
        if any(abs(pos[j] - k) < min_separation for k in kept):
            out[j] = np.inf
        else:
            kept.append(float(pos[j]))
    return out


def chain_coverage(pred_joints: np.ndarray, gt_joints: np.ndarray, chain, diag: np.ndarray,
                   sim: Similarity | None = None, tol: float = 0.05, min_joints: int = 2,
                   min_separation: float = 0.0) -> dict:
    """Is there a learned joint chain along one ground-truth joint chain (``chain``: joint indices, a polyline;
    one index: a point)? The test of :func:`limb_coverage` for any chain, for example a neck between two
    branchings. Returns ``median_pred_joints`` (within ``tol`` x the bbox diagonal), ``covered`` (``min_joints``
    or more in at least half of the frames), ``tol_needed`` (covered at every ``tol`` above it; None with
    fewer than ``min_joints`` predicted joints, or distinct ones in half the frames) and ``median_span``: per frame, how much of the chain's length
    lies between the first and the last of the joints within ``tol`` (their nearest points on it), the median
    over the frames. Two joints in a knot at the hip cover a leg with a span near 0; a hip and a knee, about
    half of it. With ``min_separation`` > 0, joints whose places along the chain (nearest points, as fractions
    of its length) are closer than that to a nearer joint's count once per frame: a knot is one joint, and a
    chain must spread along the limb."""
    pj = sim(pred_joints) if sim is not None else np.asarray(pred_joints, dtype=np.float64)
    gj = np.asarray(gt_joints, dtype=np.float64)
    T = gj.shape[0]
    ds = [_point_polyline_distance(pj[t], gj[t, list(chain)], along=True) for t in range(T)]
    d = np.stack([x[0] / diag[t] for t, x in enumerate(ds)])
    pos = np.stack([x[1] for x in ds])
    if min_separation > 0:
        d = np.stack([_distinct(pos[t], d[t], min_separation) for t in range(T)])
    near = d < tol
    counts = near.sum(1)
    span = np.where(near.any(1), np.where(near, pos, -np.inf).max(1) - np.where(near, pos, np.inf).min(1), 0.0)
    # the min_joints-th nearest joint per frame; covered iff it is < tol in ceil(T / 2) frames or more
    kth = np.sort(d, axis=1)[:, min_joints - 1] if d.shape[1] >= min_joints else None
    need = None if kth is None else float(np.sort(kth)[int(np.ceil(T / 2)) - 1])
    return {"median_pred_joints": float(np.median(counts)), "covered": bool((counts >= min_joints).mean() >= 0.5),
            "tol_needed": need if need is None or np.isfinite(need) else None,
            "median_span": float(np.median(span))}


def limb_coverage(pred_joints: np.ndarray, gt_joints: np.ndarray, gt_parents: np.ndarray, diag: np.ndarray,
                  sim: Similarity | None = None, names: list[str] | None = None, tol: float = 0.05,
                  min_joints: int = 2, branch: bool = True, min_separation: float = 0.0,
                  tips: dict[int, np.ndarray] | None = None) -> dict:
    """Does every ground-truth limb have a learned joint chain along it?

    A limb (see :func:`gt_limbs`) counts as covered when, in at least half of the frames, ``min_joints``
    or more predicted joints lie within ``tol`` x the bbox diagonal of the limb's polyline (after the
    sequence alignment ``sim``). Returns per-limb median counts, ``tol_needed`` (the limb is covered at
    every ``tol`` above it; None with fewer than ``min_joints`` predicted joints) and the covered fraction.
    ``branch=False`` leaves the branching ancestor out of the polyline (the limb's own joints: a tail from its
    base, not from the pelvis), so a joint where the limb meets the body, or a neighbouring limb's, does not
    count for it. ``min_separation`` > 0: joints closer than that along the chain (a fraction of its length) to
    a nearer one count once (:func:`chain_coverage`), so a knot at the top of a leg does not pass for a chain.
    ``tips`` (end joint index -> (T, 3) points): a limb whose end joint has one goes on to it, so its last bone
    is part of it (a joint's position is where its bone starts: a horse's lower-leg joint is its knee, and a
    third of the leg lies between it and the hoof).
    """
    gj = np.asarray(gt_joints, dtype=np.float64)
    J = gj.shape[1]
    out = []
    for limb in gt_limbs(gt_parents, names):
        chain = limb["joints"] if branch else limb["joints"][1:]
        tip = (tips or {}).get(limb["joints"][-1])
        points, chain = (gj, chain) if tip is None else (  # the end joint's tip as one more point of the polyline
            np.concatenate([gj, np.asarray(tip, np.float64)[:, None]], 1), list(chain) + [J])
        c = chain_coverage(pred_joints, points, chain, diag, sim, tol, min_joints, min_separation)
        out.append({"limb": limb["name"], "gt_joints": len(limb["joints"]), "to_tip": tip is not None, **c})
    n = len(out)
    return {"limbs": out, "covered": sum(o["covered"] for o in out), "total": n, "tol": tol, "min_joints": min_joints,
            "branch": branch, "min_separation": min_separation, "to_tip": any(o["to_tip"] for o in out)}


def empty_bones(weights: np.ndarray) -> dict:
    """Bones that are the largest weight of no vertex (``weights`` ``(N, B)``): they move nothing, and their
    joints fall back to far-apart borders. Returns ``count`` (B) and ``empty`` (their indices)."""
    W = np.asarray(weights)
    if W.ndim != 2 or W.shape[1] == 0:
        raise ValueError(f"empty_bones(): weights must have shape (N, B) with B >= 1, got {W.shape}")
    from s3o_warp.skeleton.edit import assign_parts

    owned = np.bincount(assign_parts(W), minlength=W.shape[1])
    return {"count": int(W.shape[1]), "empty": np.flatnonzero(owned == 0).tolist()}


def limb_identity(pred_verts: np.ndarray, weights: np.ndarray, gt_joints: np.ndarray, gt_parents: np.ndarray,
                  sim: Similarity | None = None, names: list[str] | None = None, k: int = 5) -> dict:
    """Do the fitted limbs keep their identity through the video, or swap places (legs that bounce off
    each other where the real ones cross)?

    Per ground-truth limb (see :func:`gt_limbs`) and frame, the ``k`` predicted vertices nearest to the
    limb's tip joint (after the sequence alignment ``sim``) vote with their dominant bone. The limb's bone
    is the most frequent winner over the frames. A frame is *swapped* when the winner is another limb's
    bone and not its own. Returns per limb its bone, the fraction of frames it wins (``kept``), the
    ``swapped`` fraction and ``shared`` (another limb has the same bone: the fit gave both one part), and
    ``mean_swapped`` over the limbs.
    """
    pv = sim(pred_verts) if sim is not None else np.asarray(pred_verts, dtype=np.float64)  # (T, N, 3)
    T = pv.shape[0]
    gj = np.asarray(gt_joints, dtype=np.float64)
    dom = np.asarray(weights).argmax(1)
    k = max(1, min(int(k), pv.shape[1]))
    limbs = gt_limbs(gt_parents, names)
    wins = np.empty((len(limbs), T), dtype=np.int64)
    for i, limb in enumerate(limbs):
        tip = gj[:, limb["joints"][-1]]  # (T, 3)
        near = np.argpartition(np.linalg.norm(pv - tip[:, None], axis=-1), k - 1, axis=1)[:, :k]
        wins[i] = [np.bincount(dom[n]).argmax() for n in near]
    own = [int(np.bincount(w).argmax()) for w in wins]
    out = []
    for i, limb in enumerate(limbs):
        others = {b for j, b in enumerate(own) if j != i and b != own[i]}
        out.append({"limb": limb["name"], "bone": own[i], "kept": float((wins[i] == own[i]).mean()),
                    "swapped": float(np.isin(wins[i], list(others)).mean()) if others else 0.0,
                    "shared": own.count(own[i]) > 1})
    return {"limbs": out, "mean_swapped": float(np.mean([o["swapped"] for o in out])) if out else 0.0, "k": k}


# --------------------------------------------------------------------------------------------------
# Whole-run evaluation
# --------------------------------------------------------------------------------------------------


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
        ``frames``, ``alpha``, ``threshold_frame``, ``per_keypoint``), ``shape_3d`` (see
        :func:`shape_metrics`), ``skeleton`` (see :func:`skeleton_distance`), ``limb_identity`` (see
        :func:`limb_identity`), each present only when its inputs are, and ``skipped`` {metric: reason}
        for the others.

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
                             alpha, threshold_frame)
            result["pck_t"] = {
                "pck": r["pck"], "correct": r["correct"], "total": r["total"], "pairs": r["pairs"],
                "frames": len(ann), "alpha": alpha, "threshold_frame": threshold_frame,
                "per_keypoint": {n: {"pck": (100.0 * c / t if t else None), "correct": int(c), "total": int(t)}
                                 for n, c, t in zip(kps.names, r["per_keypoint_correct"], r["per_keypoint_total"])},
            }
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
    if ground_truth is not None:
        gt = load_ground_truth(ground_truth)
        if gt.frame_names is None and masks_dir is not None and masks_dir.is_dir():
            stems = sorted(p.stem for p in masks_dir.iterdir() if p.suffix.lower() == ".png")
            if len(stems) == gt.verts.shape[0]:
                gt = dataclasses.replace(gt, frame_names=stems)
        pi, gi = _pair_frames(pred.frame_names, gt, pred.source)
        shape, sim = shape_metrics(pred.verts_cam[pi], pred.faces, gt.verts[gi], gt.faces, n_points=n_points,
                                   fscore_ratio=fscore_ratio, icp_iters=icp_iters, seed=seed)
        shape["frames"] = int(len(pi))
        result["shape_3d"] = shape
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
                    sims = frame_similarities(pred.verts_cam[pi], pred.faces, gt.verts[gi], gt.faces, sim, seed=seed)
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
    return write_json(_jsonable(metrics), path)


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
