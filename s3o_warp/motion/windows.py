"""Which frames each step of the warm-up and the joint phase optimises: windows of consecutive frames.

The warm-up starts with a sweep outward from the canonical frame (the coarse shape was lifted from it): each
frame entering the sweep starts from its nearest already-fitted neighbour's pose. Then, and in the joint
phase, windows are drawn around uniformly chosen frames (clamped, so the ends are covered too).
"""

from __future__ import annotations

import torch

from s3o_warp.model import S3OModel

WARMUP_SWEEP = 0.5
"""Fraction of the warm-up that sweeps windows outward from the canonical frame (the rest: random windows)."""


class FrameWindows:
    """Windows of ``batch_frames`` consecutive frames of a ``num_frames`` sequence, drawn with ``generator`` (the
    fit's, which its checkpoints carry)."""

    def __init__(self, num_frames: int, batch_frames: int, canonical: int, generator: torch.Generator, device):
        self.T, self.n = num_frames, min(batch_frames, num_frames)
        self.canonical, self.gen, self.device = canonical, generator, device

    def sweep_starts(self, stride: int | None = None) -> list[int]:
        """Window starts of the warm-up sweep: the canonical frame's window, then outward both ways, ``stride``
        frames per stage (None: half the window, the fit's)."""
        T, n = self.T, self.n
        stride = max(1, stride or n // 2)
        s0 = min(max(self.canonical - n // 2, 0), T - n)
        right = list(range(s0 + stride, T - n + 1, stride))
        if right and right[-1] != T - n:
            right.append(T - n)
        left = list(range(s0 - stride, -1, -stride))
        if left and left[-1] != 0:
            left.append(0)
        order = [s0]
        for k in range(max(len(left), len(right))):
            order += ([right[k]] if k < len(right) else []) + ([left[k]] if k < len(left) else [])
        return order

    def random(self) -> torch.Tensor:
        """A window around a uniformly drawn frame (clamped, so ends are covered too): (n,) int64 frame ids."""
        centre = int(torch.randint(0, self.T, (1,), generator=self.gen))
        start = min(max(centre - self.n // 2, 0), self.T - self.n)
        return torch.arange(start, start + self.n, device=self.device)

    def next(self, warmup: bool, step: int, warmup_steps: int, model: S3OModel) -> torch.Tensor:
        """The window of ``step``: in the first WARMUP_SWEEP of the warm-up, the sweep's (seeding frames that enter
        it from their nearest fitted neighbour in ``model``), else a random one."""
        sweep_steps = int(WARMUP_SWEEP * warmup_steps) if warmup else 0
        if step < sweep_steps:
            starts = self.sweep_starts()
            per = max(1, sweep_steps // len(starts))
            start = starts[min(step // per, len(starts) - 1)]
            frames = torch.arange(start, start + self.n, device=self.device)
            seed_unvisited(model, frames, self.canonical)
            return frames
        return self.random()


@torch.no_grad()
def seed_unvisited(model: S3OModel, frames: torch.Tensor, canonical: int) -> None:
    """Frames entering the sweep for the first time start from the nearest visited frame's pose (``model.visited``
    marks them; the canonical frame counts as visited first)."""
    m = model
    visited = m.visited
    if not bool(visited.any()):
        visited[canonical] = True
    idx = torch.nonzero(visited).flatten()
    for f in frames.tolist():
        if visited[f]:
            continue
        src = int(idx[(idx - f).abs().argmin()])
        for p in (m.root_aa, m.root_t, m.bone_aa, m.bone_t):
            p.data[f] = p.data[src]
    visited[frames] = True
