"""A sequence folder from a video and a box: ``SEQ/images/``, ``SEQ/masks/``, ``SEQ/masks_preview.mp4`` (the masks over
the frames, for checking by eye) and ``SEQ/masks.json`` (what made them, and each frame's confidence), written
atomically (the folder appears whole or not at all).

The default segmenter gives each frame a confidence (:class:`s3o_warp.masks.grabcut.Frame`); frames under
:data:`FLAG_BELOW`, and frames where the object was hidden and carried on, are flagged: listed in ``masks.json``,
marked in the preview, and named in one warning with the ``--box-at`` to add (``s3o-fit --box`` gives the same
warning before it fits, also when it reuses the masks).

Every input is checked before any work: the video or frame folder, each box (inside its frame, not empty, with
background around it), each box's frame index, the segmenter and its checkpoint, and the output folder (a folder
that exists is replaced only when ``s3o-masks`` made it).
"""

from __future__ import annotations

import logging
import re
import shutil
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
from tqdm.auto import tqdm

from s3o_warp import interrupt
from s3o_warp.data.io import atomic_dir, imwrite, read_json, write_json, write_video
from s3o_warp.data.sequence import Frames, open_frames
from s3o_warp.errors import InputError
from s3o_warp.masks.grabcut import MAX_HIDDEN, Box, Frame, ObjectLost, segment_video

log = logging.getLogger(__name__)

SEGMENTERS = ("grabcut", "sam2")
"""``--segmenter`` choices: the classical default (:mod:`s3o_warp.masks.grabcut`) and SAM 2 with the user's weights
(:mod:`s3o_warp.masks.sam2`)."""

MIN_BOX_SIDE = 8
"""A box narrower or lower than this (pixels) holds too little to segment."""

FORMAT_VERSION = 2
"""Of ``masks.json``: a folder made by another version is made again by ``s3o-fit --box``."""

FLAG_BELOW = 0.75
"""Frames whose confidence is under this are flagged for checking. From one box on frame 0 (docs/results.md): no
frame of DAVIS dog, cows or blackswan (IoU 0.74-0.97); goat 37 frames, 16 of its 47 under IoU 0.70 among them."""

_STOPPED = "the masks"

_NUMBER = r"-?\d+(?:\.\d+)?"
_BOX = re.compile(rf"^\s*({_NUMBER})\s*,\s*({_NUMBER})\s*,\s*({_NUMBER})\s*,\s*({_NUMBER})\s*$")


def parse_box(text: str, flag: str = "--box") -> Box:
    """``"X0,Y0,X1,Y1"`` (frame pixels, inclusive corners; decimals are rounded) as a box; InputError otherwise."""
    m = _BOX.match(text)
    if not m:
        raise InputError(f"{flag} {text!r}: give the box as X0,Y0,X1,Y1 in the frame's pixels, e.g. {flag} 120,80,460,400")
    return tuple(int(round(float(v))) for v in m.groups())


def parse_box_at(text: str) -> tuple[int, Box]:
    """``"K:X0,Y0,X1,Y1"`` as (frame, box); InputError otherwise."""
    k, sep, box = text.partition(":")
    if not sep or not re.fullmatch(r"\s*-?\d+\s*", k):
        raise InputError(f"--box-at {text!r}: give a frame and a box as K:X0,Y0,X1,Y1, e.g. --box-at 40:120,80,460,400")
    return int(k), parse_box(box, "--box-at")


