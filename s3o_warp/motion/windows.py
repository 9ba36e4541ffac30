"""Which frames each step of the warm-up and the joint phase optimises: windows of consecutive frames of one video.

The warm-up starts with a sweep outward from the canonical frame (the coarse shape was lifted from it), and in each
other video from its anchor (the frame its orientation was found on): each frame entering the sweep starts from its
nearest already-fitted neighbour's pose in the same video. Then, and in the joint phase, windows are drawn around
uniformly chosen frames (clamped to their video, so the ends are covered too).
"""

from __future__ import annotations

import torch

from s3o_warp.model import S3OModel

WARMUP_SWEEP = 0.5
"""Fraction of the warm-up that sweeps windows outward from the canonical frame (the rest: random windows)."""


class FrameWindows:
    """Windows of ``batch_frames`` consecutive frames of a ``num_frames`` sequence, drawn with ``generator`` (the
    fit's, which its checkpoints carry). ``videos``: ``(start, stop)`` of each video (None: one video); a window
    never leaves its video. ``anchors``: the frame each video's sweep starts from (None: the canonical frame's
    video only)."""

    def __init__(self, num_frames: int, batch_frames: int, canonical: int, generator: torch.Generator, device,
                 videos: list[tuple[int, int]] | None = None, anchors: list[int] | None = None):
        self.T, self.n = num_frames, min(batch_frames, num_frames)
        self.batch = batch_frames
        self.canonical, self.gen, self.device = canonical, generator, device
        self.videos = videos or [(0, num_frames)]
        self.anchors = anchors or [min(max(canonical, a), b - 1) for a, b in self.videos]

    def video(self, frame: int) -> int:
        return next(i for i, (a, b) in enumerate(self.videos) if a <= frame < b)

    def _sweep(self, video: int, stride: int | None) -> list[int]:
        a, b = self.videos[video]
        T, n = b - a, min(self.batch, b - a)
        stride = max(1, stride or n // 2)
        s0 = min(max(self.anchors[video] - a - n // 2, 0), T - n)
        right = list(range(s0 + stride, T - n + 1, stride))
        if right and right[-1] != T - n:
            right.append(T - n)
        left = list(range(s0 - stride, -1, -stride))
        if left and left[-1] != 0:
            left.append(0)
        order = [s0]
        for k in range(max(len(left), len(right))):
            order += ([right[k]] if k < len(right) else []) + ([left[k]] if k < len(left) else [])
        return [(a + s, n) for s in order]

    def sweep_starts(self, stride: int | None = None) -> list[int]:
        """Window starts of the warm-up sweep: the canonical frame's window, then outward both ways, ``stride``
        frames per stage (None: half the window, the fit's); several videos take their stages in turn."""
        return [s for s, _ in self.sweep_windows(stride)]

    def sweep_windows(self, stride: int | None = None) -> list[tuple[int, int]]:
        """``(start, length)`` of every window of the sweep (:meth:`sweep_starts`)."""
        per = [self._sweep(v, stride) for v in range(len(self.videos))]
        out = []
        for k in range(max(len(p) for p in per)):
            out += [p[k] for p in per if k < len(p)]
        return out

    def random(self, video: int | None = None) -> torch.Tensor:
        """A window around a uniformly drawn frame (of ``video``, or of any), clamped to its video so ends are
        covered too: (n,) int64 frame ids."""
        if video is None:
            centre = int(torch.randint(0, self.T, (1,), generator=self.gen))
            a, b = self.videos[self.video(centre)] if len(self.videos) > 1 else (0, self.T)
        else:
            a, b = self.videos[video]
            centre = a + int(torch.randint(0, b - a, (1,), generator=self.gen))
        n = min(self.batch, b - a)
        start = min(max(centre - n // 2, a), b - n)
        return torch.arange(start, start + n, device=self.device)

    def next(self, warmup: bool, step: int, warmup_steps: int, model: S3OModel) -> torch.Tensor:
        """The window of ``step``: in the first WARMUP_SWEEP of the warm-up, the sweep's (seeding frames that enter
        it from their nearest fitted neighbour in ``model``), else a random one."""
        sweep_steps = int(WARMUP_SWEEP * warmup_steps) if warmup else 0
        if step < sweep_steps:
            wins = self.sweep_windows()
            per = max(1, sweep_steps // len(wins))
            start, n = wins[min(step // per, len(wins) - 1)]
            frames = torch.arange(start, start + n, device=self.device)
            seed_unvisited(model, frames, self.canonical, self.videos, self.anchors)
            return frames
        return self.random()


@torch.no_grad()
def seed_unvisited(model: S3OModel, frames: torch.Tensor, canonical: int,
                   videos: list[tuple[int, int]] | None = None, anchors: list[int] | None = None) -> None:
    """Frames entering the sweep for the first time start from the nearest visited frame's pose in their video
    (``model.visited`` marks them; the canonical frame and each video's anchor count as visited first). Bone motion
    rows that synchronized videos share are seeded once."""
    m = model
    visited = m.visited
    if not bool(visited.any()):
        visited[canonical] = True
        for a in anchors or []:
            visited[a] = True
    rows_seen = set(m.motion_of[visited].tolist())
    videos = videos or [(0, m.num_frames)]
    for f in frames.tolist():
        if visited[f]:
            continue
        a, b = next((a, b) for a, b in videos if a <= f < b)
        idx = torch.nonzero(visited[a:b]).flatten() + a
        if len(idx) == 0:
            continue
        src = int(idx[(idx - f).abs().argmin()])
        for p in (m.root_aa, m.root_t):
            p.data[f] = p.data[src]
        row, src_row = int(m.motion_of[f]), int(m.motion_of[src])
        if row not in rows_seen:
            for p in (m.bone_aa, m.bone_t):
                p.data[row] = p.data[src_row]
            rows_seen.add(row)
    visited[frames] = True
