"""Every setting a user may change, in one dataclass tree, with its default, its type and its range.

Precedence: defaults < preset < ``--config`` TOML < ``--set`` flags. Every field has a docstring (the string under
it). Choices are ``Literal``; numeric ranges are ``Annotated[..., Bounds(...)]`` (every number has one; inf and nan
are in none). :func:`check` refuses a wrong type, choice, range or combination in one line that names the key, and
runs before any work of a fit (and at the end of :func:`make_config`). This module imports nothing of the method.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

import tomli_w
import tomllib

from s3o_warp.errors import ConfigError


@dataclass(frozen=True)
class Bounds:
    """The range of a numeric setting: ``lo <= x`` (``lo < x`` when ``lo_open``), likewise ``x <= hi``; never inf or
    nan."""

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False

    def holds(self, x) -> bool:
        if not math.isfinite(x):
            return False
        if self.lo is not None and (x <= self.lo if self.lo_open else x < self.lo):
            return False
        return self.hi is None or (x < self.hi if self.hi_open else x <= self.hi)

    def __str__(self) -> str:
        def num(x):
            return str(int(x)) if float(x).is_integer() else f"{x:g}"

        lo = "" if self.lo is None else f"{'>' if self.lo_open else '>='} {num(self.lo)}"
        hi = "" if self.hi is None else f"{'<' if self.hi_open else '<='} {num(self.hi)}"
        return " and ".join(s for s in (lo, hi) if s)


NONNEG = Bounds(0)
POSITIVE = Bounds(0, lo_open=True)
COUNT = Bounds(1)
TURN_RATE = Bounds(-30, 30)
"""Camera turn rates about the object, degrees per frame: a turn of 30 degrees between frames leaves little for the
optical flow to follow."""


@dataclass
class DataConfig:
    """How a sequence is read, cropped and given optical flow (``s3o_warp.data.sequence``)."""

    object_id: Annotated[int, Bounds(0, 65535)] | None = None
    """For palette (multi-object) masks such as DAVIS-2017: the object's palette index (or a 16-bit label mask's
    value); None = any non-zero / > 127."""
    crop_size: Annotated[int, Bounds(16, 4096)] = 256
    """Working resolution: each frame's square crop is resized to crop_size x crop_size pixels."""
    crop_scale: Annotated[float, Bounds(1, 10)] = 1.2
    """Side of the square crop as a multiple of the mask bounding box's longer side."""
    flow_preset: Literal["ultrafast", "fast", "medium"] = "medium"
    """OpenCV DIS optical-flow preset: ultrafast, fast or medium."""
    fps: Annotated[float, Bounds(0, 1000, lo_open=True)] = 30.0
    """Frame rate of image-folder sequences (DAVIS included); a video file's own frame rate wins when it has one."""
    mask_threshold: Annotated[int, Bounds(0, 254)] = 127
    """Grey-level and RGB masks: foreground = value > mask_threshold (0-255 scale)."""
    largest_blob: bool = True
    """Masks with several disconnected blobs: keep the largest and the fragments near it (a warning names the
    frames); false keeps all."""
    resident_max_frames: Annotated[int, NONNEG] = 400
    """Sequences up to this many frames keep crops and flow in (device) memory; longer ones are streamed from disk."""


