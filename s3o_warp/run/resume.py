"""Settings changed on ``--resume``: each one that differs from the checkpoint's saved settings is applied from the
checkpoint on (one log line lists them) or, where it cannot take effect from there, refused by name before any work.

A setting takes effect only while the fit still reads it. :data:`READ_UNTIL` gives, for every setting, the last
stage of a checkpoint (:data:`STAGES`) from which it is still read: the loop reads step counts, learning rates,
weights and the M-step's thresholds from the settings at every step, so a change applies from the checkpoint on
(a learning rate goes into its optimiser group, ``Fitter._apply_new_rates``; a new step count moves the phase's
end). The data, the coarse model and the seed are made before the first checkpoint, and a resumed fit takes
their result from it, so a change there is refused at every stage; so is ``motion.principal_point`` (the model's
parameters differ) and ``skeleton.method``.
"""

from __future__ import annotations

import logging
from pathlib import Path

from s3o_warp.config import Config, to_dict
from s3o_warp.errors import InputError
from s3o_warp.run.branch import _flat
from s3o_warp.run.checkpoint import check_version

log = logging.getLogger(__name__)

STAGES = ("coarse", "hypotheses", "warmup", "joint", "done")
"""Where a checkpoint stands: in the coarse phase; at the warm-up's start, before the camera hypotheses; in the
warm-up (its search included); in the joint phase; the fit done (only the run directory is written again)."""

_ALWAYS = {  # read again whenever the run directory is written: applied at every stage
    "data.fps", "data.resident_max_frames", "repeatable", "preset", "output.checkpoint_every",
    "output.keep_checkpoints", "output.render_video", "output.branch_checkpoint"}
_NEVER = {  # read before the first checkpoint (the data, the coarse model, the seed), or fixed by it
    "data.object_id", "data.crop_size", "data.crop_scale", "data.flow_preset", "data.mask_threshold",
    "data.largest_blob", "coarse.target_vertices", "coarse.fov_degrees", "coarse.canonical_frame",
    "motion.principal_point", "motion.synchronized", "skeleton.method", "skeleton.virtual_bones", "seed"}
_COARSE = {"coarse.steps", "coarse.lr", "coarse.w_sil", "coarse.w_part", "coarse.w_sym", "coarse.w_lap"}
_HYPOTHESES = {"motion.hypotheses", "motion.hypothesis_max_rate", "motion.hypothesis_steps", "motion.turn_rate"}
_WARMUP = {"motion.warmup_steps", "motion.resolve_crossings"}

READ_UNTIL: dict[str, str | None] = {
    **{k: "done" for k in _ALWAYS}, **{k: None for k in _NEVER}, **{k: "coarse" for k in _COARSE},
    **{k: "hypotheses" for k in _HYPOTHESES}, **{k: "warmup" for k in _WARMUP},
    **{k: "joint" for k in (
        "motion.batch_frames", "motion.resample_epochs", "motion.resample_vertices", "motion.steps",
        "motion.lr_motion", "motion.lr_shape", "motion.shape_smoothing", "motion.lr_color", "motion.lr_bones", "motion.lr_camera",
        "motion.sigma", "motion.sigma_final", "motion.w_sil", "motion.w_flow", "motion.w_color", "motion.w_cover",
        "motion.w_joint", "motion.w_rigid", "motion.rigidity", "motion.w_lap", "motion.w_sym", "motion.w_smooth",
        "motion.w_bone_reg", "motion.log_every", "skeleton.epochs", "skeleton.e1", "skeleton.t_o", "skeleton.t_d",
        "skeleton.t_r", "skeleton.t_u", "skeleton.max_bones")},
}
"""Every setting -> the last checkpoint stage (:data:`STAGES`) from which a change to it takes effect; None: none
(read before the first checkpoint). ``motion.shape_smoothing`` picks the joint phase's optimiser, made again on
resume and at every resampling; ``motion.resolve_crossings`` is read as it begins (and once more after its first epoch)."""

_READ = {None: "only before the first checkpoint", "coarse": "only in the coarse phase",
         "hypotheses": "only as the camera hypotheses begin", "warmup": "only until the joint phase begins",
         "joint": "only until the fit ends"}


def stage(state: dict) -> str:
    """The :data:`STAGES` entry of a checkpoint's ``state``."""
    phase = state.get("phase")
    if phase == "warmup":
        return "hypotheses" if state.get("step") == 0 and "hypotheses" not in state else "warmup"
    return phase if phase in STAGES else "done"


def apply_changed_settings(state: dict, cfg: Config, path: Path) -> list[str]:
    """Compare ``cfg`` with the settings saved in checkpoint ``state`` (read from ``path``) before any work: one
    InputError line names every changed setting that cannot take effect from there (with the ``--set`` flags that
    continue the checkpoint as it was), else one log line lists the changes, which apply; returns their keys."""
    check_version(state, f"checkpoint {path}", "start a fresh run (drop --resume or use another --out)")
    saved, ours = _flat(state.get("config", {})), _flat(to_dict(cfg))
    changed = sorted(k for k in set(saved) | set(ours) if saved.get(k) != ours.get(k))
    at = stage(state)
    where = ("the finished fit" if at == "done" else "the camera hypotheses" if "hypotheses" in state
             else f"{state.get('phase')} step {state.get('step')}")
    late = [k for k in changed
            if k not in READ_UNTIL or READ_UNTIL[k] is None or STAGES.index(at) > STAGES.index(READ_UNTIL[k])]
    if late:
        was = ", ".join(f"{k}={_shown(saved.get(k))}" for k in late)
        why = ", ".join(f"{k} is read {_READ.get(READ_UNTIL.get(k), 'by no fit of this version')}" for k in late)
        flags = " ".join(f"--set {k}={_shown(saved.get(k))}" for k in late)
        raise InputError(f"checkpoint {path} ({where}) was written with {was}, which this fit changes and which "
                         f"cannot take effect from there ({why}); add {flags} to continue it, or fit afresh "
                         "(without --resume, or into another --out)")
    if changed:
        log.info("resume from %s: applied from there on: %s", where,
                 ", ".join(f"{k} {_shown(saved.get(k))} -> {_shown(ours.get(k))}" for k in changed))
    return changed


def _shown(v) -> str:
    """A setting's value as ``--set`` takes it (none for None)."""
    return "none" if v is None else str(v).lower() if isinstance(v, bool) else str(v)
