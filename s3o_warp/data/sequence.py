"""Reading a sequence: frames + masks from a folder, a DAVIS tree or a video file, decoded on demand.

Input layouts (detected by :func:`open_sequence`, nothing needs renaming):

* a sequence folder ``<seq>/images/*`` + ``<seq>/masks/*`` (same names, or the same count in the
  same natural-sorted order); optional ``<seq>/keypoints.json`` and ``<seq>/ground_truth/`` are
  recorded as paths and never read here;
* a DAVIS tree: its root (``<root>/JPEGImages/<res>/<name>`` + ``<root>/Annotations/<res>/<name>``,
  pass ``name=``), or the ``JPEGImages/<res>/<name>`` folder itself;
* a video file OpenCV can decode (``.mp4``, ``.avi``, ...) plus a mask folder (``masks=``).

Masks are read by :mod:`s3o_warp.data.masks`, crops made by :mod:`s3o_warp.data.crops`; optical flow on the
crops is :mod:`s3o_warp.data.flow`.

Every bad input raises :class:`s3o_warp.errors.InputError` (bad settings:
:class:`s3o_warp.errors.ConfigError`) with one line naming the file or setting and the fix. This
module never writes files.
"""

from __future__ import annotations

import hashlib
import logging
import re
from collections import OrderedDict
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from PIL import Image, UnidentifiedImageError
from tqdm.auto import tqdm

from s3o_warp.config import DataConfig, check_fields
from s3o_warp.data.crops import Crop, crop_frame, crop_transform, mask_bbox
from s3o_warp.data.masks import clean_mask, read_mask
from s3o_warp.errors import InputError

log = logging.getLogger(__name__)

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
"""File name endings read as frames or masks (case-insensitive); other files in the folders are ignored."""

BORDER_WEIGHT = 0.3
"""Silhouette-loss weight of frames where the object touches the frame border (it leaves the frame, so the mask
shows only part of it)."""

FRAME_CACHE_SIZE = 4
"""Decoded frames (image and mask) a sequence keeps in memory; others are read from disk on demand."""

__all__ = ["Sequence", "open_sequence", "open_frames", "check_data_config"]


# --------------------------------------------------------------------------------------------------
# Settings
# --------------------------------------------------------------------------------------------------


def check_data_config(cfg: DataConfig) -> None:
    """Raise ConfigError (naming ``data.<key>``) for a DataConfig value that cannot work."""
    check_fields(cfg, "data.")


# --------------------------------------------------------------------------------------------------
# Files
# --------------------------------------------------------------------------------------------------


def _natural_key(name: str) -> list[Any]:
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def _list_images(folder: Path) -> list[Path]:
    files = [
        p
        for p in folder.iterdir()
        if p.is_file() and not p.name.startswith(".") and p.suffix.lower() in IMAGE_EXTENSIONS
    ]
    return sorted(files, key=lambda p: _natural_key(p.name))


def _image_size(path: Path) -> tuple[int, int]:
    """(H, W) from the file header, without decoding the pixels."""
    try:
        with Image.open(path) as im:
            w, h = im.size
    except (UnidentifiedImageError, OSError) as exc:
        raise InputError(
            f"{path}: cannot read this image ({exc.__class__.__name__}); replace or remove the file"
        ) from None
    return h, w


def _common_size(files: list[Path]) -> tuple[int, int]:
    """(H, W) shared by every file (headers only); InputError naming the first file of another size."""
    size = _image_size(files[0])
    for f in files[1:]:
        s = _image_size(f)
        if s != size:
            raise InputError(
                f"{f}: size {s[1]}x{s[0]} differs from {files[0].name}'s {size[1]}x{size[0]}; all frames must have one size"
            )
    return size


def _read_rgb(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
    if img is None:
        raise InputError(f"{path}: OpenCV cannot decode this image; replace or remove the file")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)



