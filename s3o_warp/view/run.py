"""What the viewer shows of a run directory, as plain arrays (numpy only: no viser, no torch for a finished run).

A finished fit is read from what :func:`s3o_warp.export.rig.save_rig` wrote: ``motion.npz`` (``verts_cam``, the rig's
own posed vertices of every frame in its camera, and ``joints_cam``, ``root``, ``K``, ``bone_motion``, ``colors``,
``faces``) and ``skeleton.json`` (joints, bone centres, ``world_from_object``). A fit still running has no
``motion.npz`` yet (or an older one than its checkpoints): its newest checkpoint is posed by the package's own code
(the model it saved, :func:`s3o_warp.run.outputs.rig_from_model`, :meth:`s3o_warp.export.rig.Rig.posed_camera`).

A fit of several videos (``videos.json``: their names in order) is shown one video at a time: a finished one from
``videos/<video>/``, a one-video run directory each (its ``motion.npz``, ``skeleton.json``, ``metrics.json``); a
running one from its checkpoint, whose frames are the videos' one after another (the model's ``video_of``), each
video's range posed on its own (names from ``videos.json``, else the checkpoint's ``a+b`` sequence name, else
"video 0", "video 1", ...).

World frame: the exported files' (Y up, :mod:`s3o_warp.export.rig`). A point of frame t's OpenCV camera frame goes
to the world by ``world_from_object @ inv(root[t])``, which is also that frame's camera-to-world transform in OpenCV
axes (+x right, +y down, +z forward), viser's convention for cameras.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from s3o_warp.errors import InputError

log = logging.getLogger(__name__)

MOTION_KEYS = ("verts_cam", "faces", "root", "K", "image_size", "fps", "frame_names")
"""What ``motion.npz`` must hold for the viewer (``save_rig`` writes them all)."""

SURFACES = ("colours", "plain", "see-through", "hidden")
"""How the page can draw the mesh (its "surface" choice; ``s3o-view --surface``)."""

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".webp", ".tif", ".tiff")

VIDEOS_FILE = "videos.json"
"""What a fit of several videos writes beside its ``videos/`` folder: ``{"videos": [name, ...]}`` in order."""

_warned: set = set()


def _warn_once(msg: str, *args) -> None:
    """A warning logged once per process (the viewer reads a running fit again and again)."""
    text = msg % args
    if text not in _warned:
        _warned.add(text)
        log.warning(text)


@dataclass
class FitView:
    """One state of a fit as the page draws it: world-frame arrays per frame, the cameras, figures and settings.

    Attributes:
        run: the run directory.
        source: the file the state came from (``motion.npz`` or a checkpoint).
        label: what the state is, in words ("finished fit", "checkpoint joint step 400").
        verts: (T, N, 3) float32 posed vertices in the world frame.
        faces: (F, 3) int32 triangles.
        colors: (N, 3) float32 linear RGB vertex colours in [0, 1].
        joints: (T, J, 3) float32 posed joints (world), J may be 0.
        centres: (T, B, 3) float32 posed bone centres (world): each centre moved by its own bone.
        bone_links: (S, 2) int, each drawn bone segment as (joint, bone): joint j to the centre of bone b.
        cam_to_world: (T, 4, 4) float64 fitted camera of every frame (OpenCV axes, world frame).
        K: (T, 3, 3) float64 full-frame intrinsics.
        image_size: (H, W) of the input frames.
        fps: the video's frame rate.
        frame_names: T frame names.
        metrics: ``metrics.json`` (None while the fit runs); of a fit of several videos, the shown video's.
        config_text: ``config.toml`` as written (None if absent).
        sequence: where the input frames are (None when not found: the cameras are drawn without images).
        videos: the names of the fit's videos in order ([] for a fit of one video).
        video: which of them this is (0 for a fit of one video).
    """

    run: Path
    source: Path
    label: str
    verts: np.ndarray
    faces: np.ndarray
    colors: np.ndarray
    joints: np.ndarray
    centres: np.ndarray
    bone_links: np.ndarray
    cam_to_world: np.ndarray
    K: np.ndarray
    image_size: tuple[int, int]
    fps: float
    frame_names: list[str]
    metrics: dict | None = None
    config_text: str | None = None
    sequence: Path | None = None
    videos: list[str] = field(default_factory=list)
    video: int = 0

    @property
    def num_frames(self) -> int:
        return int(self.verts.shape[0])

    def fov_y(self, t: int) -> float:
        """Vertical field of view of frame t's camera, radians."""
        return 2.0 * math.atan(0.5 * self.image_size[0] / float(self.K[t, 1, 1]))

    def aspect(self, t: int) -> float:
        """Width over height of frame t's picture as its camera sees it (fx / fy folded in)."""
        H, W = self.image_size
        return (W / float(self.K[t, 0, 0])) / (H / float(self.K[t, 1, 1]))

    def bone_segments(self, t: int) -> np.ndarray:
        """(S, 2, 3) float32 the skeleton of frame t: a segment from each joint to the centre of each of its bones."""
        if not len(self.bone_links):
            return np.zeros((0, 2, 3), np.float32)
        j, b = self.bone_links[:, 0], self.bone_links[:, 1]
        return np.stack([self.joints[t, j], self.centres[t, b]], 1).astype(np.float32)

    def centre(self) -> np.ndarray:
        """(3,) the middle of the posed meshes' bounding box over every frame (world)."""
        return 0.5 * (self.verts.min((0, 1)) + self.verts.max((0, 1))).astype(np.float64)

    def size(self) -> float:
        """The canonical size of the scene: the bounding-box diagonal of frame 0's mesh."""
        v = self.verts[0]
        return float(np.linalg.norm(v.max(0) - v.min(0))) or 1.0

    def depth_range(self, t: int) -> tuple[float, float]:
        """Nearest and farthest depth of frame t's mesh seen from its camera."""
        c2w = self.cam_to_world[t]
        z = (self.verts[t] - c2w[:3, 3]) @ c2w[:3, 2]
        return float(z.min()), float(z.max())


