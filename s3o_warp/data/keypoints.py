"""BADJA joint annotations -> the project's ``keypoints.json`` (evaluation only, never used to fit).

A BADJA file (github.com/benjiebob/BADJA, ``joint_annotations/<animal>.json``) is a list with one
entry per annotated frame::

    {"image_path": "DAVIS/JPEGImages/Full-Resolution/cows/00000.jpg",
     "segmentation_path": "...", "joints": [[row, col], ...] (37), "visibility": [bool, ...] (37)}

Coordinates are ``[row, col]`` pixels of the full-resolution DAVIS frame (1920 x 1080). The 37 joints
are the 33 SMAL model joints plus nose tip, chin and both ears; only 20 of them are ever annotated
(``BADJA_ANNOTATED``, the set LASR/ViSER score with PCK-T).

Our ``keypoints.json`` (docs/method.md, the input sequence) holds full-frame pixel coordinates of the frames
we actually fit, in OpenCV's centre convention (pixel (c, r) has its centre at (c, r))::

    {"names": [...], "frames": {"00000": [[x, y, visible], ...], ...}}

Command line: ``python -m s3o_warp.data.keypoints BADJA.json OUT.json --frames DIR`` (size read from the first
image in DIR) or ``--frame-size H W``.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import cv2
import numpy as np

from s3o_warp.data.io import read_json, write_json
from s3o_warp.errors import InputError

log = logging.getLogger(__name__)

BADJA_JOINT_NAMES: tuple[str, ...] = (
    "body_0", "body_1", "body_2", "body_3", "body_4", "body_5", "body_6",
    "upper_right_0", "upper_right_1", "upper_right_2", "upper_right_3",
    "upper_left_0", "upper_left_1", "upper_left_2", "upper_left_3",
    "neck_lower", "neck_upper",
    "lower_right_0", "lower_right_1", "lower_right_2", "lower_right_3",
    "lower_left_0", "lower_left_1", "lower_left_2", "lower_left_3",
    "tail_0", "tail_1", "tail_2", "tail_3", "tail_4", "tail_5", "tail_6",
    "jaw", "nose", "chin", "right_ear", "left_ear",
)  # fmt: skip
"""Names of BADJA's 37 joint slots (SMAL joints 0-32, then nose tip, chin, right ear, left ear)."""

BADJA_ANNOTATED: tuple[int, ...] = (8, 9, 10, 12, 13, 14, 15, 18, 19, 20, 22, 23, 24, 25, 28, 31, 32, 33, 35, 36)
"""The 20 joint slots BADJA annotates (``SMALJointInfo.annotated_classes``); the others are always 0."""

BADJA_SOURCE_SIZE: tuple[int, int] = (1080, 1920)
"""(H, W) of the full-resolution DAVIS frames that BADJA coordinates refer to."""

_IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


def _read_badja(badja_json) -> list:
    if isinstance(badja_json, list):
        return badja_json
    data = read_json(badja_json, "BADJA file", "pass a BADJA joint_annotations/<animal>.json file")
    if not isinstance(data, list):
        raise InputError(f"{badja_json}: expected a JSON list of per-frame annotations (BADJA format), "
                         f"got {type(data).__name__}")
    return data


