"""Dense pure-torch twins of the rasteriser ops in ``s3o_warp.kernels.raster`` (the right answers).

Every function here is O(T x pixels x faces) in memory and time on purpose: it is short enough to
read against the paper and the SoftRas definition, works in any float dtype (tests use float64), and
is differentiable by torch autograd. Conventions are those of the Warp ops: OpenCV camera
(+x right, +y down, +z forward), the centre of pixel (column c, row r) at (c, r), and the last row
of ``K`` taken as (0, 0, 1), so a vertex (X, Y, Z) projects to (K[0] . v / Z, K[1] . v / Z).
"""

from __future__ import annotations

import math

import torch

#: Faces whose soft coverage D = sigmoid(-d^2 / sigma) falls below this are ignored (as SoftRas).
COVERAGE_EPS = 1e-4


def silhouette_cutoff(sigma: float) -> float:
    """Squared pixel distance beyond which an outside face's coverage is < COVERAGE_EPS."""
    return sigma * math.log(1.0 / COVERAGE_EPS - 1.0)


def _frames_K(K: torch.Tensor, T: int) -> torch.Tensor:
    return K.expand(T, 3, 3) if K.dim() == 2 else K


def project_points(verts: torch.Tensor, K: torch.Tensor, near: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Pinhole projection of camera-space points to pixels.

    Args:
        verts: (T, V, 3) camera-space points (OpenCV frame, any units).
        K: (3, 3) or (T, 3, 3) intrinsics; only the first two rows are used.
        near: points with z <= near are "behind" (their pixel position is computed with z = 1 so it
            stays finite; no face containing them is ever drawn).

    Returns:
        xy: (T, V, 2) pixel coordinates (column, row) of each point.
        front: (T, V) bool, z > near.
    """
    z = verts[..., 2]
    front = z > near
    zs = torch.where(front, z, torch.ones_like(z))
    Kt = _frames_K(K, verts.shape[0])
    xy = torch.einsum("tij,tvj->tvi", Kt[:, :2, :], verts) / zs[..., None]
    return xy, front


def _pixel_centres(H: int, W: int, like: torch.Tensor) -> torch.Tensor:
    r, c = torch.meshgrid(
        torch.arange(H, dtype=like.dtype, device=like.device),
        torch.arange(W, dtype=like.dtype, device=like.device),
        indexing="ij",
    )
    return torch.stack([c, r], dim=-1).reshape(-1, 2)  # (P, 2) as (x, y)


def _cross(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def soft_silhouette_reference(verts, faces, K, image_size, sigma: float = 1.0, near: float = 1e-3):
    """Dense SoftRas silhouette: A = 1 - prod_j (1 - sigmoid(delta_j d_j^2 / sigma)).

    Args:
        verts: (T, V, 3) camera-space vertices (float32 or float64).
        faces: (F, 3) integer vertex indices.
        K: (3, 3) or (T, 3, 3) intrinsics.
        image_size: (H, W) in pixels.
        sigma: blur in square pixels.
        near: only faces with all three vertices at z > near count.

    Returns:
        (T, H, W) soft coverage A in [0, 1], dtype of ``verts``. d_j is the distance in pixels from
        the pixel centre to the boundary of projected triangle j, delta_j = +1 strictly inside
        (all three edge functions of one sign), -1 otherwise; outside faces with
        d_j^2 >= sigma ln(1/1e-4 - 1) are left out, exactly as the Warp op does.
    """
    H, W = image_size
    T = verts.shape[0]
    faces = faces.long()
    xy, front_v = project_points(verts, K, near)
    tri = xy[:, faces]  # (T, F, 3, 2)
    front = front_v[:, faces].all(-1)  # (T, F)
    p = _pixel_centres(H, W, xy)[None, :, None, :]  # (1, P, 1, 2)
    d2_edges, w_edges = [], []
    for k in range(3):
        a = tri[:, None, :, k]  # (T, 1, F, 2)
        b = tri[:, None, :, (k + 1) % 3]
        e = b - a
        ee = (e * e).sum(-1)
        s = ((p - a) * e).sum(-1) / torch.where(ee > 0, ee, torch.ones_like(ee))
        s = torch.where(ee > 0, s.clamp(0.0, 1.0), torch.zeros_like(s))
        diff = p - (a + s[..., None] * e)
        d2_edges.append((diff * diff).sum(-1))
        w_edges.append(_cross(e, p - a))
    d2_all = torch.stack(d2_edges, -1)  # nearest edge; ties go to the first edge, as in the kernel
    d2 = d2_all.gather(-1, d2_all.argmin(-1, keepdim=True))[..., 0]  # (T, P, F)
    w = torch.stack(w_edges, -1)
    inside = (w > 0).all(-1) | (w < 0).all(-1)
    x = torch.where(inside, d2, -d2) / sigma
    keep = front[:, None, :] & (inside | (d2 < silhouette_cutoff(sigma)))
    one_minus_D = torch.where(keep, torch.sigmoid(-x), torch.ones_like(x))
    A = 1.0 - one_minus_D.prod(-1)
    return A.reshape(T, H, W)


def screen_barycentrics(tri_xy: torch.Tensor, p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Screen-space barycentrics (l0, l1, l2) of points p in triangles, and twice the signed area.

    l_i is the edge function of the edge opposite vertex i divided by twice the signed area, so
    p = sum_i l_i v_i and sum_i l_i = 1 for any winding. Shapes: tri_xy (..., 3, 2), p (..., 2).
    """
    a, b, c = tri_xy[..., 0, :], tri_xy[..., 1, :], tri_xy[..., 2, :]
    area2 = _cross(b - a, c - a)
    safe = torch.where(area2 != 0, area2, torch.ones_like(area2))
    lam = torch.stack([_cross(c - b, p - b), _cross(a - c, p - c), _cross(b - a, p - a)], -1)
    return lam / safe[..., None], area2


def perspective_barycentrics(lam: torch.Tensor, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Perspective-correct barycentrics b_i = (l_i / z_i) / sum_k (l_k / z_k) and depth 1 / sum_k."""
    q = lam / z
    s = q.sum(-1, keepdim=True)
    return q / s, 1.0 / s[..., 0]


def rasterize_reference(verts, faces, K, image_size, near: float = 1e-3):
    """Dense z-buffer: nearest front face covering each pixel centre (lower face id on ties).

    Args:
        verts: (T, V, 3) camera-space vertices.
        faces: (F, 3) integer vertex indices.
        K: (3, 3) or (T, 3, 3) intrinsics.
        image_size: (H, W).
        near: only faces with all three vertices at z > near are drawn.

    Returns:
        face_index: (T, H, W) int32, -1 for background. Concretely, face_index[t, r, c] = f means
            face f is the nearest face whose projection covers the centre of pixel (c, r) in frame t
            (covers: all three screen barycentrics >= 0, non-zero area).
        bary: (T, H, W, 3) perspective-correct barycentrics of the visible point (0 on background).
        depth: (T, H, W) camera z of the visible point (0 on background).
    """
    H, W = image_size
    T = verts.shape[0]
    F = faces.shape[0]
    faces = faces.long()
    xy, front_v = project_points(verts, K, near)
    tri = xy[:, faces]  # (T, F, 3, 2)
    zf = verts[..., 2][:, faces]  # (T, F, 3)
    front = front_v[:, faces].all(-1)
    p = _pixel_centres(H, W, xy)[None, :, None, :]  # (1, P, 1, 2)
    lam, area2 = screen_barycentrics(tri[:, None], p)  # (T, P, F, 3), (T, 1, F)
    zsafe = torch.where(front[..., None], zf, torch.ones_like(zf))[:, None]
    inv_depth = (lam / zsafe).sum(-1)
    covered = front[:, None, :] & (area2 != 0) & (lam >= 0).all(-1) & (inv_depth > 0)
    depth_all = torch.where(covered, 1.0 / torch.where(covered, inv_depth, torch.ones_like(inv_depth)),
                            torch.full_like(inv_depth, math.inf))
    zmin = depth_all.min(-1, keepdim=True).values
    ids = torch.arange(F, device=verts.device).expand_as(depth_all)
    winner = torch.where(covered & (depth_all == zmin), ids, torch.full_like(ids, F)).min(-1).values
    face_index = torch.where(winner < F, winner, torch.full_like(winner, -1))  # (T, P)
    fg = face_index >= 0
    fi = face_index.clamp(min=0)
    tsel = torch.arange(T, device=verts.device)[:, None].expand_as(fi)
    lam_v, _ = screen_barycentrics(tri[tsel, fi], p[0, :, 0, :].expand(T, -1, -1))
    zsel = torch.where(fg[..., None], zf[tsel, fi], torch.ones_like(zf[tsel, fi]))
    lam_v = torch.where(fg[..., None], lam_v, torch.full_like(lam_v, 1.0 / 3.0))
    bary, depth = perspective_barycentrics(lam_v, zsel)
    bary = torch.where(fg[..., None], bary, torch.zeros_like(bary))
    depth = torch.where(fg, depth, torch.zeros_like(depth))
    return face_index.to(torch.int32).reshape(T, H, W), bary.reshape(T, H, W, 3), depth.reshape(T, H, W)


def interpolate_reference(attr, faces, face_index, bary):
    """Dense attribute interpolation: out[t, r, c] = sum_i bary[t, r, c, i] attr[t, faces[f, i]].

    Args:
        attr: (V, C) or (T, V, C) per-vertex attributes.
        faces: (F, 3) integer vertex indices.
        face_index: (T, H, W) integer, -1 for background.
        bary: (T, H, W, 3) weights.

    Returns:
        (T, H, W, C), 0 on background; written as a dense one-hot contraction over faces.
    """
    T, H, W = face_index.shape
    F = faces.shape[0]
    if attr.dim() == 2:
        attr = attr.expand(T, *attr.shape)
    attr_f = attr[:, faces.long()]  # (T, F, 3, C)
    onehot = (face_index.long()[..., None] == torch.arange(F, device=face_index.device)).to(bary.dtype)
    return torch.einsum("thwf,thwi,tfic->thwc", onehot, bary, attr_f)
