"""The ``s3o-fit`` console script."""

from __future__ import annotations

import sys


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``s3o-fit``; the end-to-end fit is not built yet, and this says so."""
    print("s3o-fit: the end-to-end fit is not built yet (issue 4); nothing was fitted.", file=sys.stderr)
    return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