def _sha256_file(path: Path, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


class _FrameSource:
    """Decodes frame k (RGB uint8) on demand; content digests for cache keys."""

    def __len__(self) -> int:  # pragma: no cover - interface
        raise NotImplementedError

    def read(self, k: int) -> np.ndarray:  # pragma: no cover - interface
        raise NotImplementedError

    def digest(self, k: int) -> str:  # pragma: no cover - interface
        raise NotImplementedError

    def describe(self, k: int) -> str:  # pragma: no cover - interface
        raise NotImplementedError


class _FolderSource(_FrameSource):
    def __init__(self, files: list[Path]):
        self.files = files
        self._digests: dict[int, str] = {}

    def __len__(self) -> int:
        return len(self.files)

    def read(self, k: int) -> np.ndarray:
        return _read_rgb(self.files[k])

    def digest(self, k: int) -> str:
        if k not in self._digests:
            self._digests[k] = _sha256_file(self.files[k])
        return self._digests[k]

    def describe(self, k: int) -> str:
        return str(self.files[k])


class _VideoSource(_FrameSource):
    """Seeks with CAP_PROP_POS_FRAMES, reading straight on when frames are asked for in order."""

    def __init__(self, path: Path):
        self.path = path
        cap = cv2.VideoCapture(str(path))
        if not cap.isOpened():
            raise InputError(
                f"{path}: OpenCV cannot open this video; re-encode it (e.g. ffmpeg -i IN -c:v libx264 OUT.mp4) "
                "or pass a folder of frames"
            )
        ok, first = cap.read()
        if not ok or first is None:
            cap.release()
            raise InputError(
                f"{path}: OpenCV cannot decode any frame of this video; re-encode it "
                "(e.g. ffmpeg -i IN -c:v libx264 OUT.mp4) or pass a folder of frames"
            )
        n = 1
        while cap.grab():  # the container's frame count is often wrong: count by decoding
            n += 1
        fps = cap.get(cv2.CAP_PROP_FPS)
        self.fps = float(fps) if fps and np.isfinite(fps) and fps > 0 else None
        self.size = first.shape[:2]
        self.n = n
        self._cap = cap
        self._next = n  # position of the next frame cap.read() would return
        self._digest: str | None = None

    def __len__(self) -> int:
        return self.n

    def read(self, k: int) -> np.ndarray:
        if k != self._next:
            self._cap.set(cv2.CAP_PROP_POS_FRAMES, k)
        ok, frame = self._cap.read()
        if not ok or frame is None:
            self._next = -1
            raise InputError(f"{self.path}: OpenCV cannot decode frame {k} of this video; re-encode it")
        self._next = k + 1
        return cv2.cvtColor(frame, cv2.COLOR_BGR2RGB)

    def digest(self, k: int) -> str:
        if self._digest is None:
            self._digest = _sha256_file(self.path)
        return f"{self._digest}:{k}"

    def describe(self, k: int) -> str:
        return f"{self.path} frame {k}"

    def close(self) -> None:
        self._cap.release()


def _read_sized(source: _FrameSource, k: int, size: tuple[int, int]) -> np.ndarray:
    """Frame k of ``source``, which must decode to ``size`` (H, W) (a file's pixels can differ from its header)."""
    img = source.read(k)
    if img.shape[:2] != tuple(size):
        raise InputError(
            f"{source.describe(k)}: size {img.shape[1]}x{img.shape[0]} differs from the header's "
            f"{size[1]}x{size[0]}; re-save the file"
        )
    return img


@dataclass
class Frames:
    """The frames of a video file or a folder of frames, without masks (what :mod:`s3o_warp.masks` segments).

    Attributes:
        name: the video file's stem or the folder's name.
        size: ``(H, W)`` in pixels.
        fps: the video's own frame rate, None for frame files.
        files: the T frame files, None for a video.
    """

    name: str
    size: tuple[int, int]
    fps: float | None
    files: list[Path] | None
    _source: _FrameSource = field(repr=False)

    def __len__(self) -> int:
        return len(self._source)

    def image(self, k: int) -> np.ndarray:
        """Frame k as ``(H, W, 3) uint8`` RGB."""
        return _read_sized(self._source, k, self.size)

    def describe(self, k: int) -> str:
        """Where frame k comes from (its file, or the video and index), for messages."""
        return self._source.describe(k)

    def close(self) -> None:
        """Release a video decoder."""
        if isinstance(self._source, _VideoSource):
            self._source.close()


def open_frames(path: str | Path) -> Frames:
    """Open a video file, a folder of frames, or a folder holding ``images/`` (masks not needed). Decodes a video
    once to count its frames; frame files are only listed and their headers read.

    Raises:
        InputError: a missing path, an undecodable video, a folder without frames, frames of different sizes,
            fewer than 2 frames.
    """
    path = Path(path).expanduser()
    if not path.exists():
        raise InputError(f"{path}: no such file or folder; pass a video file or a folder of frames")
    if path.is_file():
        source = _VideoSource(path)
        frames = Frames(path.stem, tuple(int(v) for v in source.size), source.fps, None, source)
        what = f"{path} has {len(source)} frame(s)"
    else:
        folder = path / "images" if (path / "images").is_dir() else path
        files = _list_images(folder)
        if not files:
            raise InputError(f"{folder}: no frames found (looked for {', '.join(IMAGE_EXTENSIONS)}); pass a video file "
                             "or a folder of frames")
        frames = Frames(path.name, _common_size(files), None, files, _FolderSource(files))
        what = f"{folder} has {len(files)} frame(s)"
    if len(frames) < 2:
        frames.close()
        raise InputError(f"{what}; a sequence needs at least 2 frames (optical flow pairs them)")
    return frames


# --------------------------------------------------------------------------------------------------
# Sequence
# --------------------------------------------------------------------------------------------------


@dataclass
class Sequence:
    """A validated frame + mask sequence, decoded on demand (an LRU keeps a few frames).

    Attributes:
        name: sequence name (folder name, DAVIS sequence name or video file stem).
        frame_names: T names, one per frame, in order (file stems, or ``000000``... for a video).
        size: full-frame ``(H, W)`` in pixels.
        fps: frames per second (the video's own, else ``DataConfig.fps``).
        bboxes: ``(T, 4) int64`` inclusive mask box ``(x0, y0, x1, y1)`` per frame, frame pixels.
        touches_border: ``(T,) bool``: the mask reaches the frame's first/last row or column.
        mask_digests: T SHA-256 hex digests of the boolean masks (cache keys).
        image_files: T frame files, or None for a video.
        video_file: the video, or None for frame files.
        mask_files: T mask files.
        keypoints_file: ``keypoints.json`` beside images/masks if present (recorded, never read here).
        ground_truth_dir: ``ground_truth/`` beside images/masks if present (recorded, never read here).
        cfg: the DataConfig used (object id, threshold, crop settings).
    """

    name: str
    frame_names: list[str]
    size: tuple[int, int]
    fps: float
    bboxes: np.ndarray
    touches_border: np.ndarray
    mask_digests: list[str]
    image_files: list[Path] | None
    video_file: Path | None
    mask_files: list[Path]
    keypoints_file: Path | None
    ground_truth_dir: Path | None
    cfg: DataConfig
    _source: _FrameSource = field(repr=False, compare=False)
    _lru: OrderedDict = field(default_factory=OrderedDict, init=False, repr=False, compare=False)

    @property
    def num_frames(self) -> int:
        """T, the number of frames."""
        return len(self.frame_names)

    def __len__(self) -> int:
        return self.num_frames

    def _cached(self, key: tuple[str, int], make) -> np.ndarray:
        if key in self._lru:
            self._lru.move_to_end(key)
            return self._lru[key]
        val = make()
        val.setflags(write=False)
        self._lru[key] = val
        while len(self._lru) > 2 * FRAME_CACHE_SIZE:  # images and masks
            self._lru.popitem(last=False)
        return val

    def _index(self, k: int) -> int:
        if not -self.num_frames <= k < self.num_frames:
            raise IndexError(f"frame {k} out of range for {self.num_frames} frames")
        return k % self.num_frames

    def image(self, k: int) -> np.ndarray:
        """Frame k as ``(H, W, 3) uint8`` RGB (read-only array; decoded on demand)."""
        k = self._index(k)

        return self._cached(("image", k), lambda: _read_sized(self._source, k, self.size))

    def mask(self, k: int) -> np.ndarray:
        """Frame k's foreground as ``(H, W) bool`` (read-only array; decoded on demand)."""
        k = self._index(k)
        return self._cached(
            ("mask", k), lambda: clean_mask(read_mask(self.mask_files[k], self.cfg.object_id, self.cfg.mask_threshold), self.cfg)
        )

    def frame_digest(self, k: int) -> str:
        """Content digest of frame k's image (file bytes, or video bytes + index) for cache keys."""
        return self._source.digest(self._index(k))

    @property
    def crop_to_frame(self) -> np.ndarray:
        """``(T, 3, 3) float64`` crop -> frame pixel transforms, from the mask boxes (no decoding)."""
        return np.stack([crop_transform(tuple(b), self.cfg.crop_size, self.cfg.crop_scale) for b in self.bboxes])

    @property
    def frame_to_crop(self) -> np.ndarray:
        """``(T, 3, 3) float64`` inverses of :attr:`crop_to_frame`."""
        return np.linalg.inv(self.crop_to_frame)

    def crop(self, k: int) -> Crop:
        """Frame k's square crop (see :func:`crop_frame`), with ``DataConfig`` crop settings."""
        k = self._index(k)
        return crop_frame(
            self.image(k),
            self.mask(k),
            self.cfg.crop_size,
            self.cfg.crop_scale,
            bbox=tuple(int(v) for v in self.bboxes[k]),
        )

    def crops(self) -> Iterator[Crop]:
        """Crops of frames 0..T-1 in order, one at a time (nothing accumulates in memory)."""
        for k in range(self.num_frames):
            yield self.crop(k)

    def close(self) -> None:
        """Release a video decoder and the frame cache."""
        self._lru.clear()
        if isinstance(self._source, _VideoSource):
            self._source.close()


def _resolve_layout(
    path: Path, name: str | None, masks: Path | None
) -> tuple[str, Path | None, Path | None, Path, Path | None]:
    """(name, image folder, video file, mask folder, sequence folder for extras)."""
    if not path.exists():
        raise InputError(
            f"{path}: no such file or folder; pass a sequence folder (images/ + masks/), a DAVIS root or a video file"
        )
    if path.is_file():
        if masks is None:
            raise InputError(
                f"{path}: a video needs its mask folder; pass masks=<folder> (--masks) with one mask per frame"
            )
        extras = masks.parent if masks.name == "masks" else None
        return path.stem, None, path, masks, extras
    # a DAVIS tree: the root, a resolution folder, or one sequence's frame folder
    if (path / "JPEGImages").is_dir():
        res_root = path / "JPEGImages"
        resolutions = sorted(p.name for p in res_root.iterdir() if p.is_dir())
        if "480p" in resolutions:
            res = "480p"
        elif len(resolutions) == 1:
            res = resolutions[0]
        else:
            raise InputError(
                f"{res_root}: expected one resolution folder such as 480p, found {resolutions or 'none'}; "
                "pass the JPEGImages/<resolution>/<sequence> folder itself"
            )
        path = res_root / res
    if path.parent.name == "JPEGImages" and name is not None and (path / name).is_dir():
        path = path / name
    elif path.parent.name == "JPEGImages":
        available = sorted(p.name for p in path.iterdir() if p.is_dir())
        what = f"unknown sequence {name!r}" if name else "no sequence name given"
        raise InputError(
            f"{path}: {what}; pass name=<sequence> (--name), one of: {', '.join(available[:20]) or 'none found'}"
        )
    if path.parent.parent.name == "JPEGImages":
        seq_name = path.name
        mask_dir = masks or path.parent.parent.parent / "Annotations" / path.parent.name / seq_name
        if not mask_dir.is_dir():
            raise InputError(f"{mask_dir}: DAVIS mask folder not found for {path}; pass masks=<folder> (--masks)")
        return seq_name, path, None, mask_dir, None
    if name is not None and (path / name / "images").is_dir():
        path = path / name
    if (path / "images").is_dir():
        mask_dir = masks or path / "masks"
        if not mask_dir.is_dir():
            raise InputError(
                f"{mask_dir}: mask folder not found; add masks/ beside images/ (one mask per frame) or pass masks="
            )
        return path.name, path / "images", None, mask_dir, path
    if masks is not None:  # a bare folder of frames + an explicit mask folder
        return path.name, path, None, masks, None
    raise InputError(
        f"{path}: no images/ and masks/ folders and not a DAVIS JPEGImages tree; "
        "put frames in images/ and masks in masks/, or pass masks=<folder>"
    )


def open_sequence(
    path: str | Path,
    *,
    name: str | None = None,
    masks: str | Path | None = None,
    cfg: DataConfig | None = None,
) -> Sequence:
    """Open and validate a sequence (layout detected; see the module docstring). Writes nothing.

    Reads every mask once (to validate it and record its box) and every image header; images
    themselves are decoded later, on demand, by :meth:`Sequence.image`.

    Args:
        path: a sequence folder (images/ + masks/), a DAVIS root, a DAVIS ``JPEGImages/<res>/<seq>``
            folder, a folder of frames (with ``masks``), or a video file (with ``masks``).
        name: the sequence inside a DAVIS root (or a sub-folder of ``path`` holding images/ + masks/).
        masks: mask folder; required for a video, optional otherwise (overrides the detected one).
        cfg: data settings; defaults to ``DataConfig()``.

    Returns:
        The :class:`Sequence`.

    Raises:
        InputError: one line naming the file or folder and the fix: missing folder, unreadable
            file, frame/mask count mismatch, size mismatch, empty or all-foreground mask, fewer than
            2 frames, undecodable video, palette mask without ``data.object_id``.
        ConfigError: an impossible DataConfig value.
    """
    cfg = cfg or DataConfig()
    check_data_config(cfg)
    path = Path(path).expanduser()
    masks = Path(masks).expanduser() if masks is not None else None
    if masks is not None and not masks.is_dir():
        raise InputError(f"{masks}: mask folder not found; pass an existing folder with one mask per frame")
    seq_name, image_dir, video_file, mask_dir, extras = _resolve_layout(path, name, masks)

    mask_files = _list_images(mask_dir)
    fps = cfg.fps
    if video_file is not None:
        source: _FrameSource = _VideoSource(video_file)
        n_frames = len(source)
        size = tuple(source.size)
        fps = source.fps or cfg.fps
        frame_names = [f"{k:06d}" for k in range(n_frames)]
        image_files = None
        what_frames = f"{video_file} has {n_frames} frames"
    else:
        image_files = _list_images(image_dir)
        n_frames = len(image_files)
        if n_frames == 0:
            raise InputError(f"{image_dir}: no frames found (looked for {', '.join(IMAGE_EXTENSIONS)}); add the images")
        what_frames = f"{image_dir} has {n_frames} frames"
    if len(mask_files) != n_frames:
        raise InputError(
            f"{what_frames} but {mask_dir} has {len(mask_files)} masks; give exactly one mask per frame"
        )
    if image_files is not None:
        mask_by_stem = {p.stem: p for p in mask_files}
        if all(p.stem in mask_by_stem for p in image_files):
            mask_files = [mask_by_stem[p.stem] for p in image_files]
        else:
            log.info("%s: frame and mask names differ; pairing them in sorted order", mask_dir)
        frame_names = [p.stem for p in image_files]
        source = _FolderSource(image_files)
        size = _common_size(image_files)
    if n_frames < 2:
        raise InputError(f"{what_frames}; a sequence needs at least 2 frames (optical flow pairs them)")

    bboxes = np.zeros((n_frames, 4), dtype=np.int64)
    touches = np.zeros(n_frames, dtype=bool)
    multi_blob: list[int] = []
    digests: list[str] = []
    H, W = size
    for k, mf in enumerate(tqdm(mask_files, desc=f"{seq_name}: masks", unit="mask", leave=False, disable=None)):
        raw = read_mask(mf, cfg.object_id, cfg.mask_threshold)
        m = clean_mask(raw, cfg)
        if m is not raw and (m != raw).any():
            multi_blob.append(k)
        if m.shape != (H, W):
            frame = image_files[k] if image_files is not None else f"{video_file} frame {k}"
            raise InputError(
                f"{mf}: mask size {m.shape[1]}x{m.shape[0]} differs from its frame's {W}x{H} ({frame}); "
                "resize the mask to the frame"
            )
        bb = mask_bbox(m)
        if bb is None:
            raise InputError(
                f"{mf}: the mask is empty (no foreground); fix the mask or remove this frame and its image"
            )
        if m.all():
            raise InputError(
                f"{mf}: the mask is all foreground (no background); fix the mask (foreground = value > "
                f"{cfg.mask_threshold}, or a palette id) or remove this frame"
            )
        bboxes[k] = bb
        touches[k] = bool(m[0].any() or m[-1].any() or m[:, 0].any() or m[:, -1].any())
        digests.append(hashlib.sha256(np.packbits(m).tobytes() + str(m.shape).encode()).hexdigest())

    if multi_blob:
        log.warning(
            "%s: %d mask(s) have disconnected blobs away from the object (first: %s); the largest blob and the "
            "fragments near it are used (data.largest_blob=false keeps all)", seq_name, len(multi_blob), mask_files[multi_blob[0]]
        )
    if touches.any():
        log.warning(
            "%s: the object touches the frame border in %d frame(s) (first: %s); those frames are "
            "down-weighted (x%g in the silhouette loss)", seq_name, int(touches.sum()),
            mask_files[int(np.argmax(touches))], BORDER_WEIGHT,
        )
    keypoints = extras / "keypoints.json" if extras is not None and (extras / "keypoints.json").is_file() else None
    gt = extras / "ground_truth" if extras is not None and (extras / "ground_truth").is_dir() else None
    log.info("%s: %d frames %dx%d at %.3g fps", seq_name, n_frames, W, H, fps)
    return Sequence(
        name=seq_name,
        frame_names=frame_names,
        size=(int(H), int(W)),
        fps=float(fps),
        bboxes=bboxes,
        touches_border=touches,
        mask_digests=digests,
        image_files=image_files,
        video_file=video_file,
        mask_files=mask_files,
        keypoints_file=keypoints,
        ground_truth_dir=gt,
        cfg=cfg,
        _source=source,
    )