@dataclass
class CoarseConfig:
    """Phase 1 (paper 3.2): 2D skeleton of the canonical frame, lift to ellipsoids, coarse shape fit."""

    target_vertices: Annotated[int, Bounds(100, 100_000)] = 1200
    """Vertex count of the initial mesh (the union of the lifted ellipsoids; its marching-cubes resolution is searched
    for it), and of every resampling unless motion.resample_vertices is set (>= 100)."""
    fov_degrees: Annotated[float, Bounds(0, 180, lo_open=True, hi_open=True)] = 45.0
    """Initial horizontal field of view of the full frame, used to initialise the focal length."""
    steps: Annotated[int, NONNEG] = 150
    """Optimisation steps of the coarse shape fit on the canonical frame."""
    lr: Annotated[float, NONNEG] = 0.01
    """Adam learning rate of the coarse shape fit (vertex offsets)."""
    w_sil: Annotated[float, NONNEG] = 1.0
    """Weight of the silhouette loss."""
    w_part: Annotated[float, NONNEG] = 0.5
    """Weight of the part-silhouette loss (parts = pixels nearest to each 2D skeleton edge)."""
    w_sym: Annotated[float, NONNEG] = 0.5
    """Weight of the symmetry loss (eq. 16)."""
    w_lap: Annotated[float, NONNEG] = 2.0
    """Weight of the Laplacian smoothing loss (eq. 17), on the change from the lifted shape (L(X - X_init)): the
    Laplacian of the shape itself is smallest for a flat mesh, and one view holds no depth."""
    canonical_frame: Annotated[int, NONNEG] | None = None
    """Index of the canonical frame (the one whose 2D skeleton is lifted); None = chosen automatically (the most
    horizontal skeleton with the most leg pairs). Set it when the chosen frame shows two legs overlapping."""


