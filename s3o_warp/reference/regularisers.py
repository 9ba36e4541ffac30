"""Dense pure-torch twins of ``s3o_warp.kernels.regularisers`` and ``.visibility`` (same signatures).

Short and O(everything) on purpose; they define the right answers (any float dtype, any device).
"""

from __future__ import annotations

import torch

__all__ = [
    "dynamic_rigidity_loss_reference",
    "arap_loss_reference",
    "laplacian_loss_reference",
    "symmetry_loss_reference",
    "vertex_visibility_reference",
]

ENTROPY_EPS = 1e-8


def _stretch(verts: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """(T-1, E) | ||x_i^t - x_j^t|| - ||x_i^{t+1} - x_j^{t+1}|| |."""
    e = edges.long()
    lengths = torch.linalg.vector_norm(verts[:, e[:, 0]] - verts[:, e[:, 1]], dim=-1)  # (T, E)
    return (lengths[1:] - lengths[:-1]).abs()


def dynamic_rigidity_loss_reference(
    verts: torch.Tensor, edges: torch.Tensor, weights: torch.Tensor, lam: float = 0.1
) -> torch.Tensor:
    """Eq. 1-2 (corrected): mean over (t, edge) of R_ij |len^t - len^{t+1}|, R_ij = 1/((H_i+lam)(H_j+lam))."""
    h = -(weights * torch.log2(weights.clamp_min(ENTROPY_EPS))).sum(-1) + lam
    e = edges.long()
    rigidity = 1.0 / (h[e[:, 0]] * h[e[:, 1]])
    return (rigidity * _stretch(verts, edges)).mean()


def arap_loss_reference(verts: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """Mean over (t, edge) of |len^t - len^{t+1}| (DR with R = 1; non-squared, unlike LASR)."""
    return _stretch(verts, edges).mean()


def laplacian_loss_reference(verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Eq. 17: mean_i ||x_i - mean_{j in N_i} x_j||^2 with a dense (N, N) adjacency (isolated vertex: 0)."""
    n = verts.shape[0]
    f = faces.long()
    adj = torch.zeros((n, n), dtype=verts.dtype, device=verts.device)
    for a, b in ((0, 1), (1, 2), (2, 0)):
        adj[f[:, a], f[:, b]] = 1.0
        adj[f[:, b], f[:, a]] = 1.0
    adj.fill_diagonal_(0.0)
    deg = adj.sum(1, keepdim=True)
    mean = (adj @ verts) / deg.clamp_min(1.0)
    delta = torch.where(deg > 0, verts - mean, torch.zeros_like(verts))
    return (delta**2).sum() / n


def symmetry_loss_reference(verts: torch.Tensor, plane: tuple) -> torch.Tensor:
    """Eq. 16: mean_i min_j ||v_j - phi(v_i)||^2, phi = reflection across {x : n.x = offset}; argmin not differentiated."""
    normal, offset = plane
    normal = torch.as_tensor(normal, dtype=verts.dtype, device=verts.device)
    offset = torch.as_tensor(offset, dtype=verts.dtype, device=verts.device)
    n = normal / torch.linalg.vector_norm(normal)
    reflected = verts - 2.0 * ((verts @ n) - offset)[:, None] * n
    d2 = ((reflected[:, None, :] - verts[None, :, :]) ** 2).sum(-1)  # (N, N)
    idx = d2.detach().argmin(dim=1)
    return ((verts[idx] - reflected) ** 2).sum() / verts.shape[0]


def vertex_visibility_reference(
    verts: torch.Tensor, faces: torch.Tensor, eps: float = 1e-3, chunk: int = 256
) -> torch.Tensor:
    """(T, N) bool: vertex in front of the camera (z > 0) and no face hit on the segment origin -> (1 - eps) x.

    Brute-force Moller-Trumbore over all faces (chunked over vertices to bound memory).
    """
    t_count, n = verts.shape[0], verts.shape[1]
    f = faces.long()
    out = torch.zeros((t_count, n), dtype=torch.bool, device=verts.device)
    for t in range(t_count):
        v = verts[t]
        a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]  # (F, 3)
        e1, e2 = b - a, c - a
        for s in range(0, n, chunk):
            p = v[s : s + chunk]  # ray direction (unnormalised): origin + s * p, s in [0, 1]
            dist = torch.linalg.vector_norm(p, dim=-1)
            d = p / dist.clamp_min(1e-30)[:, None]  # unit direction, ray parameter = distance
            pvec = torch.cross(d[:, None, :].expand(-1, f.shape[0], -1), e2[None].expand(p.shape[0], -1, -1), dim=-1)
            det = (e1[None] * pvec).sum(-1)  # (P, F)
            inv = 1.0 / torch.where(det.abs() > 1e-12, det, torch.ones_like(det))
            tvec = -a[None]  # origin - a
            u = (tvec * pvec).sum(-1) * inv
            qvec = torch.cross(tvec.expand(p.shape[0], -1, -1), e1[None].expand(p.shape[0], -1, -1), dim=-1)
            w = (d[:, None, :] * qvec).sum(-1) * inv
            hit_t = (e2[None] * qvec).sum(-1) * inv
            hit = (det.abs() > 1e-12) & (u >= 0) & (w >= 0) & (u + w <= 1) & (hit_t > 0)
            hit &= hit_t < (1.0 - eps) * dist[:, None]
            out[t, s : s + chunk] = (p[:, 2] > 0) & ~hit.any(dim=1)
    return out
