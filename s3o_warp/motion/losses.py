"""Reconstruction losses of the fit (paper appendix D), on crops, built from the differentiable ops.

Each function returns a scalar tensor; weights are applied by the caller from the config. Shapes:
t frames of a batch window, S the crop side, N vertices.
"""

from __future__ import annotations

import torch

from s3o_warp.geometry import project
from s3o_warp.ops import nearest_point, set_index_bounds


def silhouette_loss(sil: torch.Tensor, mask: torch.Tensor, frame_weight: torch.Tensor | None = None) -> torch.Tensor:
    """Eq. 10 as a mean squared error between the soft silhouette ``(t,S,S)`` and the mask ``(t,S,S)``.

    ``frame_weight`` ``(t,)`` scales each frame (frames where the object leaves the image count less).
    """
    per_frame = ((sil - mask) ** 2).flatten(1).mean(1)
    if frame_weight is None:
        return per_frame.mean()
    return (per_frame * frame_weight).sum() / frame_weight.sum().clamp_min(1e-6)


def coverage_loss(
    proj: torch.Tensor, uncovered: torch.Tensor, max_pixels: int = 0, generator: torch.Generator | None = None
) -> torch.Tensor:
    """Mask coverage: each mask pixel the render leaves uncovered pulls its nearest projected vertex to it.

    ``proj`` ``(t,N,2)`` projected vertices in crop pixels (all of them, hidden ones included: a leg hidden
    behind its pair is what an uncovered patch of mask most often wants), ``uncovered`` ``(t,S,S)`` bool.
    Returns ``sum_p |p - proj[nearest(p)]| / (t S^2)`` in crop pixels per crop pixel: unlike the soft
    silhouette, whose gradient reaches only about sigma pixels past the outline, this one pulls from any
    distance. ``max_pixels`` > 0 keeps a random sample of at most that many pixels per frame on average
    (rescaled, so the expected value is unchanged).
    """
    t, S = uncovered.shape[0], uncovered.shape[-1]
    idx = uncovered.nonzero()  # (Q, 3): frame, row, column
    total = idx.shape[0]
    if total == 0:
        return proj.sum() * 0
    if max_pixels > 0 and total > max_pixels * t:
        keep = torch.randperm(total, device=idx.device, generator=generator)[: max_pixels * t]
        idx = idx[keep]
    q = idx[:, [2, 1]].to(proj.dtype)
    frame = idx[:, 0]
    set_index_bounds(frame, 0, t - 1)  # rows of nonzero() over t frames: nearest_point's check reads nothing back
    nearest = nearest_point(q.float(), frame, proj.detach().float())
    d = (proj[frame, nearest] - q).norm(dim=-1)
    return d.sum() * (total / idx.shape[0]) / (t * S * S)


def joint_attachment_loss(bone_rt: torch.Tensor, joints: torch.Tensor, positions: torch.Tensor, scale: float) -> torch.Tensor:
    """Bones stay joined: each joint, carried by both of its bones, lands in one place.

    ``bone_rt`` ``(t, B, 3, 4)`` per-frame bone transforms (object frame), ``joints`` ``(J, 2)`` long bone
    pairs, ``positions`` ``(J, 3)`` rest joint positions. Returns the mean over frames and joints of
    ``|T_a j - T_b j|^2 / scale^2`` (``scale``: the object's size, so the weight does not depend on units).
    Without it each bone's free translation lets a leg slide across the body as a rigid piece instead of
    swinging about its hip.
    """
    if joints.numel() == 0:
        return bone_rt.sum() * 0
    jh = torch.cat([positions.to(bone_rt), torch.ones_like(positions[:, :1]).to(bone_rt)], -1)  # (J, 4)
    d = bone_rt[:, joints[:, 0]] - bone_rt[:, joints[:, 1]]  # (t, J, 3, 4)
    gap = torch.einsum("tjik,jk->tji", d, jh)
    return (gap**2).sum(-1).mean() / (scale * scale)


def soft_iou(sil: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Hard IoU of ``sil > 0.5`` against ``mask > 0.5`` per frame ``(t,)`` (for progress reporting)."""
    a = sil > 0.5
    b = mask > 0.5
    inter = (a & b).flatten(1).sum(1).float()
    union = (a | b).flatten(1).sum(1).float().clamp_min(1)
    return inter / union


def vertex_flow_crop(verts_cam: torch.Tensor, K_crop: torch.Tensor) -> torch.Tensor:
    """Projected displacement of each vertex from frame t to t+1 in crop pixels ``(t-1, N, 2)``.

    Matches the observed flow's meaning (``s3o_warp.data.flow``): crop-t pixel x is seen at crop-(t+1)
    pixel x + flow, so the displacement is ``proj_{t+1}(X^{t+1}) - proj_t(X^t)``, each frame with its own
    crop intrinsics.
    """
    p = project(verts_cam, K_crop)
    return p[1:] - p[:-1]


def flow_loss(rendered: torch.Tensor, observed: torch.Tensor, conf: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Eq. 11: confidence-weighted L2 norm of the flow error over ``valid`` pixels ``(t,S,S)``."""
    err = (rendered - observed).norm(dim=-1)
    w = conf * valid
    return (w * err).sum() / w.sum().clamp_min(1.0)


def color_loss(rendered: torch.Tensor, image: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Eq. 12: L1 between rendered colour ``(t,S,S,3)`` and the image over ``valid`` pixels."""
    err = (rendered - image).abs().sum(-1)
    return (err * valid).sum() / valid.sum().clamp_min(1.0) / 3.0


def temporal_smoothness(x: torch.Tensor, pairs: torch.Tensor | None = None) -> torch.Tensor:
    """Mean squared first difference over frames of a per-frame parameter ``(T, ...)`` (velocity: consecutive
    frames differing); ``pairs`` ``(T - 1,)`` bool keeps only the consecutive frames of one video."""
    if x.shape[0] < 2:
        return x.sum() * 0
    d = (x[1:] - x[:-1]) ** 2
    return d.mean() if pairs is None else d[pairs].mean()