def check_boxes(boxes: dict[int, Box], n: int, size: tuple[int, int]) -> None:
    """InputError naming the first box whose frame is out of range or that is empty, outside its frame, too small
    or the whole frame."""
    H, W = size
    for k, (x0, y0, x1, y1) in sorted(boxes.items()):
        what = f"the box {x0},{y0},{x1},{y1} on frame {k}"
        if not 0 <= k < n:
            raise InputError(f"frame {k} is out of range: the video has {n} frames; give a frame from 0 to {n - 1}")
        if x1 <= x0 or y1 <= y0:
            raise InputError(f"{what} is empty; give X0 < X1 and Y0 < Y1 (left, top, right, bottom)")
        if x0 < 0 or y0 < 0 or x1 > W - 1 or y1 > H - 1:
            raise InputError(f"{what} lies outside the {W}x{H} frame; give X from 0 to {W - 1} and Y from 0 to {H - 1}")
        if min(x1 - x0, y1 - y0) + 1 < MIN_BOX_SIDE:
            raise InputError(f"{what} is under {MIN_BOX_SIDE} pixels across; draw it around the whole object")
        if (x0, y0, x1, y1) == (0, 0, W - 1, H - 1):
            raise InputError(f"{what} is the whole frame; draw it around the object, with background around it")


def _request(frames: Frames, source: Path, boxes: dict[int, Box], segmenter: str, checkpoint: Path | None) -> dict:
    """What the masks are made from (recorded in masks.json; ``s3o-fit --box`` reuses a folder with the same)."""
    if frames.files is None:
        st = source.stat()
        content = {"video": str(source.resolve()), "bytes": st.st_size, "mtime_ns": st.st_mtime_ns}
    else:
        content = {"frames": [str(p.resolve()) for p in frames.files]}
    return {
        "format": FORMAT_VERSION,
        "input": content,
        "boxes": {str(k): list(b) for k, b in sorted(boxes.items())},
        "segmenter": segmenter,
        "checkpoint": str(checkpoint.resolve()) if checkpoint else None,
    }


def made_from(out: Path) -> dict | None:
    """The request recorded in ``out/masks.json`` (None when there is none)."""
    if not (out / "masks.json").is_file():
        return None
    return read_json(out / "masks.json", "masks record", "delete the folder to make the masks again").get("request")


def _check_out(out: Path) -> None:
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: is a file; give --out a folder to create")
    if out.is_dir() and any(out.iterdir()) and not (out / "masks.json").is_file():
        raise InputError(f"{out}: exists and was not made by s3o-masks; give --out a new folder (it is replaced whole)")


def check_segmenter(segmenter: str, checkpoint: Path | None) -> None:
    """InputError for an unknown segmenter, or SAM 2 without its package or a readable checkpoint."""
    if segmenter not in SEGMENTERS:
        raise InputError(f"--segmenter {segmenter!r}: choose one of {', '.join(SEGMENTERS)}")
    if segmenter == "grabcut":
        if checkpoint is not None:
            raise InputError("--checkpoint is for --segmenter sam2; leave it out with the default segmenter")
        return
    from s3o_warp.masks import sam2

    sam2.check(checkpoint)


def _write_frames(frames: Frames, folder: Path) -> list[Path]:
    """Frame files copied as they are (a video's frames as PNG); returns the files written, in order."""
    folder.mkdir()
    files = []
    for k in tqdm(range(len(frames)), desc=f"{frames.name}: frames", unit="frame", leave=False, disable=None):
        interrupt.check(_STOPPED)
        if frames.files is not None:
            files.append(Path(shutil.copyfile(frames.files[k], folder / frames.files[k].name)))
        else:
            files.append(imwrite(folder / f"{k:06d}.png", frames.image(k)))
    if len({p.stem for p in files}) != len(files):
        raise InputError(f"{frames.describe(0)}: two frames share a name but not an extension; rename them")
    return files


def _read_rgb(path: Path) -> np.ndarray:
    return cv2.cvtColor(cv2.imread(str(path), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION), cv2.COLOR_BGR2RGB)


