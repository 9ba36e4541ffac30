"""One configuration dataclass tree for every hyper-parameter, with its default.

Precedence: defaults < preset < ``--config`` TOML < command-line flags. Every field has a one-line
docstring (the comment under it) that becomes its ``--help`` text.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class DataConfig:
    """How a sequence is read, cropped and given optical flow (``s3o_warp.video``)."""

    object_id: int | None = None
    """For palette (multi-object) masks such as DAVIS-2017: the object's palette index; None = any non-zero / > 127."""
    crop_size: int = 256
    """Working resolution: each frame's square crop is resized to crop_size x crop_size pixels."""
    crop_scale: float = 1.2
    """Side of the square crop as a multiple of the mask bounding box's longer side."""
    flow_preset: str = "medium"
    """OpenCV DIS optical-flow preset: ultrafast, fast or medium."""
    fps: float = 30.0
    """Frame rate of image-folder sequences (DAVIS included); a video file's own frame rate wins when it has one."""
    mask_threshold: int = 127
    """Grey-level and RGB masks: foreground = value > mask_threshold (0-255 scale)."""
    largest_blob: bool = True
    """Masks with several disconnected blobs: keep the largest and the fragments near it (a warning names the
    frames); false keeps all."""
    resident_max_frames: int = 400
    """Sequences up to this many frames keep crops and flow in (device) memory; longer ones are streamed from disk."""


@dataclass
class CoarseConfig:
    """Phase 1 (paper 3.2): 2D skeleton of the canonical frame, lift to ellipsoids, coarse shape fit."""

    target_vertices: int = 1200
    """Vertex count of the initial mesh (the union of the lifted ellipsoids; its marching-cubes resolution is searched
    for it), and of every resampling unless motion.resample_vertices is set (>= 100)."""
    fov_degrees: float = 45.0
    """Initial horizontal field of view of the full frame, used to initialise the focal length."""
    steps: int = 150
    """Optimisation steps of the coarse shape fit on the canonical frame."""
    lr: float = 0.01
    """Adam learning rate of the coarse shape fit (vertex offsets)."""
    w_sil: float = 1.0
    """Weight of the silhouette loss."""
    w_part: float = 0.5
    """Weight of the part-silhouette loss (parts = pixels nearest to each 2D skeleton edge)."""
    w_sym: float = 0.5
    """Weight of the symmetry loss (eq. 16)."""
    w_lap: float = 2.0
    """Weight of the Laplacian smoothing loss (eq. 17), on the change from the lifted shape (L(X - X_init)): the
    Laplacian of the shape itself is smallest for a flat mesh, and one view holds no depth."""
    canonical_frame: int | None = None
    """Index of the canonical frame (the one whose 2D skeleton is lifted); None = chosen automatically (the most
    horizontal skeleton with the most leg pairs). Set it when the chosen frame shows two legs overlapping."""


