"""The sequence on the fit's device: every frame's crop, mask and forward flow, held in memory for short videos
and streamed from disk for long ones (``data.resident_max_frames``).

``prepare_data`` opens a sequence (:mod:`s3o_warp.data.sequence`), crops every frame and computes or loads its
optical flow (:mod:`s3o_warp.data.flow`); the fit reads frames through :class:`FitData` only.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from s3o_warp.config import Config
from s3o_warp.data import sequence
from s3o_warp.data.long_flow import compute_long_flow
from s3o_warp.errors import ConfigError, InputError


@dataclass
class FitData:
    """Crops of the whole sequence on the fit's device (S = crop side, T frames)."""

    name: str
    frame_names: list
    frame_size: tuple  # (H, W) full frame
    fps: float
    images: "FrameStore"  # (T,S,S,3) float in [0,1], indexed by frame ids
    masks: torch.Tensor  # (T,S,S) float {0,1}
    crop_to_frame: torch.Tensor  # (T,3,3)
    crop_scale: torch.Tensor  # (T,) crop pixels per frame pixel
    flow_fwd: "FrameStore"  # (T-1,S,S,2) crop-t pixels, indexed by pair ids
    conf_fwd: "FrameStore"  # (T-1,S,S) in [0,1]
    sequence_dir: Path
    frame_weight: torch.Tensor | None = None  # (T,) silhouette weight (objects leaving the frame count less)
    open_kwargs: dict | None = None  # how to re-open the sequence (masks=, name=) for pictures
    mask_dir: Path | None = None  # where the sequence's masks are (for scoring)
    keypoints_file: Path | None = None  # keypoints.json beside the sequence, if any (scoring only)
    ground_truth_dir: Path | None = None  # ground_truth/ beside the sequence, if any (scoring only)
    long_flow: dict | None = None  # {gap > 1: (flow (T-g,S,S,2), conf (T-g,S,S)) FrameStores}, pairs (t, t + gap)

    @property
    def num_frames(self) -> int:
        return self.masks.shape[0]

    @property
    def crop_size(self) -> int:
        return self.masks.shape[1]


class FrameStore:
    """Per-frame arrays indexed by a tensor of frame ids, returned as float tensors on the fit's device.

    Resident: one device tensor (fast; short videos). Streamed: numpy arrays or memory maps on disk,
    read per batch, so memory grows with the batch and the resolution, not with the video length.
    """

    def __init__(self, arrays, device: torch.device, scale: float = 1.0, resident: bool = True, stack_axis=None):
        self.device, self.scale, self.resident = device, scale, resident
        self._list = not hasattr(arrays, "shape")  # a sequence of per-frame arrays (e.g. flow pairs)
        if resident:
            a = np.stack([np.asarray(arrays[i]) for i in range(len(arrays))]) if self._list else np.asarray(arrays)
            self._data = torch.from_numpy(a.astype(np.float32) * scale if scale != 1.0 else a.astype(np.float32)).to(device)
        else:
            self._data = arrays

    def __len__(self) -> int:
        return len(self._data)

    def __getitem__(self, frames) -> torch.Tensor:
        if self.resident:
            return self._data[frames]
        idx = frames.detach().cpu().numpy() if isinstance(frames, torch.Tensor) else np.asarray(frames)
        if self._list:
            a = np.stack([np.asarray(self._data[int(i)]) for i in np.atleast_1d(idx)])
            if np.ndim(idx) == 0:
                a = a[0]
        else:
            a = np.asarray(self._data[idx])
        t = torch.from_numpy(np.ascontiguousarray(a)).to(self.device).float()
        return t * self.scale if self.scale != 1.0 else t


class _PairField:
    """Lazy list over a FlowCache: element t is one field of pair t (a memory-mapped array)."""

    def __init__(self, flow, field: str):
        self.flow, self.field = flow, field

    def __len__(self) -> int:
        return len(self.flow)

    def __getitem__(self, t: int):
        return getattr(self.flow.pair(int(t)), self.field)