@dataclass
class MotionConfig:
    """Phase 2 (paper 3.3-3.4): warm-up with the mesh frozen, then shape, colour, camera and motion."""

    batch_frames: Annotated[int, COUNT] = 8
    """Frames per optimisation step."""
    warmup_steps: Annotated[int, NONNEG] = 200
    """Steps with the mesh frozen (camera and motion only)."""
    hypotheses: Annotated[int, COUNT] = 7
    """Root-rotation hypotheses tried at the start of the warm-up (1 = off): each assumes the camera turns
    about the object's vertical axis at a constant rate; a short fit of the root and camera alone scores each by
    its optical-flow term over every frame, and the best is kept."""
    hypothesis_max_rate: Annotated[float, Bounds(0, TURN_RATE.hi)] = 3.0
    """Largest turn rate of the hypotheses, degrees per frame (rates spread evenly in +-this, 0 included; <= 30)."""
    hypothesis_steps: Annotated[int, NONNEG] = 10
    """Warm-up steps spent scoring each hypothesis before the best three go on for 60 more and are ranked again (10
    and 30 chose the same rate, and the same three finalists, on the Fox, horse and DAVIS dog)."""
    resample_epochs: Annotated[int, NONNEG] = 1
    """Even resampling of the canonical mesh (paper B) every this many epochs of the joint phase; 0 = never."""
    resample_vertices: Annotated[int, NONNEG] = 0
    """Vertex count the resampled mesh aims at; 0 = the coarse mesh's count."""
    turn_rate: Annotated[float, TURN_RATE] | None = None
    """Known camera turn rate about the object's vertical axis, degrees per frame (-30 to 30): used as is, no
    hypotheses scored."""
    steps: Annotated[int, NONNEG] = 1200
    """Steps of the joint shape + motion + camera phase after the warm-up."""
    lr_motion: Annotated[float, NONNEG] = 0.01
    """Adam learning rate of root and bone rotations/translations."""
    lr_shape: Annotated[float, NONNEG] = 0.006
    """Learning rate of the canonical vertices in the joint phase: the step in ``u`` (``shape_smoothing``) of the
    vertex with the largest gradient."""
    shape_smoothing: Annotated[float, POSITIVE] = 4.0
    """``lam`` of the joint phase's shape step (``s3o_warp.motion.large_steps``, Nicolet et al. 2021): Adam steps on
    ``u = (I + lam L) x``, ``L`` the mesh's umbrella Laplacian, with one second moment for the whole mesh (the
    largest), so the vertices move by a smoothed step and a vertex with a small gradient moves little. Larger:
    smoother steps that follow thin parts less closely (16 lost 0.013 of the Fox's mask IoU on its last epoch)."""
    lr_color: Annotated[float, NONNEG] = 0.02
    """Adam learning rate of the vertex-colour logits."""
    lr_bones: Annotated[float, NONNEG] = 0.005
    """Adam learning rate of the bone Gaussians (centres, orientations, scales)."""
    lr_camera: Annotated[float, NONNEG] = 0.005
    """Adam learning rate of the focal length (log) and principal points."""
    principal_point: Literal["frame", "shared"] = "frame"
    """frame: a principal point per frame, in the crop (LASR's; it starts at each crop's centre, so the object sits
    on every frame's optical axis and its motion across the picture goes into the camera). shared: one principal
    point for the video in full-frame pixels, from the frame's centre, as a real camera has (not in the paper): the
    object's path across the picture is the root's, in camera space, and the exported camera's film offset is constant."""
    sigma: Annotated[float, POSITIVE] = 1.0
    """Soft-silhouette blur sigma in square crop pixels at the start of each phase."""
    sigma_final: Annotated[float, POSITIVE] = 0.1
    """Sigma at the end of each phase (geometric decay); SoftRas's aggregation grows the silhouette by about
    sqrt(sigma) pixels, which matters for legs a few pixels wide."""
    w_sil: Annotated[float, NONNEG] = 1.0
    """Weight of the silhouette loss (mean squared error of the soft silhouette)."""
    w_flow: Annotated[float, NONNEG] = 0.02
    """Weight of the optical-flow loss (confidence-weighted L2 of rendered vs observed flow, crop pixels)."""
    w_color: Annotated[float, NONNEG] = 0.2
    """Weight of the colour L1 loss."""
    w_cover: Annotated[float, NONNEG] = 0.2
    """Weight of the mask-coverage loss (``losses.coverage_loss``, not in the paper): every mask pixel the hard
    render leaves uncovered pulls its nearest projected vertex (hidden ones included) towards it, from any
    distance; it frees a far leg glued behind the near one after a crossing (horse PCK-T 83-85 -> 91-92)."""
    w_joint: Annotated[float, NONNEG] = 10.0
    """Weight of the joint-attachment loss (``losses.joint_attachment_loss``, not in the paper): each joint of
    the kinematic tree, moved by either of its two bones, lands in the same place (squared gap over the
    object's size squared), so a leg swings about its hip instead of sliding across the body (joints inside
    the body: quadruped 70 -> 85 %, Fox 77 -> 98 %, horse 78 -> 89 %); 0 = off."""
    synchronized: bool = False
    """Several videos are the same instants seen from several cameras (``s3o-fit A B --synchronized``): frame k of
    every video shares one body pose (bone motion); each video keeps its own camera and root. The videos must have
    as many frames each."""
    resolve_crossings: bool = True
    """After the warm-up, and once more after the first epoch of the joint phase, let each symmetric limb pair of
    the lift swing through its crossings instead of bouncing back (frames relabelled where the feet's paths cross
    in the image and that keeps their velocities, ``s3o_warp.motion.crossings``); on the synthetic walks it lifts PCK-T
    by 6-8 points (README, Benchmarks)."""
    w_rigid: Annotated[float, NONNEG] = 1.0
    """Weight of the dynamic rigidity loss (eq. 1-2, with eq. 1 corrected as docs/method.md says)."""
    rigidity: Literal["dynamic", "arap", "none"] = "dynamic"
    """Rigidity regulariser: dynamic (S3O), arap (the ablation) or none."""
    w_lap: Annotated[float, NONNEG] = 1.0
    """Weight of the Laplacian smoothing loss on the canonical mesh's change from a reference shape (the mesh at the
    joint phase's start and after each even resampling)."""
    w_sym: Annotated[float, NONNEG] = 0.2
    """Weight of the symmetry loss on the canonical mesh."""
    w_smooth: Annotated[float, NONNEG] = 0.1
    """Weight of the temporal smoothness of root and bone motion between consecutive frames."""
    w_bone_reg: Annotated[float, NONNEG] = 0.01
    """Weight of the penalty on bone translation magnitude (keeps bones rotating about their centres)."""
    log_every: Annotated[int, COUNT] = 10
    """Write a log.jsonl line every this many steps."""