# --------------------------------------------------------------------------------------------- what to read
def checkpoints(run: Path) -> list[Path]:
    """The run's step checkpoints, oldest first by name (phase index, then step: the order the fit writes them)."""
    ck = run / "checkpoints"
    return sorted(ck.glob("step-*.pt"), key=lambda p: p.name) if ck.is_dir() else []


def _mtime(p: Path) -> int | None:
    try:
        return p.stat().st_mtime_ns
    except OSError:
        return None


def signature(run: Path) -> tuple:
    """What changes when the fit writes something the page shows: ``motion.npz``'s (each video's) and the newest
    checkpoint's names and times (the viewer polls this)."""
    cks = checkpoints(run)
    newest = cks[-1] if cks else None
    try:
        homes = [run / "videos" / n for n in video_names(run)] or [run]
    except InputError:  # videos.json half-way through being written: its time is in the signature
        homes = [run]
    return (_mtime(run / VIDEOS_FILE), newest.name if newest else None, _mtime(newest) if newest else None,
            _mtime(run / "metrics.json"), tuple((_mtime(h / "motion.npz"), _mtime(h / "metrics.json")) for h in homes))


def video_names(run: Path) -> list[str]:
    """The videos of a finished fit of several, in order (``videos.json``); [] for a fit of one video.

    Raises:
        InputError: ``videos.json`` is malformed.
    """
    p = Path(run) / VIDEOS_FILE
    if not p.is_file():
        return []
    try:
        names = json.loads(p.read_text())["videos"]
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise InputError(f"{p}: cannot be read ({type(e).__name__}: {e}); re-run the fit to write it again") from None
    named = isinstance(names, list) and names and all(isinstance(n, str) and n and Path(n).name == n for n in names)
    if not named or len(set(names)) != len(names):
        raise InputError(f"{p}: 'videos' is not a list of distinct folder names; re-run the fit to write it again")
    return names


