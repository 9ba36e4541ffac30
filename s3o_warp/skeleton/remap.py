"""Applying a skeleton edit to the model (paper 3.4; Algorithm 1's "Update Skeleton"): :func:`remap_bones`
replaces the bones of an ``S3OModel`` in place, giving each new bone the blend of its source bones' per-frame
motion, re-pivoted about its new centre so that the posed mesh does not jump, and carries the Adam state over
with the same weights; :func:`apply_edit` does that for a :class:`s3o_warp.skeleton.edit.SkeletonEdit`, copying
the bones the edit kept bit for bit.
"""

from __future__ import annotations

import logging
from typing import Sequence

import torch

from s3o_warp.geometry import axis_angle_to_matrix
from s3o_warp.skeleton.edit import SkeletonEdit, precision_to_quat_scales
from s3o_warp.skeleton.measures import _np

log = logging.getLogger(__name__)


def _mix(old: torch.Tensor, dim: int, sources: Sequence) -> torch.Tensor:
    """new[..., j, ...] = sum_i w_ji old[..., i, ...] along ``dim``; single weight-1 sources are copied exactly."""
    cols = []
    for src in sources:
        if len(src) == 1 and src[0][1] == 1.0:
            cols.append(old.select(dim, src[0][0]))
        else:
            acc = sum(float(w) * old.select(dim, i) for i, w in src)
            cols.append(acc)
    return torch.stack(cols, dim)


def remap_bones(model, optimizer, sources, centers, quats, log_scales) -> None:
    """Replace the bone set of an ``S3OModel`` in place, carrying motion and Adam state over.

    New ``nn.Parameter`` objects replace ``bone_centers`` ``(B', 3)``, ``bone_quat`` ``(B', 4)`` (w, x, y,
    z), ``bone_log_scales`` ``(B', 3)``, ``bone_aa`` ``(T, B', 3)`` and ``bone_t`` ``(T, B', 3)``.

    Motion: new bone j with sources ``[(i, w_i)]`` gets ``aa_j = sum_i w_i aa_i`` and the translation
    that reproduces the blend of its sources' affine maps about the NEW centre. The model poses bone b
    as ``A_b = [R_b | c_b + t_b - R_b c_b]`` (rotation about its own centre), so with ``R_j = R(aa_j)``::

        t_j = sum_i w_i t_i + sum_i w_i (I - R_i)(c_i - c_j) + (sum_i w_i R_i - R_j) c_j

    For a single source (a split, a shifted or an unchanged bone) ``R_j = R_i`` and ``A_j = A_i``
    exactly: the posed mesh changes only through the skinning weights of the new Gaussians.

    Optimiser: every state tensor of the old parameters that has the parameter's shape (Adam's
    ``exp_avg``, ``exp_avg_sq``, ...) is mapped with the same weights along the bone axis (copied bit
    for bit for single weight-1 sources); other entries (``step``) are copied. The optimiser's
    param_groups then point at the new parameters. Parameters the optimiser does not hold are just
    replaced. ``optimizer`` may be None.

    Args:
        model: the ``S3OModel``.
        optimizer: a ``torch.optim`` optimiser over (some of) the model's parameters, or None.
        sources: one list of ``(old bone, weight)`` per new bone (weights summing to 1).
        centers: ``(B', 3)`` new Gaussian centres. quats: ``(B', 4)`` (w, x, y, z). log_scales: ``(B', 3)``.

    Raises:
        ValueError: mismatched lengths, an out-of-range source index or weights not summing to 1.
    """
    name = "remap_bones"
    B_old = model.num_bones
    Bn = len(sources)
    ref = model.bone_centers
    dt = dict(dtype=ref.dtype, device=ref.device)

    def as_t(x) -> torch.Tensor:
        return x.detach().to(**dt) if isinstance(x, torch.Tensor) else torch.as_tensor(_np(x), **dt)

    cn, qn, sn = as_t(centers), as_t(quats), as_t(log_scales)
    for arg, t, k in (("centers", cn, 3), ("quats", qn, 4), ("log_scales", sn, 3)):
        if tuple(t.shape) != (Bn, k):
            raise ValueError(f"{name}(): {arg} must have shape ({Bn}, {k}) for {Bn} sources, got {tuple(t.shape)}")
    if Bn == 0:
        raise ValueError(f"{name}(): need at least one new bone")
    for j, src in enumerate(sources):
        if not src or any(not 0 <= int(i) < B_old for i, _ in src):
            raise ValueError(f"{name}(): sources[{j}] must list old bones in [0, {B_old}), got {src}")
        if abs(sum(float(w) for _, w in src) - 1.0) > 1e-6:
            raise ValueError(f"{name}(): sources[{j}] weights must sum to 1, got {src}")
    sources = [[(int(i), float(w)) for i, w in src] for src in sources]
    with torch.no_grad():
        c_old = model.bone_centers.detach()
        aa_old, t_old = model.bone_aa.detach(), model.bone_t.detach()
        aa_new = _mix(aa_old, 1, sources)
        R_old = axis_angle_to_matrix(aa_old)  # (T, B, 3, 3)
        R_new = axis_angle_to_matrix(aa_new)
        t_cols = []
        for j, src in enumerate(sources):
            if len(src) == 1 and src[0][1] == 1.0:
                i = src[0][0]
                dc = c_old[i] - cn[j]
                t_cols.append(t_old[:, i] + dc - (R_old[:, i] @ dc[:, None])[..., 0] if bool((dc != 0).any())
                              else t_old[:, i].clone())
                continue
            acc = torch.zeros_like(t_old[:, 0])
            Rmix = torch.zeros_like(R_old[:, 0])
            for i, w in src:
                dc = c_old[i] - cn[j]
                acc = acc + w * (t_old[:, i] + dc - (R_old[:, i] @ dc[:, None])[..., 0])
                Rmix = Rmix + w * R_old[:, i]
            acc = acc + ((Rmix - R_new[:, j]) @ cn[j][:, None])[..., 0]
            t_cols.append(acc)
        t_new = torch.stack(t_cols, 1)
    new_vals = {
        "bone_centers": (cn.clone(), 0),
        "bone_quat": (qn.clone(), 0),
        "bone_log_scales": (sn.clone(), 0),
        "bone_aa": (aa_new, 1),
        "bone_t": (t_new, 1),
    }
    for attr, (val, dim) in new_vals.items():
        old = getattr(model, attr)
        new = torch.nn.Parameter(val.contiguous().clone(), requires_grad=old.requires_grad)
        if optimizer is not None:
            _move_state(optimizer, old, new, dim, sources, B_old)
        setattr(model, attr, new)
    log.info("remap_bones: %d -> %d bones", B_old, Bn)


