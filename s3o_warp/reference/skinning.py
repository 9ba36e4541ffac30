"""Dense pure-torch twins of ``s3o_warp.kernels.skinning`` (same signatures): the right answers."""

from __future__ import annotations

import torch

__all__ = ["skinning_weights_reference", "blend_skinning_reference"]


def skinning_weights_reference(verts: torch.Tensor, centers: torch.Tensor, precisions: torch.Tensor) -> torch.Tensor:
    """``(N, B)`` ``softmax_b(-1/2 (x_n - c_b)^T Q_b (x_n - c_b))`` for verts (N,3), centers (B,3), precisions (B,3,3)."""
    d = verts[:, None, :] - centers[None, :, :]  # (N, B, 3)
    logits = -0.5 * torch.einsum("nbi,bij,nbj->nb", d, precisions, d)
    return torch.softmax(logits, dim=1)


def blend_skinning_reference(
    verts: torch.Tensor, weights: torch.Tensor, bone_rt: torch.Tensor, root_rt: torch.Tensor
) -> torch.Tensor:
    """``(T, N, 3)`` ``X_n^t = T_0^t (sum_b W[n,b] T_b^t) X_n^0`` (eq. 3) as an einsum; 3x4 ``[R|t]``: x -> R x + t."""
    blended = torch.einsum("nb,tbij->tnij", weights, bone_rt)  # (T, N, 3, 4)
    y = torch.einsum("tnij,nj->tni", blended[..., :3], verts) + blended[..., 3]
    return torch.einsum("tij,tnj->tni", root_rt[:, :, :3], y) + root_rt[:, None, :, 3]