def video_index(run: Path, names: list[str], video) -> int:
    """Which of the run's videos ``names`` to show: ``video`` a name, an index (past the last: the last) or None
    (the first).

    Raises:
        InputError: a name the run lacks, or any name for a fit of one video (``names`` empty).
    """
    if video is None or (isinstance(video, int) and not names):
        return 0
    if isinstance(video, int):
        return min(max(video, 0), len(names) - 1)
    if not names:
        raise InputError(f"--video {video}: {run} is a fit of one video; leave --video out")
    if video not in names:
        raise InputError(f"--video {video}: {run} has no such video; its videos: {', '.join(names)}")
    return names.index(video)


def pick_source(run: Path, home: Path | None = None) -> Path:
    """``motion.npz`` (of ``home``: the run, or one video's folder of a fit of several), or the newest checkpoint
    when there is no ``motion.npz`` or it is older (a fit running into the folder again).

    Raises:
        InputError: the folder is missing, is not a run directory, or holds neither.
    """
    run = Path(run)
    if not run.is_dir():
        raise InputError(f"{run}: no such folder; pass a run directory that s3o-fit wrote (its --out)")
    npz = Path(home or run) / "motion.npz"
    cks = checkpoints(run)
    if not npz.is_file() and not cks:
        if not (run / "config.toml").is_file():
            raise InputError(f"{run} is not a run directory (no motion.npz, config.toml or checkpoints/); pass the "
                             "folder s3o-fit wrote (its --out)")
        raise InputError(f"{npz}: missing and the fit has saved no checkpoint yet; wait for its first checkpoint, or "
                         "run s3o-fit into this folder")
    if cks and (not npz.is_file() or (_mtime(cks[-1]) or 0) > (_mtime(npz) or 0)):
        return cks[-1]
    return npz


def load_view(run, sequence=None, video=None) -> FitView:
    """The state of the run directory ``run`` that the page shows (see :func:`pick_source`).

    Args:
        run: the run directory.
        sequence: where the input frames are, for the cameras' pictures (of a fit of several videos, the shown
            video's); default: the sequence ``metrics.json`` names, else ``run/sequence``.
        video: of a fit of several videos, which one (a name or an index, see :func:`video_index`); default the
            first.

    Raises:
        InputError: one line naming the file and the fix (not a run, no ``motion.npz`` nor checkpoint, a malformed
            file, a video the run lacks).
    """
    run = Path(run)
    _check_given(sequence)
    names = video_names(run)
    index = video_index(run, names, video) if names else 0  # a running fit's videos are in its checkpoint
    home = run / "videos" / names[index] if names else run
    source = pick_source(run, home)
    view = None
    if source.name != "motion.npz":
        try:
            view = _checkpoint_view(run, names, video, sequence)
        except InputError as e:
            if not (home / "motion.npz").is_file():
                raise
            log.warning("%s; showing %s instead", e, home / "motion.npz")
    if view is None:
        video_index(run, names, video)  # a name given for a fit of one video: said here
        arrays, skel = _read_motion(home)
        view = _view(run, home / "motion.npz", "finished fit", arrays, skel)
        view.metrics = _read_metrics(home)
        view.sequence = find_sequence(home, view.metrics, sequence)
        view.videos, view.video = names, index
    view.config_text = (run / "config.toml").read_text() if (run / "config.toml").is_file() else None
    log.debug("%s: %s, %d frames, %d vertices, %d bones", run, view.label, view.num_frames, view.verts.shape[1],
              view.centres.shape[1])
    return view


def _view(run: Path, source: Path, label: str, arrays: dict, skel: dict) -> FitView:
    """:func:`_view_from_arrays`, arrays or a skeleton of the wrong shape said in one line."""
    try:
        return _view_from_arrays(run, source, label, arrays, skel)
    except (ValueError, KeyError, IndexError, TypeError) as e:
        raise InputError(f"{source}: malformed ({type(e).__name__}: {e}); re-run the fit to write it again") from None


def _read_metrics(run: Path) -> dict | None:
    p = run / "metrics.json"
    if not p.is_file():
        return None
    try:
        m = json.loads(p.read_text())
    except (OSError, ValueError) as e:
        log.warning("%s cannot be read (%s); the figures are left out", p, e)
        return None
    return m if isinstance(m, dict) else None


