"""The ``s3o-fit`` console script (same as ``python scripts/fit.py``).

    s3o-fit [SEQUENCE ...] [--synchronized] [--device cpu|cuda[:N]] [--out RUN_DIR] [--config FILE] [--preset NAME]
            [--seed N] [--resume] [--branch-from RUN_DIR] [--set section.key=value ...]
            [--box X0,Y0,X1,Y1 [--frame K] [--box-at K:X0,Y0,X1,Y1 ...] [--segmenter NAME] [--checkpoint PATH]]

With no SEQUENCE it renders the built-in procedural quadruped into ``RUN_DIR/sequence`` and fits it. Several
SEQUENCEs are videos of one object: one fit, one body (``--masks`` and ``--box`` then once per video, in order). With ``--box``
SEQUENCE is a video or a folder of frames without masks: ``s3o-masks`` makes ``RUN_DIR/sequence`` first.
Bad input ends with one line on stderr (exit code 2), never a traceback.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from s3o_warp import interrupt
from s3o_warp.config import PRESETS, make_config
from s3o_warp.data.io import read_json
from s3o_warp.errors import InputError
from s3o_warp.fit import fit, resolve_device
from s3o_warp.masks.cli import add_box_arguments, boxes_from
from s3o_warp.masks.make import make_masks
from s3o_warp.synth import make_sequence

log = logging.getLogger("s3o_warp")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="s3o-fit", description="Fit shape, skeleton and motion to one video with masks.")
    p.add_argument("sequence", nargs="*", help="sequence folder (images/ + masks/), a DAVIS sequence folder, a DAVIS root "
                   "with --name, or a video file / frame folder with --masks; several: videos of one object, fitted "
                   "together; default: the built-in quadruped")
    p.add_argument("--masks", default=None, action="append",
                   help="mask folder for a video file or a frame folder without masks/ (several videos: once per video)")
    p.add_argument("--synchronized", action="store_true", help="several videos are the same instants seen from "
                   "several cameras (as many frames each): one body pose per frame (motion.synchronized)")
    p.add_argument("--name", default=None, help="sequence name inside a DAVIS root (e.g. cows)")
    p.add_argument("--device", default=None, help="cpu, cuda or cuda:N (default: CUDA when Warp sees a GPU, else cpu)")
    p.add_argument("--out", default=None, help="run directory (default: runs/<sequence name>)")
    p.add_argument("--config", default=None, help="TOML file with settings (see a run's config.toml)")
    p.add_argument("--preset", default="default", choices=list(PRESETS), help="; ".join(f"{k}: {v[0]}" for k, v in PRESETS.items()))
    p.add_argument("--seed", type=int, default=None, help="seed for every random choice")
    p.add_argument("--resume", action="store_true", help="continue from the last checkpoint in the run directory")
    p.add_argument("--branch-from", default=None, metavar="RUN_DIR",
                   help="start from that run's state just before its first merge (its checkpoints/branch.pt): the same "
                        "sequence and settings but another skeleton.t_o (or another setting read only from there on: fit.BRANCH_MAY_DIFFER), e.g. --set skeleton.t_o=0.90, "
                        "at a fraction of a fit")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE", help="override one setting, e.g. motion.steps=300")
    p.add_argument("--object-id", type=int, default=None, help="palette index of the object in multi-object masks")
    add_box_arguments(p, per_video=True)
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO, format="%(message)s")
    try:
        with interrupt.on_signals():  # Ctrl-C, SIGTERM: the work stops at its next check (a checkpoint where it fits)
            return _run(args)
    except InputError as e:
        print(f"s3o-fit: error: {e}", file=sys.stderr)
        return 2
    except interrupt.Interrupted as e:
        print(f"s3o-fit: {e}; continue with --resume", file=sys.stderr)
        return 130
    except KeyboardInterrupt:
        print("s3o-fit: interrupted; the last checkpoint is kept, continue with --resume", file=sys.stderr)
        return 130


def _per_video(flag: str, values: list | None, count: int) -> list:
    """One value of ``flag`` per video: none, one for one video, or one per video."""
    if not values:
        return [None] * count
    if len(values) != count:
        raise InputError(f"{flag} given {len(values)} times for {count} videos; give it once per video, in their order")
    return list(values)


def _run(args) -> int:
    cfg = make_config(args.preset, args.config, args.overrides + (["motion.synchronized=true"] if args.synchronized
                                                                   else []), args.seed)
    if args.object_id is not None:
        cfg.data.object_id = args.object_id
    n = max(len(args.sequence), 1)
    masks = _per_video("--masks", args.masks, n)
    boxes = [boxes_from(args, b, 0 if f is None else f) for b, f in zip(_per_video("--box", args.box, n), _per_video("--frame", args.frame, n))
             if b is not None] if args.box else []
    if args.frame and not args.box:
        raise InputError("--frame says which frame --box is drawn on; add --box X0,Y0,X1,Y1")
    if args.box_at and n > 1:
        raise InputError("--box-at needs one video; make each video's masks with s3o-masks VIDEO --box ... --box-at ... "
                         "and pass the folders it writes")
    if boxes and not args.sequence:
        raise InputError("--box needs a video or a folder of frames to segment; pass it as SEQUENCE")
    if boxes and any(m is not None for m in masks):
        raise InputError("--box makes the masks; leave out --masks (or leave out --box to use your masks)")
    if args.synchronized and n < 2:
        raise InputError("--synchronized needs several videos (the same instants from several cameras); pass two or more")
    device = resolve_device(args.device)
    log.info("s3o-fit: device %s (%s)", device, "requested" if args.device else "auto")
    if not args.sequence:
        out = Path(args.out or "runs/quadruped")
        seqs = [out / "sequence"]
        if not (seqs[0] / "images").is_dir():
            log.info("no sequence given: rendering the built-in procedural quadruped into %s", seqs[0])
            make_sequence(seqs[0], seed=cfg.seed)
    else:
        seqs = [Path(p) for p in args.sequence]
        for seq in seqs:
            if not seq.exists():
                raise InputError(f"sequence folder {seq} does not exist; pass a folder with images/ and masks/")
        stem = "+".join(args.name or p.stem for p in seqs) if n > 1 else (args.name or seqs[0].stem)
        out = Path(args.out or Path("runs") / stem)
    if boxes:
        seqs = [_masks_first(seq, out, bx, args, cfg) for seq, bx in zip(seqs, boxes)]
    metrics = fit(seqs[0] if n == 1 else seqs, out, cfg, device, resume=args.resume,
                  masks=masks[0] if n == 1 else masks, name=args.name, branch_from=args.branch_from)
    log.info("run directory: %s", out.resolve())
    for label, m in ([(None, metrics)] if n == 1 else list(metrics["videos"].items())):
        iou = (m.get("mask_iou") or {}).get("mean")
        pck = (m.get("pck_t") or {}).get("pck")
        log.info("%smask IoU %s, PCK-T %s", f"{label}: " if label else "", f"{iou:.3f}" if iou is not None else "n/a",
                 f"{pck:.1f}" if pck is not None else "n/a")
    for p in sorted((out / "renders").glob("*")):
        log.info("render: %s", p)
    return 0


def _masks_first(source: Path, out: Path, boxes: dict, args, cfg) -> Path:
    """``s3o-masks SOURCE --out RUN_DIR/sequence/NAME`` (NAME the video's or folder's, which the export is named
    after; kept when made from the same input and boxes); a video's own frame rate becomes ``data.fps``."""
    name = source.parent.name if source.name == "images" else source.stem if source.is_file() else source.name
    seq = out / "sequence" / name
    make_masks(source, seq, boxes, args.segmenter, args.checkpoint, cfg.data.flow_preset, reuse=True)
    fps = read_json(seq / "masks.json", "masks record", "delete the folder to make the masks again").get("fps")
    if fps:
        cfg.data.fps = float(fps)
    return seq


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