@dataclass
class SkeletonConfig:
    """Skeleton learning, the M-step (paper 3.4, Algorithm 1), between epochs of the joint phase."""

    method: Literal["s3o", "virtual", "fixed"] = "s3o"
    """s3o (learned physical skeleton), virtual (LASR-like k-means bones, no skeleton learning) or fixed (coarse bones kept)."""
    epochs: Annotated[int, COUNT] = 6
    """Epochs of the joint phase; an M-step runs after every epoch but the last."""
    e1: Annotated[int, NONNEG] = 2
    """Epoch of the one skeleton upsampling; before it: shifting and growth, after it: merge and joints."""
    t_o: Annotated[float, Bounds(-1, 1)] = 0.95
    """Merge bones whose flow-derived motion directions have cosine > t_o in every frame (0.99 finer, 0.90 coarser)."""
    t_d: Annotated[float, POSITIVE] = 0.15
    """Create a joint in a bone whose length varies over frames by more than t_d of its median length (the paper's
    0.25 gives the legs fewer joints)."""
    t_r: Annotated[float, Bounds(0, 1, lo_open=True)] = 0.4
    """Joint position: mean of the vertices with both bones' weights >= t_r."""
    t_u: Annotated[float, NONNEG] = 0.4
    """Not in the paper: also create a joint in a bone whose part's two halves move relative to each other in a way
    the one rigid bone does not reproduce: when the unexplained share of the halves' relative image motion,
    |observed - fitted| / max(|observed|, |fitted|), median over the frames both halves are seen in, is above t_u
    (0 = the fit reproduces the halves' motion, 0.5 = a knee the fit bends half way, 1 and above = it does not
    follow at all). Eq. 6 cannot split an end bone (one joint: a leg's shin and paw), whose length runs from its
    joint to its far end, which both move with the bone, and sees a knee inside an inner bone only through its
    end-to-end length, which a 30-degree bend half way along shortens by 3 % (t_d is 15 %)."""
    max_bones: Annotated[int, COUNT] = 40
    """Never grow the skeleton beyond this many bones."""
    virtual_bones: Annotated[int, COUNT] = 25
    """Bone count of the virtual-bones baseline."""


@dataclass
class OutputConfig:
    """What the run directory receives."""

    checkpoint_every: Annotated[int, COUNT] = 200
    """Write a checkpoint every this many steps (and at every phase boundary)."""
    keep_checkpoints: Annotated[int, COUNT] = 2
    """How many checkpoints to keep."""
    render_video: bool = True
    """Write renders/ (overlay video, loss plot)."""
    branch_checkpoint: bool = True
    """Keep ``checkpoints/branch.pt``, the state just before the first M-step that reads skeleton.t_o (after epoch
    e1 + 1 of the joint phase), so ``--branch-from RUN`` fits the same sequence at another t_o from there."""


@dataclass
class Config:
    """Root of the configuration tree."""

    data: DataConfig = field(default_factory=DataConfig)
    coarse: CoarseConfig = field(default_factory=CoarseConfig)
    motion: MotionConfig = field(default_factory=MotionConfig)
    skeleton: SkeletonConfig = field(default_factory=SkeletonConfig)
    output: OutputConfig = field(default_factory=OutputConfig)
    seed: Annotated[int, Bounds(0, 2**32 - 1)] = 0
    """Seed for every random choice (numpy's seeds end at 2**32 - 1)."""
    repeatable: bool = True
    """On the CPU, run torch's deterministic algorithms during the fit so one seed gives the same run every time.
    Without them the backward of indexing (``index_put_`` accumulating) adds in thread order and a fit drifts
    apart from its own rerun within a hundred steps. On CUDA this does nothing: Warp's atomic adds already
    make runs differ in the last bits."""
    preset: str = "default"
    """Name of the preset applied on top of the defaults."""