def _read_motion(run: Path) -> tuple[dict, dict]:
    """``motion.npz`` and ``skeleton.json`` of a finished fit."""
    npz = run / "motion.npz"
    try:
        with np.load(npz, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (OSError, ValueError) as e:
        raise InputError(f"{npz}: cannot be read ({e}); re-run the fit (or its export) to write it again") from None
    missing = [k for k in MOTION_KEYS if k not in arrays]
    if missing:
        raise InputError(f"{npz}: lacks {', '.join(missing)}; it was not written by s3o-fit, re-run the fit")
    skel: dict = {}
    sp = run / "skeleton.json"
    if sp.is_file():
        try:
            skel = json.loads(sp.read_text())
        except ValueError as e:
            raise InputError(f"{sp}: not valid JSON ({e}); re-run the fit or restore the file") from None
    else:
        log.warning("%s is missing: the bones are not drawn", sp)
    return arrays, skel


def _view_from_arrays(run: Path, source: Path, label: str, a: dict, skel: dict) -> FitView:
    """The world-frame :class:`FitView` of ``motion.npz``-like arrays and a ``skeleton.json``-like dict."""
    G = np.asarray(skel.get("world_from_object", np.diag([1.0, -1.0, -1.0, 1.0])), dtype=np.float64)
    root = np.asarray(a["root"], dtype=np.float64)
    c2w = G @ np.linalg.inv(root)  # (T, 4, 4) camera (OpenCV axes) -> world
    T = root.shape[0]

    def to_world(cam: np.ndarray) -> np.ndarray:  # (T, M, 3) camera-frame points of each frame -> world
        world = np.einsum("tij,tmj->tmi", c2w[:, :3, :3], cam.astype(np.float64)) + c2w[:, None, :3, 3]
        return world.astype(np.float32)

    verts = to_world(np.asarray(a["verts_cam"]))
    N = verts.shape[1]
    colors = np.asarray(a["colors"], np.float32) if "colors" in a else np.full((N, 3), 0.7, np.float32)
    joints = to_world(np.asarray(a["joints_cam"])) if "joints_cam" in a else np.zeros((T, 0, 3), np.float32)
    bones = skel.get("bones") or []
    motion = a.get("bone_motion")
    links = []
    if bones and motion is not None and len(bones) == motion.shape[1]:
        c = np.asarray([b.get("centre", np.asarray(b["bind"])[:3, 3].tolist()) for b in bones], dtype=np.float64)
        obj = np.einsum("tbij,bj->tbi", motion[..., :3, :3], c) + motion[..., :3, 3]  # each centre moved by its bone
        centres = (obj @ G[:3, :3].T + G[:3, 3]).astype(np.float32)
        if joints.shape[1] == len(skel.get("joints") or []):
            links = [(j, int(b)) for j, jt in enumerate(skel.get("joints") or []) for b in jt["bones"]]
    else:
        centres = np.zeros((T, 0, 3), np.float32)
    H, W = (int(s) for s in np.asarray(a["image_size"]).reshape(-1)[:2])
    return FitView(
        run=run, source=source, label=label, verts=verts, faces=np.asarray(a["faces"], np.int32),
        colors=np.clip(colors, 0, 1), joints=joints, centres=centres,
        bone_links=np.asarray(links, np.int64).reshape(-1, 2), cam_to_world=c2w, K=np.asarray(a["K"], np.float64),
        image_size=(H, W), fps=float(a["fps"]), frame_names=[str(s) for s in np.asarray(a["frame_names"]).tolist()],
    )


# ------------------------------------------------------------------------------------------ a running fit
def _checkpoint_view(run: Path, names: list[str], video, sequence) -> FitView:
    """The :class:`FitView` of the run's newest readable checkpoint (of a fit of several videos, one video's frames),
    posed by the package's own model and rig code."""
    from s3o_warp.run.checkpoint import CHECKPOINT_VERSION, load_newest

    found = load_newest(run, map_location="cpu")  # a damaged newest one is passed over, with a warning
    if found is None:
        raise InputError(f"{run / 'checkpoints'}: no checkpoint can be read; wait for the fit's next one")
    path, st = found
    if st.get("version") != CHECKPOINT_VERSION:
        raise InputError(f"{path}: written by another version of s3o-warp (checkpoint version {st.get('version')}); "
                         "view a run of this version")
    try:
        spans = video_spans(st["model"])
    except (KeyError, IndexError, ValueError, TypeError) as e:
        raise InputError(f"{path}: cannot be posed ({type(e).__name__}: {e}); wait for the fit's next checkpoint"
                         ) from None
    if len(spans) > 1:
        names = names if len(names) == len(spans) else _checkpoint_names(st, len(spans))
    else:
        names = []
    index = video_index(run, names, video)
    home = run / "videos" / names[index] if names else run
    seq = find_sequence(home, _read_metrics(home), sequence)  # a metrics.json there names the frames still
    try:
        rig = _rig_of_checkpoint(run, st, seq, spans[index] if names else None)
    except (KeyError, IndexError, RuntimeError, ValueError, TypeError) as e:  # not a state this version wrote
        raise InputError(f"{path}: cannot be posed ({type(e).__name__}: {e}); wait for the fit's next checkpoint"
                         ) from None
    arrays = {"verts_cam": rig.posed_camera(), "faces": rig.faces, "colors": rig.colors, "root": rig.root, "K": rig.K,
              "bone_motion": rig.bone_motion, "image_size": np.asarray(rig.image_size), "fps": rig.fps,
              "frame_names": np.asarray(rig.frame_names)}
    jc = rig.joints_camera()
    if jc is not None:
        arrays["joints_cam"] = jc
    sk = {"world_from_object": rig.world_from_object.tolist(),
          "bones": [{"centre": c.tolist(), "bind": m.tolist()} for c, m in zip(rig.centres, rig.bind)],
          "joints": [] if rig.joints is None else [{"bones": [int(a), int(b)]} for a, b in rig.joint_pairs]}
    view = _view(run, path, f"checkpoint {path.name} (no motion.npz yet)", arrays, sk)
    view.sequence, view.videos, view.video = seq, names, index  # no metrics: a metrics.json belongs to an earlier fit
    return view


def video_spans(model_state: dict) -> list[tuple[int, int]]:
    """Each video's frames ``(start, stop)`` in a checkpoint's model state (its ``video_of``; one video without it).

    Raises:
        ValueError: a video's frames are not one range.
    """
    T = int(model_state["root_t"].shape[0])
    vo = model_state.get("video_of")
    vo = np.zeros(T, np.int64) if vo is None else np.asarray(vo, np.int64).reshape(-1)
    spans = []
    for v in range(int(vo.max()) + 1 if len(vo) else 1):
        idx = np.flatnonzero(vo == v)
        if not len(idx) or idx[-1] - idx[0] + 1 != len(idx):
            raise ValueError(f"video {v}'s frames are not one range of frames")
        spans.append((int(idx[0]), int(idx[-1]) + 1))
    return spans


def _checkpoint_names(st: dict, n: int) -> list[str]:
    """The names of a running fit's ``n`` videos: its ``a+b`` sequence name split, else "video 0", "video 1", ..."""
    parts = str(st.get("sequence", "")).split("+")
    if len(parts) == n and all(parts) and len(set(parts)) == n:
        return parts
    return [f"video {i}" for i in range(n)]


def _rig_of_checkpoint(run: Path, st: dict, seq: Path | None, span: tuple[int, int] | None = None):
    """The :class:`s3o_warp.export.rig.Rig` of a checkpoint's state, made as a finished fit makes it (``span``: one
    video's frames ``(start, stop)`` of a fit of several)."""
    from types import SimpleNamespace

    import torch

    from s3o_warp.model import ModelInit, S3OModel
    from s3o_warp.run.outputs import rig_from_model
    from s3o_warp.skeleton.mstep import SkeletonState

    cfg = st["config"]
    sd = st["model"]
    T, B, N = sd["root_t"].shape[0], sd["bone_centers"].shape[0], sd["verts"].shape[0]
    start, stop = span or (0, T)
    names, size = frame_list(seq, stop - start)
    z = torch.zeros
    init = ModelInit(verts=sd["verts"], faces=sd["faces"], colors=z(N, 3) + 0.5, centers=z(B, 3),
                     rotations=torch.eye(3).expand(B, 3, 3), log_scales=z(B, 3), root_R=torch.eye(3).expand(T, 3, 3),
                     root_t=z(T, 3), focal=torch.ones(sd["log_focal"].shape), crop_scale=torch.ones(T),
                     crop_size=int(cfg["data"]["crop_size"]), crop_to_frame=torch.eye(3).expand(T, 3, 3),
                     principal_point=cfg["motion"]["principal_point"], frame_size=size or (1, 1),
                     video_of=sd.get("video_of"), motion_of=sd.get("motion_of"))
    model = S3OModel(init)  # the checkpoint's shapes; its values come next
    model.load_state_dict(sd)
    if size is None:  # no frames found: twice the mean principal point (only the frusta's shape depends on it)
        with torch.no_grad():
            K = model.intrinsics_frame(torch.arange(start, stop)).double()
        size = (int(round(2 * float(K[:, 1, 2].mean()) + 1)), int(round(2 * float(K[:, 0, 2].mean()) + 1)))
        _warn_once("the input frames of %s were not found (pass --sequence): frame size taken as %d x %d from the "
                   "intrinsics", run if span is None else f"{run} frames {start}-{stop - 1}", size[1], size[0])
    skel = SkeletonState.from_dict(st["skeleton"])
    # rig_from_model reads a Fitter's model, skeleton, data (frame size, rate, names) and skeleton settings, and of
    # one video of several its frames, frame size, rate and names
    data = SimpleNamespace(frame_size=size, fps=float(cfg["data"]["fps"]), frame_names=names)
    fitter = SimpleNamespace(model=model, skel=skel, data=data,
                             cfg=SimpleNamespace(skeleton=SimpleNamespace(t_r=float(cfg["skeleton"]["t_r"]))))
    if span is None:
        return rig_from_model(fitter)
    return rig_from_model(fitter, SimpleNamespace(start=start, stop=stop, **vars(data)))


# ------------------------------------------------------------------------------------------------- frames
def find_sequence(run: Path, metrics: dict | None, given=None) -> Path | None:
    """Where the input frames are: ``given``, the sequence ``metrics.json`` names, ``run/sequence`` (the built-in
    quadruped's) or the one sequence folder under it (``s3o-fit --box``'s); None when none exists."""
    _check_given(given)
    cands = [Path(given)] if given is not None else []
    if metrics and isinstance(metrics.get("sequence"), str) and metrics["sequence"]:
        cands.append(Path(metrics["sequence"]))
    sq = run / "sequence"
    cands.append(sq)
    if sq.is_dir():
        cands += sorted(p for p in sq.iterdir() if (p / "images").is_dir())
    for c in cands:
        if c.is_file() or (c.is_dir() and _image_files(c)):
            return c
    return None


def _check_given(given) -> None:
    if given is not None and not Path(given).exists():
        raise InputError(f"--sequence {given}: no such file or folder; pass the video or the folder of frames the fit "
                         "read")


def _image_files(seq: Path) -> list[Path]:
    """The frame images of a sequence folder (``images/`` or the folder itself), sorted by name."""
    d = seq / "images" if (seq / "images").is_dir() else seq
    return sorted(p for p in d.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file()) if d.is_dir() else []


def frame_list(seq: Path | None, T: int) -> tuple[list[str], tuple[int, int] | None]:
    """The names of the T frames and their (H, W), read from the sequence (numbered names and None without it)."""
    names = [f"{i:06d}" for i in range(T)]
    if seq is None:
        return names, None
    if seq.is_file():
        import cv2

        cap = cv2.VideoCapture(str(seq))
        size = (int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)), int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)))
        cap.release()
        return names, size if min(size) > 0 else None
    files = _image_files(seq)
    if len(files) != T:
        return names, None
    from PIL import Image

    with Image.open(files[0]) as im:
        return [p.stem for p in files], (im.height, im.width)


