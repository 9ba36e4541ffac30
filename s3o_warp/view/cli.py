"""The ``s3o-view`` console script (same as ``python scripts/view.py``): a local web page showing one fit.

    s3o-view RUN_DIR [--port N] [--host ADDR] [--sequence PATH] [--surface NAME] [--poll S] [--video NAME]

The page (viser, ``pip install 's3o-warp[view]'``) shows the fitted mesh playing the clip's motion with its skeleton,
the fitted camera of every frame with that frame's picture, and the run's figures and settings
(:mod:`s3o_warp.view.server`). A run still fitting shows its newest checkpoint and follows the next ones. A fit of
several videos shows one at a time, chosen on the page (``--video``: the first shown). Without viser, or on bad input
(a folder that is not a run, a run with neither ``motion.npz`` nor a checkpoint, a video the run lacks), one line on
stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import logging
import sys
import threading

from s3o_warp.errors import InputError
from s3o_warp.view.run import SURFACES

INSTALL_HINT = "pip install 's3o-warp[view]'"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="s3o-view", description="Look at a fit in the browser: mesh, skeleton, cameras, "
                                "figures and settings of a run directory.")
    p.add_argument("run_dir", metavar="RUN_DIR", help="the run directory s3o-fit wrote (its --out)")
    p.add_argument("--port", type=int, default=8080, help="port of the page (default 8080; the next free one if busy)")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1: this machine only; "
                   "0.0.0.0 for every interface)")
    p.add_argument("--sequence", default=None, metavar="PATH", help="where the input frames are, for the cameras' "
                   "pictures (default: the sequence metrics.json names, else RUN_DIR/sequence; of a fit of several "
                   "videos, those of the video shown first)")
    p.add_argument("--surface", default=SURFACES[0], choices=SURFACES, help="how the mesh is drawn first")
    p.add_argument("--poll", type=float, default=2.0, metavar="S",
                   help="seconds between looks for a newer checkpoint or motion.npz (0: never)")
    p.add_argument("--video", default=None, metavar="NAME", help="of a fit of several videos (videos.json), the one "
                   "shown first (default: the first; the page switches between them)")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO, format="%(message)s")
    # a browser's unused pre-connections end in a logged traceback each; the page does not depend on them
    logging.getLogger("websockets.server").setLevel(logging.DEBUG if args.verbose else logging.CRITICAL)
    try:
        import viser  # noqa: F401 - the optional dependency, checked before anything else
    except ImportError as e:
        print(f"s3o-view: error: the viewer needs viser, which cannot be imported ({e}); install it with: "
              f"{INSTALL_HINT}", file=sys.stderr)
        return 2
    from s3o_warp.view.server import ViewServer

    try:
        server = ViewServer(args.run_dir, host=args.host, port=args.port, sequence=args.sequence,
                            surface=args.surface, poll_s=args.poll, video=args.video)
    except InputError as e:
        print(f"s3o-view: error: {e}", file=sys.stderr)
        return 2
    v = server.view
    which = f", video {v.videos[v.video]} of {len(v.videos)}" if len(v.videos) > 1 else ""
    print(f"s3o-view: {server.url} shows {args.run_dir}{which} ({v.label}); Ctrl-C to stop", flush=True)
    try:
        threading.Event().wait()
    except KeyboardInterrupt:
        pass
    try:
        server.close()
    except KeyboardInterrupt:  # a second Ctrl-C: leave without waiting
        pass
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