def badja_to_keypoints(
    badja_json,
    frame_size: tuple[int, int],
    source_size: tuple[int, int] = BADJA_SOURCE_SIZE,
    annotated_only: bool = True,
) -> dict:
    """Convert BADJA annotations to our keypoints dictionary in the frames' own pixels.

    Args:
        badja_json: Path of a BADJA ``joint_annotations/*.json`` file, or its already-parsed list.
        frame_size: ``(H, W)`` of the frames the sequence uses (DAVIS 480p: ``(480, 854)``).
        source_size: ``(H, W)`` the BADJA coordinates refer to (full-resolution DAVIS, 1080 x 1920).
        annotated_only: Keep only the 20 joints BADJA annotates (``BADJA_ANNOTATED``, as LASR/ViSER
            score); False keeps all 37 slots (the other 17 are always invisible).

    Returns:
        ``{"names": [J names], "frames": {stem: [[x, y, visible], ...] (J rows)}}``: x = column and
        y = row in pixels of the ``frame_size`` image with OpenCV's centre convention, ``visible``
        1 or 0 (BADJA's flag). Each axis is rescaled by its own ratio about pixel centres:
        ``x = (col + 0.5) * W / W_src - 0.5`` (DAVIS 480p: 854/1920 and 480/1080 differ by 0.08%).
        Frame keys are the stems of BADJA's ``image_path`` (``"00000"``); invisible joints keep
        their (meaningless) converted coordinates.

    Raises:
        InputError: malformed file (missing keys, wrong joint count) or a bad size.
    """
    data = _read_badja(badja_json)
    src = badja_json if not isinstance(badja_json, list) else "BADJA annotations"
    try:
        h, w = (int(v) for v in frame_size)
        sh, sw = (int(v) for v in source_size)
    except (TypeError, ValueError):
        raise InputError(f"badja_to_keypoints(): frame_size and source_size must be (H, W) pairs of integers, "
                         f"got {frame_size}, {source_size}") from None
    if min(h, w, sh, sw) <= 0:
        raise InputError(f"badja_to_keypoints(): sizes must be positive, "
                         f"got frame_size={frame_size}, source_size={source_size}")
    slots = list(BADJA_ANNOTATED) if annotated_only else list(range(len(BADJA_JOINT_NAMES)))
    frames: dict[str, list] = {}
    for n, entry in enumerate(data):
        if not isinstance(entry, dict) or not {"image_path", "joints", "visibility"} <= set(entry):
            raise InputError(f"{src}: entry {n} lacks image_path/joints/visibility; "
                             "pass an unmodified BADJA joint_annotations file")
        joints = np.asarray(entry["joints"], dtype=np.float64)
        vis = np.asarray(entry["visibility"], dtype=bool)
        if joints.shape != (len(BADJA_JOINT_NAMES), 2) or vis.shape != (len(BADJA_JOINT_NAMES),):
            raise InputError(
                f"{src}: entry {n} has joints {joints.shape} and visibility {vis.shape}, "
                f"expected ({len(BADJA_JOINT_NAMES)}, 2) and ({len(BADJA_JOINT_NAMES)},); is this a BADJA file?"
            )
        stem = Path(str(entry["image_path"]).replace("\\", "/")).stem
        if stem in frames:
            raise InputError(f"{src}: frame {stem} is annotated twice; remove one entry")
        rows, cols = joints[slots, 0], joints[slots, 1]
        x = (cols + 0.5) * (w / sw) - 0.5
        y = (rows + 0.5) * (h / sh) - 0.5
        frames[stem] = [[float(a), float(b), int(v)] for a, b, v in zip(x, y, vis[slots])]
    if not frames:
        raise InputError(f"{src}: no annotated frames; pass a non-empty BADJA joint_annotations file")
    log.info("converted %d BADJA frames (%d joints) to %dx%d pixels", len(frames), len(slots), w, h)
    return {"names": [BADJA_JOINT_NAMES[s] for s in slots], "frames": dict(sorted(frames.items()))}


def write_keypoints(keypoints: dict, path) -> Path:
    """Write a keypoints dictionary as JSON to ``path`` atomically (its folder is created if missing)."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    return write_json(path, keypoints, indent=1)


def frame_size_of(frames_dir) -> tuple[int, int]:
    """(H, W) of the first image (in name order) of a folder of frames."""
    d = Path(frames_dir)
    if not d.is_dir():
        raise InputError(f"{d}: frames folder not found; pass the sequence's images/ folder or use --frame-size H W")
    files = sorted(p for p in d.iterdir() if p.suffix.lower() in _IMAGE_EXTS)
    if not files:
        raise InputError(f"{d}: no images ({', '.join(_IMAGE_EXTS)}) in the frames folder; use --frame-size H W")
    img = cv2.imread(str(files[0]), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(f"{files[0]}: cannot read the image; pass --frame-size H W instead")
    return int(img.shape[0]), int(img.shape[1])


def main(argv=None) -> int:
    """``python -m s3o_warp.data.keypoints IN.json OUT.json (--frames DIR | --frame-size H W)``."""
    ap = argparse.ArgumentParser(prog="python -m s3o_warp.data.keypoints",
                                 description="Convert BADJA joint annotations to keypoints.json.")
    ap.add_argument("badja_json", help="BADJA joint_annotations/<animal>.json")
    ap.add_argument("out", help="keypoints.json to write")
    size = ap.add_mutually_exclusive_group(required=True)
    size.add_argument("--frames", help="folder of the sequence's frames (their size is read from the first one)")
    size.add_argument("--frame-size", nargs=2, type=int, metavar=("H", "W"), help="frame height and width in pixels")
    ap.add_argument("--source-size", nargs=2, type=int, metavar=("H", "W"), default=list(BADJA_SOURCE_SIZE),
                    help="size the BADJA coordinates refer to (default: 1080 1920)")
    ap.add_argument("--all-joints", action="store_true", help="keep all 37 BADJA slots, not only the 20 annotated")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        fs = frame_size_of(args.frames) if args.frames else tuple(args.frame_size)
        kp = badja_to_keypoints(args.badja_json, fs, tuple(args.source_size), annotated_only=not args.all_joints)
        write_keypoints(kp, args.out)
    except InputError as e:
        ap.exit(2, f"error: {e}\n")
    log.info("wrote %s", args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
