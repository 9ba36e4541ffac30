"""Dense pure-torch twin of ``s3o_warp.kernels.nearest`` (same signature): the right answer."""

from __future__ import annotations

import torch

__all__ = ["nearest_point_reference"]


def nearest_point_reference(queries: torch.Tensor, query_frame: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """``(Q,)`` ``argmin_n |points[query_frame[q], n] - queries[q]|`` from the full distance table."""
    d = ((points[query_frame.long()] - queries[:, None, :]) ** 2).sum(-1)  # (Q, N)
    return d.argmin(1)
