"""The ``s3o-masks`` console script: a sequence folder (frames, masks and a preview) from a video and a box.

    s3o-masks INPUT --box X0,Y0,X1,Y1 [--frame K] [--box-at K:X0,Y0,X1,Y1 ...] --out SEQ
              [--segmenter grabcut|sam2] [--checkpoint PATH]

Bad input ends with one line on stderr (exit code 2) and nothing written.
"""

from __future__ import annotations

import argparse
import logging
import sys

from s3o_warp import interrupt
from s3o_warp.errors import InputError
from s3o_warp.masks.make import SEGMENTERS, make_masks, parse_box, parse_box_at


def add_box_arguments(p: argparse.ArgumentParser, per_video: bool = False) -> None:
    """The flags that describe the object (shared with ``s3o-fit``, where ``per_video`` lets --box and --frame be
    given once per video)."""
    each = " (several videos: once per video, in their order)" if per_video else ""
    p.add_argument("--box", default=None, metavar="X0,Y0,X1,Y1", action="append" if per_video else "store",
                   help="a box around the object on frame --frame, in that frame's pixels (left, top, right, bottom)"
                   + each)
    p.add_argument("--frame", type=int, default=None if per_video else 0, metavar="K",
                   action="append" if per_video else "store", help="the frame --box is drawn on (default 0)" + each)
    p.add_argument("--box-at", dest="box_at", action="append", default=[], metavar="K:X0,Y0,X1,Y1",
                   help="a further box on frame K (repeatable): where the object is lost, or changes much")
    p.add_argument("--segmenter", default="grabcut", help=f"one of {', '.join(SEGMENTERS)}: grabcut (default, OpenCV "
                   "and PyMaxflow) or sam2 (the sam2 package and --checkpoint)")
    p.add_argument("--checkpoint", default=None, metavar="PATH", help="SAM 2 weights for --segmenter sam2 "
                   "(e.g. sam2.1_hiera_tiny.pt, downloaded once; never fetched here)")


def boxes_from(args, box=None, frame=None) -> dict:
    """``{frame: box}`` from --box/--frame (or the given ``box`` and ``frame``) and every --box-at."""
    boxes = {}
    box = args.box if box is None else box
    if box is not None:
        boxes[args.frame if frame is None else frame] = parse_box(box)
    for item in args.box_at:
        k, b = parse_box_at(item)
        if k in boxes:
            raise InputError(f"--box-at {item!r}: frame {k} already has a box; give one box per frame")
        boxes[k] = b
    return boxes


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="s3o-masks", description="Masks for a video from a box around the object.")
    p.add_argument("input", help="a video file, a folder of frames, or a folder with images/")
    p.add_argument("--out", required=True, metavar="SEQ", help="the sequence folder to write (images/, masks/, "
                   "masks_preview.mp4); s3o-fit SEQ fits it")
    add_box_arguments(p)
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO, format="%(message)s")
    try:
        with interrupt.on_signals():  # Ctrl-C, SIGTERM: the masks stop at the next frame, nothing is written
            make_masks(args.input, args.out, boxes_from(args), args.segmenter, args.checkpoint)
    except InputError as e:
        print(f"s3o-masks: error: {e}", file=sys.stderr)
        return 2
    except (interrupt.Interrupted, KeyboardInterrupt) as e:
        print(f"s3o-masks: {e or 'interrupted'}; nothing was written", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