def _scaled(rgb: np.ndarray, max_side: int) -> np.ndarray:
    import cv2

    h, w = rgb.shape[:2]
    s = min(1.0, max_side / max(h, w))
    if s >= 1.0:
        return np.ascontiguousarray(rgb)
    return cv2.resize(rgb, (max(1, round(w * s)), max(1, round(h * s))), interpolation=cv2.INTER_AREA)


def _frame_paths(view: FitView) -> list[Path] | None:
    """The image file of each frame (by name, else in sorted order), or None (a warning says why)."""
    files = _image_files(view.sequence)
    by_name = {p.stem: p for p in files}
    if all(n in by_name for n in view.frame_names):
        return [by_name[n] for n in view.frame_names]
    if len(files) == view.num_frames:
        return files
    _warn_once("%s holds %d frames, the fit %d: the cameras are drawn without pictures", view.sequence, len(files),
               view.num_frames)
    return None


def _read_image(path: Path, max_side: int) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as im:
        im.draft("RGB", (max_side, max_side))  # JPEG: decode at a fraction of the size
        im = im.convert("RGB")
        im.thumbnail((max_side, max_side))
        return np.asarray(im)


def frame_images(view: FitView, max_side: int = 320):
    """Yield ``(t, RGB uint8 image)`` of the input frames, scaled to at most ``max_side`` pixels; nothing when the
    frames are not found or do not match the fit's (a warning says so)."""
    seq = view.sequence
    if seq is None:
        _warn_once("the input frames of %s were not found (pass --sequence): the cameras are drawn without pictures",
                   view.run)
        return
    if seq.is_file():  # a video: read in order
        import cv2

        cap = cv2.VideoCapture(str(seq))
        try:
            for t in range(view.num_frames):
                ok, bgr = cap.read()
                if not ok:
                    log.warning("%s ends at frame %d of %d: the later cameras have no picture", seq, t, view.num_frames)
                    return
                yield t, _scaled(bgr[..., ::-1], max_side)
        finally:
            cap.release()
        return
    for t, p in enumerate(_frame_paths(view) or []):
        try:
            yield t, _read_image(p, max_side)
        except OSError as e:
            log.warning("%s cannot be read (%s): its camera has no picture", p, e)


