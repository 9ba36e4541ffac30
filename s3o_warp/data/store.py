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
    videos: list | None = None  # [Video]: where each video's frames lie (one for a one-video fit)

    @property
    def num_frames(self) -> int:
        return self.masks.shape[0]

    @property
    def crop_size(self) -> int:
        return self.masks.shape[1]

    @property
    def num_videos(self) -> int:
        return len(self.videos) if self.videos else 1

    def video_of(self) -> np.ndarray:
        """``(T,)`` int64: the video of each frame."""
        if not self.videos:
            return np.zeros(self.num_frames, np.int64)
        return np.concatenate([np.full(v.num_frames, i, np.int64) for i, v in enumerate(self.videos)])

    def pair_valid(self, gap: int = 1) -> np.ndarray:
        """``(T - gap,)`` bool: pair (t, t + gap) lies in one video."""
        vo = self.video_of()
        return vo[:-gap] == vo[gap:] if gap < len(vo) else np.zeros(0, bool)


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


@dataclass
class Video:
    """One video of a fit: frames ``start .. stop - 1`` of :class:`FitData` and where it came from."""

    name: str
    start: int
    stop: int
    frame_names: list
    frame_size: tuple  # (H, W)
    fps: float
    sequence_dir: Path
    open_kwargs: dict
    mask_dir: Path | None = None
    keypoints_file: Path | None = None
    ground_truth_dir: Path | None = None

    @property
    def num_frames(self) -> int:
        return self.stop - self.start


@dataclass
class _Source:
    """One video's crops, masks and flow cache before they are joined into :class:`FitData`."""

    seq: "sequence.Sequence"
    images: np.ndarray  # (T, S, S, 3) uint8, in memory or memory-mapped
    masks: np.ndarray  # (T, S, S) bool
    crop_to_frame: np.ndarray  # (T, 3, 3)
    flow: "object"  # LongFlowCache
    open_kwargs: dict


class _Joined:
    """Per-pair arrays of several videos as one list over the fit's pair ids: pair t of gap g joins frames t and
    t + g, which lie in one video or in none (then a zero array: no flow, no confidence)."""

    def __init__(self, parts: list, starts: list[int], lengths: list[int], gap: int, total: int, shape):
        self.parts, self.starts, self.lengths, self.gap, self.total = parts, starts, lengths, gap, total
        self.item_shape = shape

    def __len__(self) -> int:
        return max(self.total - self.gap, 0)

    def __getitem__(self, t: int):
        t = int(t)
        for part, s, n in zip(self.parts, self.starts, self.lengths):
            if s <= t < s + n:
                k = t - s
                if part is None or k + self.gap >= n:
                    break
                return part[k]
        return np.zeros(self.item_shape, np.float32)


class _JoinedFrames:
    """Per-frame arrays of several videos (e.g. memory-mapped crops) as one list over the fit's frame ids."""

    def __init__(self, parts: list, starts: list[int]):
        self.parts, self.starts = parts, starts

    def __len__(self) -> int:
        return self.starts[-1] + len(self.parts[-1])

    def __getitem__(self, t: int):
        t = int(t)
        v = max(i for i, s in enumerate(self.starts) if s <= t)
        return self.parts[v][t - self.starts[v]]


def _crops_and_flow(seq: "sequence.Sequence", cfg: Config, run_dir: Path, open_kwargs: dict, resident: bool) -> _Source:
    """Crop every frame of one opened video and compute (or load) its flow."""
    T, S = seq.num_frames, cfg.data.crop_size
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
    return _Source(seq, imgs, mask_crops, c2f, lflow, open_kwargs)


def prepare_data(sequence_dir, cfg: Config, run_dir: Path, device: torch.device, masks=None, name=None) -> FitData:
    """Open the sequence (or each of several: ``sequence_dir`` a list, ``masks`` a list or None), crop every frame
    and compute (or load) the forward flow and its confidence, between consecutive frames and, where the camera
    hypotheses are scored, frames 2-32 apart (:mod:`s3o_warp.data.long_flow`).

    Several videos are one :class:`FitData` whose frames are the videos' one after another (:attr:`FitData.videos`
    says where each lies); no flow pair joins two videos (zero flow and confidence there).

    Sequences of up to ``data.resident_max_frames`` frames in all live in (device) memory; longer ones are
    streamed: crops go to a memory-mapped file in ``<run>/cache`` and flow stays in its per-pair cache.
    """
    several = isinstance(sequence_dir, (list, tuple))
    dirs = [Path(p) for p in sequence_dir] if several else [Path(sequence_dir)]
    mask_list = list(masks) if isinstance(masks, (list, tuple)) else [masks] * len(dirs)
    if len(mask_list) != len(dirs):
        raise InputError(f"{len(mask_list)} mask folders for {len(dirs)} videos; give one per video or none")
    kwargs = [{"masks": mk, "name": name} for mk in mask_list]
    seqs = [sequence.open_sequence(d, cfg=cfg.data, **kw) for d, kw in zip(dirs, kwargs)]
    for d, seq in zip(dirs, seqs):
        if seq.num_frames < 2:
            raise InputError(f"sequence {d} has {seq.num_frames} frame(s); the fit needs at least 2")
    if len(seqs) > 1 and cfg.motion.synchronized and len({s.num_frames for s in seqs}) > 1:
        raise InputError("motion.synchronized: the videos have " + ", ".join(
            f"{s.num_frames} ({d})" for s, d in zip(seqs, dirs)) + " frames; synchronized videos have as many "
            "frames each (trim them to the same instants) or leave out --synchronized")
    T = sum(s.num_frames for s in seqs)
    if cfg.coarse.canonical_frame is not None and cfg.coarse.canonical_frame >= T:
        raise ConfigError(f"coarse.canonical_frame={cfg.coarse.canonical_frame}: the sequence has frames 0-{T - 1}; "
                          "pick one of them or leave it unset for the automatic choice")
    resident = T <= cfg.data.resident_max_frames
    srcs = [_crops_and_flow(seq, cfg, run_dir, kw, resident) for seq, kw in zip(seqs, kwargs)]
    return _fit_data(srcs, dirs, resident, device)


