"""Readers of what is scored: a run's predictions (``motion.npz`` or an exported USD), a sequence's masks and
keypoints, and synthetic ground truth (docs/method.md, "Conventions").

* **Prediction** (:func:`load_predictions`): ``<run>/motion.npz`` with
  ``verts_cam`` (T, N, 3) float32, posed vertices in the OpenCV camera frame of each full input frame;
  ``faces`` (F, 3) int32; ``K`` (T, 3, 3) or (3, 3) float32 full-frame intrinsics in pixels (pixel
  (c, r) has its centre at (c, r)); ``image_size`` (2,) int (H, W); ``frame_names`` (T,) str, the
  image file stems; optional ``joints_cam`` (T, J, 3) float32 predicted joints in camera space.
* **Sequence**: ``masks/<stem>.png`` (foreground > 127, or palette index, :func:`load_masks`), optional
  ``keypoints.json`` ``{"names": [...], "frames": {"<stem>": [[x, y, visible], ...]}}`` in
  full-frame pixels (:func:`load_keypoints`), optional ``ground_truth/ground_truth.npz`` (:func:`load_ground_truth`).

Every reader raises a one-line ``InputError`` that names the file and the fix.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pxr import Usd, UsdGeom, UsdSkel

from s3o_warp.data.io import read_json
from s3o_warp.data.masks import read_mask
from s3o_warp.errors import InputError

_USD_EXTS = (".usd", ".usda", ".usdc", ".usdz")


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
        cam_from_world: float64 (T, 4, 4) world -> camera transforms (world: the model's object frame, +y up),
            or None; the views from every side (:mod:`~s3o_warp.evaluation.views`) need it.
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
    cam_from_world: np.ndarray | None = None
    keypoints: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)
    """Per keypoint name, float32 (T, 3): its surface point (``keypoint_vertex``) in camera space; empty when the
    file has none."""


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
    animated camera; intrinsics are recovered from its focal length and apertures (the inverse of the
    USD camera formulas in docs/method.md, "Conventions"). Frame names and the image size come from the
    layer's ``s3o:`` custom data.
    """
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
    ``keypoint_vertex`` (K,) (each ``<joint>_tip`` of a joint kept becomes that joint's entry of ``tips``),
    ``cam_from_world`` (T, 4, 4). Unknown keys are ignored.
    Without ``frame_names``, :func:`~s3o_warp.evaluation.report.evaluate_run` names the frames by the sorted mask
    stems of the sequence when their count matches (``s3o_warp.synth`` writes ``masks/000000.png`` ...), else by
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
    tips, points = {}, {}
    if "keypoint_names" in d and "keypoint_vertex" in d:
        kv = np.asarray(d["keypoint_vertex"]).reshape(-1)
        for kn, v in zip((str(s) for s in d["keypoint_names"].reshape(-1)), kv):
            if not 0 <= int(v) < verts.shape[1]:
                raise InputError(f"{path}: keypoint {kn!r} names vertex {int(v)}, but there are {verts.shape[1]}")
            points[kn] = verts[:, int(v)]
            if names and kn.endswith("_tip") and kn[:-4] in names:
                tips[kn[:-4]] = points[kn]
    c2w = None
    if "cam_from_world" in d:
        c2w = np.asarray(d["cam_from_world"], dtype=np.float64)
        if c2w.shape != (T, 4, 4):
            raise InputError(f"{path}: 'cam_from_world' must have shape ({T}, 4, 4), got {c2w.shape}")
    return GroundTruth(verts, faces.astype(np.int32), joints, names or [], parents, fnames, K, size, path, tips, c2w,
                       points)


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