class _GapPairs:
    """The pairs (t, t + gap) of a LongFlowCache as a FlowCache-like list (``len``, ``pair(t)``)."""

    def __init__(self, cache, gap: int):
        self.cache, self.gap = cache, gap

    def __len__(self) -> int:
        return len(self.cache.files[self.gap])

    def pair(self, t: int):
        return self.cache.pair(t, self.gap)


def prepare_data(sequence_dir: Path, cfg: Config, run_dir: Path, device: torch.device, masks=None, name=None) -> FitData:
    """Open the sequence, crop every frame and compute (or load) the forward flow and its confidence, between
    consecutive frames and, where the camera hypotheses are scored, frames 2-32 apart (:mod:`s3o_warp.data.long_flow`).

    Sequences of up to ``data.resident_max_frames`` frames live in (device) memory; longer ones are
    streamed: crops go to a memory-mapped file in ``<run>/cache`` and flow stays in its per-pair cache.
    """
    open_kwargs = {"masks": masks, "name": name}
    seq = sequence.open_sequence(sequence_dir, cfg=cfg.data, **open_kwargs)
    T = seq.num_frames
    if T < 2:
        raise InputError(f"sequence {sequence_dir} has {T} frame(s); the fit needs at least 2")
    if cfg.coarse.canonical_frame is not None and cfg.coarse.canonical_frame >= T:
        raise ConfigError(f"coarse.canonical_frame={cfg.coarse.canonical_frame}: the sequence has frames 0-{T - 1}; "
                          "pick one of them or leave it unset for the automatic choice")
    S = cfg.data.crop_size
    resident = T <= cfg.data.resident_max_frames
    mask_crops = np.zeros((T, S, S), np.bool_)
    c2f = np.zeros((T, 3, 3), np.float32)
    if resident:
        imgs = np.zeros((T, S, S, 3), np.uint8)
    else:
        (run_dir / "cache").mkdir(parents=True, exist_ok=True)
        key = "-".join(seq.mask_digests[:1] + seq.mask_digests[-1:])[:24]
        path = run_dir / "cache" / f"crops_{T}_{S}_{key}.npy"
        imgs = np.lib.format.open_memmap(path, mode="w+", dtype=np.uint8, shape=(T, S, S, 3))
    for k, crop in enumerate(seq.crops()):
        imgs[k] = crop.image
        mask_crops[k] = crop.mask
        c2f[k] = crop.crop_to_frame
    mc = cfg.motion  # frames far apart serve the camera hypotheses' score only
    scored = mc.hypotheses > 1 and mc.turn_rate is None and mc.w_flow > 0
    lflow = compute_long_flow(seq, run_dir / "cache", gaps=None if scored else (1,), cfg=cfg.data)
    flow = _GapPairs(lflow, 1)
    long_flow = {g: (FrameStore(_PairField(_GapPairs(lflow, g), "flow_fwd"), device, resident=resident),
                     FrameStore(_PairField(_GapPairs(lflow, g), "conf_fwd"), device, resident=resident))
                 for g in lflow.gaps if g > 1}
    dev = dict(device=device)
    return FitData(
        name=seq.name,
        frame_names=list(seq.frame_names),
        frame_size=tuple(int(x) for x in seq.size),
        fps=float(seq.fps),
        images=FrameStore(imgs, device, scale=1.0 / 255.0, resident=resident),
        masks=torch.from_numpy(mask_crops.astype(np.float32)).to(**dev),
        crop_to_frame=torch.from_numpy(c2f).to(**dev),
        crop_scale=torch.from_numpy(1.0 / c2f[:, 0, 0]).to(**dev),
        flow_fwd=FrameStore(_PairField(flow, "flow_fwd"), device, resident=resident),
        conf_fwd=FrameStore(_PairField(flow, "conf_fwd"), device, resident=resident),
        sequence_dir=Path(sequence_dir),
        frame_weight=torch.as_tensor(
            np.where(np.asarray(seq.touches_border), sequence.BORDER_WEIGHT, 1.0), dtype=torch.float32, device=device
        ),
        open_kwargs=open_kwargs,
        mask_dir=Path(seq.mask_files[0]).parent,
        keypoints_file=seq.keypoints_file,
        ground_truth_dir=seq.ground_truth_dir,
        long_flow=long_flow,
    )
