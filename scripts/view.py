#!/usr/bin/env python
"""Look at a fit in the browser: ``python scripts/view.py RUN_DIR [--port N]`` (= ``s3o-view``)."""

import sys

from s3o_warp.view.cli import main

if __name__ == "__main__":
    sys.exit(main())