@dataclass
class MotionConfig:
    """Phase 2 (paper 3.3-3.4): warm-up with the mesh frozen, then shape, colour, camera and motion."""

    batch_frames: int = 8
    """Frames per optimisation step."""
    warmup_steps: int = 200
    """Steps with the mesh frozen (camera and motion only)."""
    hypotheses: int = 7
    """Root-rotation hypotheses tried at the start of the warm-up (1 = off): each assumes the camera turns
    about the object's vertical axis at a constant rate; a short fit of the root and camera alone scores each by
    its optical-flow term over every frame, and the best is kept."""
    hypothesis_max_rate: float = 3.0
    """Largest turn rate of the hypotheses, degrees per frame (rates spread evenly in +-this, 0 included)."""
    hypothesis_steps: int = 30
    """Warm-up steps spent scoring each hypothesis."""
    resample_epochs: int = 1
    """Even resampling of the canonical mesh (paper B) every this many epochs of the joint phase; 0 = never."""
    resample_vertices: int = 0
    """Vertex count the resampled mesh aims at; 0 = the coarse mesh's count."""
    turn_rate: float | None = None
    """Known camera turn rate about the object's vertical axis, degrees per frame: used as is, no hypotheses scored."""
    steps: int = 1200
    """Steps of the joint shape + motion + camera phase after the warm-up."""
    lr_motion: float = 0.01
    """Adam learning rate of root and bone rotations/translations."""
    lr_shape: float = 0.002
    """Adam learning rate of the canonical vertices."""
    lr_color: float = 0.02
    """Adam learning rate of the vertex-colour logits."""
    lr_bones: float = 0.005
    """Adam learning rate of the bone Gaussians (centres, orientations, scales)."""
    lr_camera: float = 0.005
    """Adam learning rate of the focal length (log) and principal points."""
    principal_point: str = "frame"
    """frame: a principal point per frame, in the crop (LASR's; it starts at each crop's centre, so the object sits
    on every frame's optical axis and its motion across the picture goes into the camera). shared: one principal
    point for the video in full-frame pixels, from the frame's centre, as a real camera has (not in the paper): the
    object's path across the picture is the root's, in camera space, and the exported camera's film offset is constant."""
    sigma: float = 1.0
    """Soft-silhouette blur sigma in square crop pixels at the start of each phase."""
    sigma_final: float = 0.1
    """Sigma at the end of each phase (geometric decay); SoftRas's aggregation grows the silhouette by about
    sqrt(sigma) pixels, which matters for legs a few pixels wide."""
    w_sil: float = 1.0
    """Weight of the silhouette loss (mean squared error of the soft silhouette)."""
    w_flow: float = 0.02
    """Weight of the optical-flow loss (confidence-weighted L2 of rendered vs observed flow, crop pixels)."""
    w_color: float = 0.2
    """Weight of the colour L1 loss."""
    w_cover: float = 0.2
    """Weight of the mask-coverage loss (``losses.coverage_loss``, not in the paper): every mask pixel the hard
    render leaves uncovered pulls its nearest projected vertex (hidden ones included) towards it, from any
    distance; it frees a far leg glued behind the near one after a crossing (horse PCK-T 83-85 -> 91-92)."""
    w_joint: float = 10.0
    """Weight of the joint-attachment loss (``losses.joint_attachment_loss``, not in the paper): each joint of
    the kinematic tree, moved by either of its two bones, lands in the same place (squared gap over the
    object's size squared), so a leg swings about its hip instead of sliding across the body (joints inside
    the body: quadruped 70 -> 85 %, Fox 77 -> 98 %, horse 78 -> 89 %); 0 = off."""
    resolve_crossings: bool = True
    """After the warm-up, and once more after the first epoch of the joint phase, let each symmetric limb pair of
    the lift swing through its crossings instead of bouncing back (frames relabelled where the feet's paths cross
    in the image and that keeps their velocities, ``s3o_warp.crossings``); on the synthetic walks it lifts PCK-T
    by 6-8 points (README, Benchmarks)."""
    w_rigid: float = 1.0
    """Weight of the dynamic rigidity loss (eq. 1-2, corrected as in DESIGN.md)."""
    rigidity: str = "dynamic"
    """Rigidity regulariser: dynamic (S3O), arap (the ablation) or none."""
    w_lap: float = 1.0
    """Weight of the Laplacian smoothing loss on the canonical mesh's change from a reference shape (the mesh at the
    joint phase's start and after each even resampling)."""
    w_sym: float = 0.2
    """Weight of the symmetry loss on the canonical mesh."""
    w_smooth: float = 0.1
    """Weight of the temporal smoothness of root and bone motion between consecutive frames."""
    w_bone_reg: float = 0.01
    """Weight of the penalty on bone translation magnitude (keeps bones rotating about their centres)."""
    log_every: int = 10
    """Write a log.jsonl line every this many steps."""


@dataclass
class SkeletonConfig:
    """Skeleton learning, the M-step (paper 3.4, Algorithm 1), between epochs of the joint phase."""

    method: str = "s3o"
    """s3o (learned physical skeleton), virtual (LASR-like k-means bones, no skeleton learning) or fixed (coarse bones kept)."""
    epochs: int = 6
    """Epochs of the joint phase; an M-step runs after every epoch but the last."""
    e1: int = 2
    """Epoch of the one skeleton upsampling; before it: shifting and growth, after it: merge and joints."""
    t_o: float = 0.95
    """Merge bones whose flow-derived motion directions have cosine > t_o in every frame (0.99 finer, 0.90 coarser)."""
    t_d: float = 0.15
    """Create a joint in a bone whose length varies over frames by more than t_d of its median length (the paper's
    0.25 gives the legs fewer joints)."""
    t_r: float = 0.4
    """Joint position: mean of the vertices with both bones' weights >= t_r."""
    t_u: float = 0.4
    """Not in the paper: also create a joint in a bone whose part's two halves move relative to each other in a way
    the one rigid bone does not reproduce: when the unexplained share of the halves' relative image motion,
    |observed - fitted| / max(|observed|, |fitted|), median over the frames both halves are seen in, is above t_u
    (0 = the fit reproduces the halves' motion, 0.5 = a knee the fit bends half way, 1 and above = it does not
    follow at all). Eq. 6 cannot split an end bone (one joint: a leg's shin and paw), whose length runs from its
    joint to its far end, which both move with the bone, and sees a knee inside an inner bone only through its
    end-to-end length, which a 30-degree bend half way along shortens by 3 % (t_d is 15 %)."""
    max_bones: int = 40
    """Never grow the skeleton beyond this many bones."""
    virtual_bones: int = 25
    """Bone count of the virtual-bones baseline."""


