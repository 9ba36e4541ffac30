"""Re-export a finished run as rigged, animated USD and glTF.

Usage::

    python scripts/export.py RUN_DIR [--out FILE.usda|.usdc|.usd|.glb] [--baked] [--influences K]

Without ``--out`` it writes ``RUN_DIR/<name>.usdc`` (``<name>_baked.usdc`` with ``--baked``) and
``RUN_DIR/<name>.glb``, where ``<name>`` is the run directory's name. Every file is written to a
temporary name and renamed. Exit status 2 with one line on bad input.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from s3o_warp.errors import InputError
from s3o_warp.export import export_gltf, export_usd, load_rig

logger = logging.getLogger("s3o_warp.scripts.export")


def main(argv: list[str] | None = None) -> int:
    """Parse arguments, load the run's rig and write the requested files; returns the exit status."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", type=Path, help="run directory holding canonical.ply, skeleton.json, motion.npz")
    parser.add_argument("--out", type=Path, default=None, help="one output file: .usda, .usdc, .usd or .glb")
    parser.add_argument("--baked", action="store_true", help="USD with skinning baked into time-sampled points")
    parser.add_argument("--influences", type=int, default=4, help="joints per vertex in the USD skin binding (glTF always stores the top 4)")
    parser.add_argument("--meters-per-unit", type=float, default=1.0, help="the USD stage's metersPerUnit")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        rig = load_rig(args.run_dir)
        name = args.run_dir.resolve().name
        outs = [args.out] if args.out is not None else [
            args.run_dir / (f"{name}_baked.usdc" if args.baked else f"{name}.usdc"),
            args.run_dir / f"{name}.glb",
        ]
        for out in outs:
            if out.suffix.lower() == ".glb":
                report = export_gltf(rig, out)
            else:
                report = export_usd(rig, out, influences=args.influences, baked=args.baked, meters_per_unit=args.meters_per_unit)
            logger.info(
                "%s: %d influences, skinning approximation error %.3g (%.2g of the bbox diagonal), camera %.3g px",
                report.path, report.influences, report.topk_error, report.topk_error_rel, report.camera_px_error,
            )
    except InputError as exc:
        print(f"export: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