# ---------------------------------------------------------------------------------------------------
# Presets, TOML round trip and overrides. Precedence: defaults < preset < --config TOML < flags.
# ---------------------------------------------------------------------------------------------------

PRESETS: dict[str, tuple[str, dict]] = {
    "default": ("The defaults: a good fit on the CPU in minutes at 192 px crops.", {"data.crop_size": 192}),
    "fast": (
        "A quick look: 96 px crops, fewer steps.",
        {"data.crop_size": 96, "coarse.steps": 80, "motion.warmup_steps": 100, "motion.steps": 300},
    ),
    "quality": (
        "Slower and finer: 256 px crops, more vertices and steps.",
        {
            "data.crop_size": 256,
            "coarse.target_vertices": 2500,
            "motion.warmup_steps": 400,
            "motion.steps": 2000,
            "motion.hypotheses": 9,
        },
    ),
    "smoke": (
        "A seconds-long smoke run for tests: 48 px crops, a few steps.",
        {
            "data.crop_size": 48,
            "coarse.target_vertices": 300,
            "coarse.steps": 10,
            "motion.warmup_steps": 5,
            "motion.steps": 10,
            "motion.batch_frames": 4,
            "motion.hypotheses": 1,
        },
    ),
}


def to_dict(cfg) -> dict:
    """Plain nested dict of every resolved value (for ``config.toml``); None values are dropped."""
    out = {}
    for f in dataclasses.fields(cfg):
        v = getattr(cfg, f.name)
        if dataclasses.is_dataclass(v):
            out[f.name] = to_dict(v)
        elif v is not None:
            out[f.name] = v
    return out


def _parts(hint):
    """(base type, choices or None, Bounds or None, whether None is allowed) of a field's type hint."""
    bounds = None
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        return (*_parts(args[0])[:3], len(args) < len(typing.get_args(hint)))
    if typing.get_origin(hint) is Annotated:
        hint, *extra = typing.get_args(hint)
        bounds = next((e for e in extra if isinstance(e, Bounds)), None)
    choices = None
    if typing.get_origin(hint) is Literal:
        choices = typing.get_args(hint)
        hint = type(choices[0])
    return hint, choices, bounds, False


def _coerce(key: str, current, value, hint):
    """``value`` converted to the field's type and checked against its choices and range; ConfigError names the key."""
    base, choices, bounds, optional = _parts(hint)
    if value is None or (optional and isinstance(value, str) and value.lower() == "none"):
        if optional:
            return None
        raise ConfigError(f"config key '{key}' cannot be none; give a value like {current!r}")
    try:
        if base is bool:
            if isinstance(value, str) and value.lower() in ("true", "1", "yes", "false", "0", "no"):
                value = value.lower() in ("true", "1", "yes")
            elif not isinstance(value, bool):
                raise ValueError
        elif base is int:
            if isinstance(value, bool) or (isinstance(value, float) and not value.is_integer()):
                raise ValueError
            value = int(value)
        elif base is float:
            if isinstance(value, bool):
                raise ValueError
            value = float(value)
        elif not isinstance(value, str):
            raise ValueError
    except (TypeError, ValueError):
        raise ConfigError(f"config key '{key}' must be {base.__name__}, got {value!r} ({type(value).__name__}); "
                          f"e.g. {key}={current!r}") from None
    if base is float and not math.isfinite(value):
        raise ConfigError(f"config key '{key}' must be a finite number, got {value!r}")
    if choices is not None and value not in choices:
        raise ConfigError(f"config key '{key}' must be one of {', '.join(map(repr, choices))}, got {value!r}")
    if bounds is not None and not bounds.holds(value):
        raise ConfigError(f"config key '{key}' must be {bounds}, got {value!r}")
    return value