def frame_image(view: FitView, t: int, max_side: int = 1280) -> np.ndarray | None:
    """Frame t's input picture, scaled to at most ``max_side`` pixels, or None when it cannot be read."""
    seq = view.sequence
    try:
        if seq is None:
            return None
        if seq.is_file():
            import cv2

            cap = cv2.VideoCapture(str(seq))
            try:
                cap.set(cv2.CAP_PROP_POS_FRAMES, t)
                ok, bgr = cap.read()
            finally:
                cap.release()
            return _scaled(bgr[..., ::-1], max_side) if ok else None
        paths = _frame_paths(view)
        return _read_image(paths[t], max_side) if paths else None
    except OSError as e:
        log.warning("frame %d of %s cannot be read (%s)", t, seq, e)
        return None


# ------------------------------------------------------------------------------------------------ figures
def figures(metrics: dict | None) -> list[tuple[str, str]]:
    """The run's headline figures from ``metrics.json`` as (name, value) rows; those a run lacks are left out."""
    if not metrics:
        return []

    def get(*keys):
        v = metrics
        for k in keys:
            v = v.get(k) if isinstance(v, dict) else None
        return v

    rows = [
        ("mask IoU", get("mask_iou", "mean"), "{:.3f}"),
        ("PCK-T", get("pck_t", "pck"), "{:.1f}"),
        ("bones", get("bones", "count"), "{:d}"),
        ("joints inside the body", get("joints_inside", "fraction"), "{:.0%}"),
        ("F-score @2%", get("shape_3d", "fscore"), "{:.3f}"),
        ("Chamfer", get("shape_3d", "chamfer"), "{:.4f}"),
        ("joint distance", get("skeleton", "distance"), "{:.3f}"),
        ("IoU from every side", get("views", "sequence", "mean"), "{:.3f}"),
        ("frames", get("frames"), "{:d}"),
        ("fit seconds", get("seconds"), "{:.0f}"),
    ]
    out = []
    for name, value, fmt in rows:
        if value is None:
            continue
        try:
            out.append((name, fmt.format(value)))
        except (TypeError, ValueError):
            out.append((name, str(value)))
    return out