def preview_frame(image: np.ndarray, mask: np.ndarray, k: int, box: Box | None = None, flag: str | None = None
                  ) -> np.ndarray:
    """``image`` with ``mask`` tinted and outlined, the frame index, the box on a box's frame, and on a flagged frame a
    red border and ``flag`` ("check", "hidden") beside the index (RGB uint8)."""
    out = image.astype(np.float32)
    out[mask] = 0.55 * out[mask] + 0.45 * np.array([255.0, 40.0, 40.0])
    out = out.astype(np.uint8)
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(out, contours, -1, (255, 255, 0), max(1, image.shape[0] // 360))
    if box is not None:
        cv2.rectangle(out, box[:2], box[2:], (0, 255, 0), max(1, image.shape[0] // 240))
    scale = max(0.4, image.shape[0] / 720)
    text = str(k)
    if flag is not None:
        edge = max(2, image.shape[0] // 60)
        cv2.rectangle(out, (0, 0), (image.shape[1] - 1, image.shape[0] - 1), (255, 0, 0), 2 * edge)
        text = f"{k} {flag}"
    cv2.putText(out, text, (8, int(28 * scale) + 4), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255),
                max(1, int(2 * scale)))
    return out


def _preview(files: list[Path], masks: Path, boxes: dict[int, Box], name: str, flags: dict[int, str]
             ) -> Iterator[np.ndarray]:
    """The preview's frames (:func:`preview_frame`), one at a time."""
    for k, f in enumerate(tqdm(files, desc=f"{name}: preview", unit="frame", leave=False, disable=None)):
        interrupt.check(_STOPPED)
        mask = cv2.imread(str(masks / f"{f.stem}.png"), cv2.IMREAD_GRAYSCALE) > 127
        yield preview_frame(_read_rgb(f), mask, k, boxes.get(k), flags.get(k))


def _spans(frames: list[int]) -> str:
    """``[3, 4, 5, 9]`` as ``"3-5, 9"``."""
    out, i = [], 0
    while i < len(frames):
        j = i
        while j + 1 < len(frames) and frames[j + 1] == frames[j] + 1:
            j += 1
        out.append(str(frames[i]) if i == j else f"{frames[i]}-{frames[j]}")
        i = j + 1
    return ", ".join(out)


def flag_warning(out: Path, record: dict) -> str | None:
    """The warning for the flagged frames of a ``masks.json`` record (None when there are none): how many, which,
    where to look and the ``--box-at`` to add on the first."""
    flagged = record.get("flagged") or []
    if not flagged:
        return None
    hidden = set(record.get("hidden") or [])
    what = f"{len(flagged)} frame(s) may be wrong" + (f" ({len(hidden)} with the object hidden)" if hidden else "")
    return (f"{out}: {what}: {_spans(flagged)}; check them in {out / 'masks_preview.mp4'} (marked in red) and, where "
            f"the mask is wrong, add a box on the first: --box-at {flagged[0]}:X0,Y0,X1,Y1")


def _segment(segmenter: str, files: list[Path], boxes: dict[int, Box], checkpoint: Path | None,
             flow_preset: str) -> Iterator[Frame]:
    """Each frame's mask as a :class:`Frame` (SAM 2's with no confidence: ``None``)."""
    if segmenter == "sam2":
        from s3o_warp.masks import sam2

        return (Frame(k, m, None, False) for k, m in sam2.segment_video(files, boxes, checkpoint))
    return segment_video(lambda k: _read_rgb(files[k]), len(files), boxes, flow_preset)


def make_masks(source, out, boxes: dict[int, Box], segmenter: str = "grabcut", checkpoint=None,
               flow_preset: str = "medium", reuse: bool = False) -> Path:
    """Make the sequence folder ``out`` (see the module docstring) from a video file or folder of frames and boxes.

    Args:
        source: a video file, a folder of frames, or a folder holding ``images/``.
        out: the folder to write (replaced when ``s3o-masks`` made it).
        boxes: ``{frame: (x0, y0, x1, y1)}`` in that frame's pixels (inclusive corners); at least one.
        segmenter: one of :data:`SEGMENTERS`.
        checkpoint: SAM 2 weights (``segmenter="sam2"`` only).
        flow_preset: ``DataConfig.flow_preset`` (the grabcut segmenter's optical flow).
        reuse: keep ``out`` as it is when it was made from the same input, boxes and segmenter (``s3o-fit --box``
            run again, or with ``--resume``).

    Returns:
        ``out``.

    Raises:
        InputError: a bad input (see the module docstring), checked before any work; or an object lost while its
            mask is carried (the frame, and a second box to add there). Nothing is written then.
        s3o_warp.interrupt.Interrupted: a stop was requested (Ctrl-C, SIGTERM inside ``interrupt.on_signals``);
            checked once a frame, nothing is written.
    """
    source, out = Path(source).expanduser(), Path(out).expanduser()
    checkpoint = Path(checkpoint).expanduser() if checkpoint is not None else None
    if not boxes:
        raise InputError("no box given; pass --box X0,Y0,X1,Y1 around the object on one frame (--frame K)")
    boxes = {int(k): tuple(int(v) for v in b) for k, b in boxes.items()}
    check_segmenter(segmenter, checkpoint)
    frames = open_frames(source)
    try:
        check_boxes(boxes, len(frames), frames.size)
        _check_out(out)
        request = _request(frames, source, boxes, segmenter, checkpoint)
        if reuse and made_from(out) == request:
            log.info("%s: masks made from the same video and boxes; reusing them", out)
            warning = flag_warning(out, read_json(out / "masks.json", "masks record", "delete the folder"))
            if warning:
                log.warning("%s", warning)
            return out
        fps = frames.fps or 30.0
        with atomic_dir(out) as tmp:
            files = _write_frames(frames, tmp / "images")
            names = [p.stem for p in files]
            (tmp / "masks").mkdir()
            areas = np.zeros(len(names), np.int64)
            touches = np.zeros(len(names), bool)
            confidence: list[float | None] = [None] * len(names)
            hidden = np.zeros(len(names), bool)
            bar = tqdm(total=len(names), desc=f"{frames.name}: masks ({segmenter})", unit="frame", disable=None)
            try:
                for k, m, c, carried in _segment(segmenter, files, boxes, checkpoint, flow_preset):
                    interrupt.check(_STOPPED)
                    confidence[k], hidden[k] = (None if c is None else round(float(c), 3)), carried
                    imwrite(tmp / "masks" / f"{names[k]}.png", m.astype(np.uint8) * 255)
                    areas[k] = int(m.sum())
                    touches[k] = bool(m[0].any() or m[-1].any() or m[:, 0].any() or m[:, -1].any())
                    bar.update()
            except ObjectLost as e:
                if e.frame == e.anchor:
                    b = ",".join(map(str, boxes[e.anchor]))
                    raise InputError(f"nothing was segmented in the box {b} on frame {e.anchor}; draw the box around "
                                     "the object with a little background around it, or put it on another frame"
                                     ) from None
                raise InputError(
                    f"the object is lost at frame {e.frame} (not found again in the {MAX_HIDDEN} frames after it; its "
                    f"mask was {e.anchor_area} pixels on frame {e.anchor}); if it is still in the picture there, add a "
                    f"box around it: --box-at {e.frame}:X0,Y0,X1,Y1"
                ) from None
            finally:
                bar.close()
            low = [k for k, c in enumerate(confidence) if c is not None and c < FLAG_BELOW]
            flags = {k: "check" for k in low} | {int(k): "hidden" for k in np.flatnonzero(hidden)}
            write_video(_preview(files, tmp / "masks", boxes, frames.name, flags), tmp / "masks_preview.mp4", fps)
            record = {
                "request": request,
                "fps": fps if frames.fps else None,
                "frames": len(names),
                "size": list(frames.size),
                "mask_pixels": areas.tolist(),
                "touches_border": np.flatnonzero(touches).tolist(),
                "confidence": confidence,
                "flag_below": FLAG_BELOW,
                "hidden": np.flatnonzero(hidden).tolist(),
                "flagged": sorted(flags),
            }
            write_json(tmp / "masks.json", record)
    finally:
        frames.close()
    warning = flag_warning(out, record)
    if warning:
        log.warning("%s", warning)
    if touches.any():
        log.warning("%s: the object touches the frame border in %d frame(s) (first: %d); the fit down-weights them",
                    out, int(touches.sum()), int(np.argmax(touches)))
    log.info("%s: %d frames, masks by %s; check them in %s", out, len(names), segmenter, out / "masks_preview.mp4")
    return out
