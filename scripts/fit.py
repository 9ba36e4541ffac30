#!/usr/bin/env python
"""Fit one sequence: ``python scripts/fit.py [SEQUENCE] --device cpu|cuda[:N] --out RUN_DIR ...`` (= ``s3o-fit``)."""

import sys

from s3o_warp.cli import main

if __name__ == "__main__":
    sys.exit(main())