@dataclass
class OutputConfig:
    """What the run directory receives."""

    checkpoint_every: int = 200
    """Write a checkpoint every this many steps (and at every phase boundary)."""
    keep_checkpoints: int = 2
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
    seed: int = 0
    """Seed for every random choice."""
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


def _is_dataclass_field(obj, name: str) -> bool:
    import dataclasses

    return dataclasses.is_dataclass(obj) and name in {f.name for f in dataclasses.fields(obj)}


def to_dict(cfg) -> dict:
    """Plain nested dict of every resolved value (for ``config.toml``); None values are dropped."""
    import dataclasses

    out = {}
    for f in dataclasses.fields(cfg):
        v = getattr(cfg, f.name)
        if dataclasses.is_dataclass(v):
            out[f.name] = to_dict(v)
        elif v is not None:
            out[f.name] = v
    return out


def _coerce(key: str, current, value, annotation: str):
    """Convert ``value`` to the type of the field ``key`` or raise ConfigError naming the key."""
    from s3o_warp.errors import ConfigError

    ann = str(annotation)
    want_none_ok = "None" in ann
    if value is None or (isinstance(value, str) and value.lower() == "none" and want_none_ok):
        if want_none_ok:
            return None
        raise ConfigError(f"config key '{key}' cannot be none; give a value like {current!r}")
    base = ann.replace("| None", "").replace("None |", "").strip()
    try:
        if base == "bool":
            if isinstance(value, bool):
                return value
            if isinstance(value, str) and value.lower() in ("true", "1", "yes", "false", "0", "no"):
                return value.lower() in ("true", "1", "yes")
            raise ValueError
        if base == "int":
            if isinstance(value, bool) or (isinstance(value, float) and not value.is_integer()):
                raise ValueError
            return int(value)
        if base == "float":
            if isinstance(value, bool):
                raise ValueError
            return float(value)
        if base == "str":
            if not isinstance(value, str):
                raise ValueError
            return value
    except (TypeError, ValueError):
        raise ConfigError(
            f"config key '{key}' must be {base}, got {value!r} ({type(value).__name__}); e.g. {key}={current!r}"
        ) from None
    return value


def set_value(cfg, key: str, value) -> None:
    """Set a dotted key such as ``motion.steps``; unknown keys and wrong types raise ConfigError."""
    import dataclasses

    from s3o_warp.errors import ConfigError

    parts = key.split(".")
    obj = cfg
    for p in parts[:-1]:
        if not _is_dataclass_field(obj, p) or not dataclasses.is_dataclass(getattr(obj, p)):
            raise ConfigError(f"unknown config key '{key}' (no section '{p}'); see config.toml of a run for valid keys")
        obj = getattr(obj, p)
    name = parts[-1]
    if not _is_dataclass_field(obj, name) or dataclasses.is_dataclass(getattr(obj, name)):
        raise ConfigError(f"unknown config key '{key}'; see config.toml of a run for valid keys")
    ann = {f.name: f.type for f in dataclasses.fields(obj)}[name]
    setattr(obj, name, _coerce(key, getattr(obj, name), value, ann))


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
    import tomllib
    from pathlib import Path

    from s3o_warp.errors import ConfigError

    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"config file {path} does not exist; pass an existing TOML file to --config")
    try:
        return tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"config file {path} is not valid TOML ({e}); fix the line it names") from None


def make_config(preset: str = "default", toml_path=None, overrides: list[str] | None = None, seed: int | None = None) -> Config:
    """Defaults < preset < TOML file < ``key=value`` overrides (< an explicit seed)."""
    from s3o_warp.errors import ConfigError

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
        cfg.seed = int(seed)
    return cfg


def save_toml(cfg, path) -> None:
    """Write every resolved setting to ``path`` atomically (temp name + rename)."""
    import os
    from pathlib import Path

    import tomli_w

    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(tomli_w.dumps(to_dict(cfg)).encode())
    os.replace(tmp, path)
