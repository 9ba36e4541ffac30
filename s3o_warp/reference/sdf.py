"""Dense torch twin of ``s3o_warp.kernels.sdf.closest_point``: every point against every face.

O(points x faces) on purpose (float64 by default, any device); tests use it on small meshes.
"""

from __future__ import annotations

import math

import torch

__all__ = ["closest_on_faces_naive", "closest_point_naive", "ray_hit_naive", "winding_number_naive"]


def winding_number_naive(verts: torch.Tensor, faces: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """(M,) generalised winding number: sum over faces of the solid angle at the point / 4 pi.

    Solid angle of triangle (a, b, c) seen from the origin (Van Oosterom and Strackee 1983):
    ``tan(omega / 2) = a . (b x c) / (|a||b||c| + (a.b)|c| + (a.c)|b| + (b.c)|a|)``. It is 1 inside
    a closed mesh wound counter-clockwise seen from outside, 0 outside.
    """
    tri = verts[faces.long()]  # (F, 3, 3)
    r = tri[None] - points[:, None, None, :]  # (M, F, 3, 3)
    a, b, c = r[..., 0, :], r[..., 1, :], r[..., 2, :]
    la, lb, lc = (torch.linalg.vector_norm(x, dim=-1) for x in (a, b, c))
    num = (a * torch.linalg.cross(b, c)).sum(-1)
    den = la * lb * lc + (a * b).sum(-1) * lc + (a * c).sum(-1) * lb + (b * c).sum(-1) * la
    return (2.0 * torch.atan2(num, den)).sum(-1) / (4.0 * math.pi)


def closest_on_faces_naive(tri: torch.Tensor, p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Squared distance (M, F) and barycentrics (M, F, 3) of the closest point of each face (F, 3, 3) to each point (M, 3)."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]  # (F, 3)
    n = torch.linalg.cross(b - a, c - a)
    nn = (n * n).sum(-1).clamp_min(torch.finfo(tri.dtype).tiny)
    q = p[:, None, :]  # (M, 1, 3)
    # projection onto the plane and its barycentrics (signed sub-areas / total area)
    proj = q - ((q - a) * n).sum(-1, keepdim=True) / nn[:, None] * n
    wa = (torch.linalg.cross((c - b).expand_as(proj), proj - b) * n).sum(-1) / nn
    wb = (torch.linalg.cross((a - c).expand_as(proj), proj - c) * n).sum(-1) / nn
    wc = 1.0 - wa - wb
    inside = (wa >= 0) & (wb >= 0) & (wc >= 0)
    best_d2 = torch.where(inside, ((q - proj) ** 2).sum(-1), torch.full_like(wa, math.inf))
    best_w = torch.stack([wa, wb, wc], -1)
    # the three edges (u, v) with weights on vertex slots (i, j)
    for u, v, i, j in ((a, b, 0, 1), (b, c, 1, 2), (c, a, 2, 0)):
        e = v - u
        t = (((q - u) * e).sum(-1) / (e * e).sum(-1).clamp_min(torch.finfo(tri.dtype).tiny)).clamp(0.0, 1.0)
        d2 = ((q - (u + t[..., None] * e)) ** 2).sum(-1)
        w = torch.zeros_like(best_w)
        w[..., i] = 1.0 - t
        w[..., j] = t
        better = d2 < best_d2
        best_d2 = torch.where(better, d2, best_d2)
        best_w = torch.where(better[..., None], w, best_w)
    return best_d2, best_w


def closest_point_naive(
    verts: torch.Tensor, faces: torch.Tensor, points: torch.Tensor, chunk: int = 256
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Brute-force signed distance, closest face and barycentrics (see ``kernels.sdf.closest_point``).

    Args:
        verts: ``(N, 3)`` float vertices (computed in their dtype; pass float64 for a reference).
        faces: ``(F, 3)`` integer vertex indices.
        points: ``(M, 3)`` float query points.
        chunk: points per batch (memory is chunk x F x 9 floats).

    Returns:
        ``(distance (M,), face (M,) int64, bary (M, 3))`` in verts' dtype; distance < 0 where the
        winding number exceeds 1/2. Ties between faces go to the lowest face index.
    """
    points = points.to(verts.dtype)
    tri = verts[faces.long()]
    dist, face, bary = [], [], []
    for s in range(0, points.shape[0], chunk):
        p = points[s : s + chunk]
        d2, w = closest_on_faces_naive(tri, p)
        f = d2.argmin(dim=1)
        d = d2.gather(1, f[:, None])[:, 0].sqrt()
        inside = winding_number_naive(verts, faces, p) > 0.5
        dist.append(torch.where(inside, -d, d))
        face.append(f)
        bary.append(w[torch.arange(p.shape[0], device=p.device), f])
    if not dist:
        return verts.new_zeros(0), torch.zeros(0, dtype=torch.int64, device=verts.device), verts.new_zeros(0, 3)
    return torch.cat(dist), torch.cat(face), torch.cat(bary)


def ray_hit_naive(verts: torch.Tensor, faces: torch.Tensor, origins: torch.Tensor, dirs: torch.Tensor,
                  max_t: float = 1.0e18) -> tuple[torch.Tensor, torch.Tensor]:
    """Brute-force twin of ``kernels.sdf.ray_hit``: Moller-Trumbore against every face, nearest t >= 0.

    Returns ``(t (M,), face (M,) int64)`` in verts' dtype; ``max_t`` and -1 on a miss.
    """
    d = dirs.to(verts.dtype)
    d = d / torch.linalg.vector_norm(d, dim=1, keepdim=True)
    o = origins.to(verts.dtype)
    tri = verts[faces.long()]  # (F, 3, 3)
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]  # (F, 3)
    pvec = torch.linalg.cross(d[:, None, :].expand(-1, len(tri), -1), e2[None].expand(len(d), -1, -1))  # (M, F, 3)
    det = (e1[None] * pvec).sum(-1)
    ok = det.abs() > 1e-12
    inv = 1.0 / torch.where(ok, det, torch.ones_like(det))
    s = o[:, None, :] - tri[None, :, 0]
    u = (s * pvec).sum(-1) * inv
    q = torch.linalg.cross(s, e1[None].expand_as(s))
    v = (d[:, None, :] * q).sum(-1) * inv
    t = (e2[None] * q).sum(-1) * inv
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= 0) & (t <= max_t)
    t = torch.where(hit, t, torch.full_like(t, math.inf))
    best, face = t.min(dim=1)
    missed = ~torch.isfinite(best)
    return torch.where(missed, torch.full_like(best, max_t), best), torch.where(missed, -1, face)