def _move_state(optimizer, old: torch.nn.Parameter, new: torch.nn.Parameter, dim: int, sources, B_old: int) -> None:
    held = False
    for g in optimizer.param_groups:
        for k, p in enumerate(g["params"]):
            if p is old:
                g["params"][k] = new
                held = True
    if not held:
        return
    st = optimizer.state.pop(old, None)
    if not st:
        return
    out = {}
    for key, v in st.items():
        if isinstance(v, torch.Tensor) and v.shape == old.shape and v.dim() > dim and v.shape[dim] == B_old:
            out[key] = _mix(v, dim, sources).contiguous().clone()
        else:
            out[key] = v.clone() if isinstance(v, torch.Tensor) else v
    optimizer.state[new] = out


def apply_edit(model, optimizer, edit: SkeletonEdit) -> None:
    """:func:`remap_bones` with an edit's bones; kept bones reuse their exact old quaternion and log-scales."""
    dt = dict(dtype=model.bone_centers.dtype, device=model.bone_centers.device)
    q, s = precision_to_quat_scales(edit.precisions)
    centers = torch.as_tensor(edit.centers, **dt)
    quats, scales = torch.as_tensor(q, **dt), torch.as_tensor(s, **dt)
    for j, src in enumerate(edit.sources):
        if edit.kept[j]:  # bit-exact copies, so an unchanged bone's skinning and optimiser step are unchanged
            i = src[0][0]
            centers[j] = model.bone_centers.detach()[i]
            quats[j] = model.bone_quat.detach()[i]
            scales[j] = model.bone_log_scales.detach()[i]
    remap_bones(model, optimizer, edit.sources, centers, quats, scales)


__all__ = [
    "apply_edit",
    "remap_bones",
]
