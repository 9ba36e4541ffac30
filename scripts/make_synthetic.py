#!/usr/bin/env python
"""Make a synthetic sequence with ground truth (thin wrapper over ``s3o_warp.synth.make_sequence``).

Examples:
    python scripts/make_synthetic.py --out data/quadruped
    python scripts/make_synthetic.py --out data/fox --glb Fox.glb --clip Walk --frames 60 --fps 30
    python scripts/make_synthetic.py --out data/lizard --model lizard --elev 30
"""

from __future__ import annotations

import argparse
import logging
import sys

from s3o_warp.errors import InputError
from s3o_warp.synth import make_sequence
from s3o_warp.synth.sequence import PROCEDURAL


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--size must look like 320x240 (W x H), got {text!r}") from None
    return w, h


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", required=True, help="sequence folder to create")
    p.add_argument("--glb", default=None, help="render this skinned glTF (.glb/.gltf) instead of a built-in model")
    p.add_argument("--model", choices=sorted(PROCEDURAL), default="quadruped",
                   help="the built-in model rendered without --glb: quadruped (walk) or lizard (a long body on short legs, "
                        "crawling with lateral undulation); default quadruped")
    p.add_argument("--clip", default=None, help="glTF animation clip name (default: the first)")
    p.add_argument("--frames", type=int, default=48, help="number of frames (default 48)")
    p.add_argument("--fps", type=float, default=24.0, help="frames per second (default 24)")
    p.add_argument("--size", type=_size, default=(320, 240), help="image size WxH (default 320x240)")
    p.add_argument("--azim", type=float, nargs=2, default=(-30.0, 30.0), metavar=("A0", "A1"),
                   help="orbit azimuth range in degrees, 0 = right flank, 90 = face (default -30 30)")
    p.add_argument("--elev", type=float, default=10.0, help="camera elevation in degrees (default 10)")
    p.add_argument("--path", choices=("orbit", "pan"), default="orbit", help="camera path (default orbit)")
    p.add_argument("--seed", type=int, default=0, help="seed of the built-in model, texture and background")
    p.add_argument("--device", default="cpu", help="torch device for the rasteriser: cpu or cuda:0")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out folder")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        out = make_sequence(args.out, source=args.glb or args.model, clip=args.clip, frames=args.frames,
                            fps=args.fps, size=args.size, azim=tuple(args.azim), elev=args.elev, seed=args.seed,
                            path=args.path, device=args.device, overwrite=args.overwrite)
    except InputError as exc:
        print(f"make_synthetic: {exc}", file=sys.stderr)
        return 2
    print(out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