def _video_names(srcs: list[_Source]) -> list[str]:
    """Each video's name (its sequence's), made unique with ``-2``, ``-3``, ... where two are alike."""
    names: list[str] = []
    for s in srcs:
        base, k = s.seq.name, 2
        name = base
        while name in names:
            name, k = f"{base}-{k}", k + 1
        names.append(name)
    return names


def _fit_data(srcs: list[_Source], dirs: list[Path], resident: bool, device) -> FitData:
    lengths = [s.seq.num_frames for s in srcs]
    starts = [int(x) for x in np.cumsum([0] + lengths[:-1])]
    T, S = sum(lengths), srcs[0].masks.shape[1]

    def pairs(gap: int, field: str, shape):
        one = [(_PairField(_GapPairs(s.flow, gap), field) if gap in s.flow.gaps else None) for s in srcs]
        if len(srcs) == 1:
            return one[0]
        return _Joined(one, starts, lengths, gap, T, shape)

    gaps = sorted({g for s in srcs for g in s.flow.gaps})
    flow_fwd = FrameStore(pairs(1, "flow_fwd", (S, S, 2)), device, resident=resident)
    conf_fwd = FrameStore(pairs(1, "conf_fwd", (S, S)), device, resident=resident)
    long_flow = {g: (FrameStore(pairs(g, "flow_fwd", (S, S, 2)), device, resident=resident),
                     FrameStore(pairs(g, "conf_fwd", (S, S)), device, resident=resident))
                 for g in gaps if g > 1 and g < T}
    if len(srcs) == 1:
        imgs = srcs[0].images
    elif resident:
        imgs = np.concatenate([s.images for s in srcs])
    else:
        imgs = _JoinedFrames([s.images for s in srcs], starts)
    c2f = np.concatenate([s.crop_to_frame for s in srcs])
    touches = np.concatenate([np.asarray(s.seq.touches_border) for s in srcs])
    names = _video_names(srcs)
    videos = [Video(name=n, start=a, stop=a + s.seq.num_frames, frame_names=list(s.seq.frame_names),
                    frame_size=tuple(int(x) for x in s.seq.size), fps=float(s.seq.fps), sequence_dir=d,
                    open_kwargs=s.open_kwargs, mask_dir=Path(s.seq.mask_files[0]).parent,
                    keypoints_file=s.seq.keypoints_file, ground_truth_dir=s.seq.ground_truth_dir)
              for n, a, s, d in zip(names, starts, srcs, dirs)]
    first = videos[0]
    dev = dict(device=device)
    return FitData(
        name=first.name if len(videos) == 1 else "+".join(names),
        frame_names=[f for v in videos for f in v.frame_names],
        frame_size=first.frame_size,
        fps=first.fps,
        images=FrameStore(imgs, device, scale=1.0 / 255.0, resident=resident),
        masks=torch.from_numpy(np.concatenate([s.masks for s in srcs]).astype(np.float32)).to(**dev),
        crop_to_frame=torch.from_numpy(c2f).to(**dev),
        crop_scale=torch.from_numpy(1.0 / c2f[:, 0, 0]).to(**dev),
        flow_fwd=flow_fwd,
        conf_fwd=conf_fwd,
        sequence_dir=first.sequence_dir,
        frame_weight=torch.as_tensor(np.where(touches, sequence.BORDER_WEIGHT, 1.0), dtype=torch.float32, device=device),
        open_kwargs=first.open_kwargs,
        mask_dir=first.mask_dir,
        keypoints_file=first.keypoints_file,
        ground_truth_dir=first.ground_truth_dir,
        long_flow=long_flow,
        videos=videos,
    )
