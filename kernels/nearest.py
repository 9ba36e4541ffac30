"""Nearest projected point per query pixel (brute force, one thread per query), forward only.

Used by the mask-coverage loss: each mask pixel the render leaves uncovered is matched to the nearest
projected vertex of its frame, and the loss (in torch, on the matched indices) pulls that vertex
towards it. The search is not differentiable (an argmin); the distance built from its result is.
"""

from __future__ import annotations

import torch
import warp as wp

from ._warp import (
    check_float,
    check_shape,
    frame_chunks,
    index_bounds,
    map_chunks,
    same_device,
    stream_of,
    to_wp,
    wp_device,
)

__all__ = ["nearest_point"]

wp.set_module_options({"enable_backward": False})  # an argmin: forward only


@wp.kernel
def nearest_point_kernel(
    queries: wp.array(dtype=wp.vec2),
    query_frame: wp.array(dtype=wp.int32),
    points: wp.array2d(dtype=wp.vec2),
    # outputs
    index: wp.array(dtype=wp.int32),
):
    """Per-query thread q: the index n minimising |points[frame(q), n] - queries[q]| (first on ties)."""
    q = wp.tid()
    x = queries[q]
    t = query_frame[q]
    best = float(1.0e30)
    arg = int(-1)
    for n in range(points.shape[1]):
        d = points[t, n] - x
        d2 = wp.dot(d, d)
        if d2 < best:
            best = d2
            arg = n
    index[q] = wp.int32(arg)


def nearest_point(queries: torch.Tensor, query_frame: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """For each 2D query, the index of the nearest point of its frame.

    Args:
        queries: ``(Q, 2)`` float32 positions (e.g. pixel centres ``(c, r)``).
        query_frame: ``(Q,)`` integer frame of each query, in ``[0, T)``.
        points: ``(T, N, 2)`` float32 candidate positions per frame (e.g. projected vertices), ``N >= 1``.

    Returns:
        ``(Q,)`` int64: ``out[q] = argmin_n |points[query_frame[q], n] - queries[q]|`` (lowest n on ties).
        Not differentiable; gather ``points`` with it to get a differentiable distance.

    Raises:
        ValueError: wrong shapes, mixed devices, no points, frames out of range. TypeError: non-float32.
    """
    name = "nearest_point"
    check_shape(name, "queries", queries, (None, 2))
    check_shape(name, "query_frame", query_frame, (queries.shape[0],))
    check_shape(name, "points", points, (None, None, 2))
    check_float(name, "queries", queries)
    check_float(name, "points", points)
    same_device(name, queries, query_frame, points)
    if query_frame.dtype.is_floating_point or query_frame.dtype == torch.bool:
        raise TypeError(f"{name}(): query_frame must be an integer tensor, got {query_frame.dtype}")
    out = torch.empty(queries.shape[0], dtype=torch.int32, device=queries.device)
    if queries.shape[0] == 0:
        return out.long()
    if points.shape[1] == 0:
        raise ValueError(f"{name}(): points has no candidates (shape {tuple(points.shape)})")
    fmin, fmax = index_bounds(query_frame, (0, points.shape[0] - 1))  # a device sync unless the bounds are known
    if fmin < 0 or fmax >= points.shape[0]:
        raise ValueError(f"{name}(): query_frame must lie in [0, {points.shape[0]}), got [{fmin}, {fmax}]")
    qf = query_frame.to(torch.int32).contiguous()
    q, pts = queries.contiguous(), to_wp(points, wp.vec2)

    def launch(s: slice) -> None:  # on the CPU, ranges of queries side by side
        with stream_of(queries):
            wp.launch(nearest_point_kernel, dim=s.stop - s.start, inputs=[to_wp(q[s], wp.vec2), to_wp(qf[s]), pts],
                      outputs=[to_wp(out[s])], device=wp_device(queries))

    map_chunks(launch, frame_chunks(queries, queries.shape[0]))
    return out.long()