def _settings(obj, prefix: str = ""):
    """(dotted key, owning dataclass, field name, type hint) of every setting under ``obj``."""
    hints = typing.get_type_hints(type(obj), include_extras=True)
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        if dataclasses.is_dataclass(v):
            yield from _settings(v, f"{prefix}{f.name}.")
        else:
            yield f"{prefix}{f.name}", obj, f.name, hints[f.name]


def set_value(cfg, key: str, value) -> None:
    """Set a dotted key such as ``motion.steps``; unknown keys, wrong types, choices and ranges raise ConfigError."""
    for k, owner, name, hint in _settings(cfg):
        if k == key:
            setattr(owner, name, _coerce(key, getattr(owner, name), value, hint))
            return
    section = key.rsplit(".", 1)[0] if "." in key else ""
    known = sorted({k.rsplit(".", 1)[0] for k, *_ in _settings(cfg) if "." in k})
    where = f" (no section '{section}'; sections: {', '.join(known)})" if section and section not in known else ""
    raise ConfigError(f"unknown config key '{key}'{where}; see config.toml of a run or s3o_warp/config.py for valid keys")


def check_fields(obj, prefix: str = ""):
    """Every setting's type, choice and range under ``obj`` (a section such as a DataConfig with ``prefix="data."``,
    or the whole tree); the first problem is one ConfigError line naming the key and what it may be."""
    for key, owner, name, hint in _settings(obj, prefix):
        _coerce(key, getattr(owner, name), getattr(owner, name), hint)
    return obj


def check(cfg: Config) -> Config:
    """:func:`check_fields` of the whole tree, then the combinations of settings. Called by :func:`make_config`
    and by the fit before any work, so a bad setting writes nothing."""
    check_fields(cfg)
    if cfg.preset not in PRESETS:
        raise ConfigError(f"config key 'preset' must be one of {', '.join(map(repr, PRESETS))}, got {cfg.preset!r}")
    if 0 < cfg.motion.resample_vertices < 20:
        raise ConfigError(f"config key 'motion.resample_vertices' must be 0 (the coarse mesh's count) or >= 20, got "
                          f"{cfg.motion.resample_vertices}")
    return cfg


def apply_dict(cfg, d: dict, prefix: str = "") -> None:
    """Apply a nested dict (from TOML) onto ``cfg``; unknown keys raise ConfigError naming them."""
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            apply_dict(cfg, v, key + ".")
        else:
            set_value(cfg, key, v)


def load_toml(path) -> dict:
    """Read a TOML file into a dict; a syntax error raises ConfigError naming the file."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"config file {path} does not exist; pass an existing TOML file to --config")
    try:
        return tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"config file {path} is not valid TOML ({e}); fix the line it names") from None


def make_config(preset: str = "default", toml_path=None, overrides: list[str] | None = None, seed: int | None = None) -> Config:
    """Defaults < preset < TOML file < ``key=value`` overrides (< an explicit seed), checked (:func:`check`)."""
    cfg = Config()
    if preset not in PRESETS:
        raise ConfigError(f"unknown preset '{preset}'; choose one of {', '.join(PRESETS)}")
    for k, v in PRESETS[preset][1].items():
        set_value(cfg, k, v)
    cfg.preset = preset
    if toml_path is not None:
        apply_dict(cfg, load_toml(toml_path))
    for item in overrides or []:
        if "=" not in item:
            raise ConfigError(f"override '{item}' must look like section.key=value, e.g. motion.steps=300")
        k, v = item.split("=", 1)
        set_value(cfg, k.strip(), v.strip())
    if seed is not None:
        set_value(cfg, "seed", seed)
    return check(cfg)


def to_toml(cfg) -> str:
    """Every resolved setting as TOML text (a run's ``config.toml``; :func:`make_config` reads it back)."""
    return tomli_w.dumps(to_dict(cfg))
