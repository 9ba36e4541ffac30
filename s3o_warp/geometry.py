"""Small differentiable rotation and projection helpers (torch), shared by the model and the fit, and the numpy
projection (:func:`project_np`) and tensor-to-array conversion (:func:`to_numpy`) that the rest of the package uses.

Conventions: OpenCV camera (+x right, +y down, +z forward); a 3x4 ``[R|t]`` maps x -> R x + t;
intrinsics K are 3x3 pixel matrices with the centre of pixel (c, r) at (c, r).
"""

from __future__ import annotations

import math

import numpy as np
import torch


def axis_angle_to_matrix(v: torch.Tensor) -> torch.Tensor:
    """Rodrigues: axis-angle vectors ``(..., 3)`` -> rotation matrices ``(..., 3, 3)``, smooth at 0."""
    theta2 = (v * v).sum(-1, keepdim=True)
    theta = torch.sqrt(theta2 + 1e-20)
    small = theta2 < 1e-8
    # sin(t)/t and (1-cos t)/t^2 with Taylor expansions near zero
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / (theta2 + 1e-20))
    x, y, z = v.unbind(-1)
    zero = torch.zeros_like(x)
    kx = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], -1).reshape(v.shape[:-1] + (3, 3))
    eye = torch.eye(3, dtype=v.dtype, device=v.device).expand_as(kx)
    return eye + a[..., None] * kx + b[..., None] * (kx @ kx)


def matrix_to_axis_angle(R: torch.Tensor) -> torch.Tensor:
    """Rotation matrices ``(..., 3, 3)`` -> axis-angle ``(..., 3)`` (not for gradients; for inits)."""
    R = R.double()
    cos = ((R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1) / 2).clamp(-1, 1)
    theta = torch.acos(cos)
    w = torch.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    s = torch.sin(theta)
    out = torch.where(s[..., None].abs() > 1e-6, w * (theta / (2 * s))[..., None], w / 2)
    # near pi: axis from the largest diagonal entry
    near_pi = theta > math.pi - 1e-3
    if near_pi.any():
        d = torch.diagonal(R, dim1=-2, dim2=-1)
        axis = torch.sqrt(((d + 1) / 2).clamp_min(0))
        sign = torch.sign(w)
        sign = torch.where(sign == 0, torch.ones_like(sign), sign)
        out = torch.where(near_pi[..., None], axis * sign * theta[..., None], out)
    return out


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """Unit-normalised quaternions ``(..., 4)`` ordered (w, x, y, z) -> rotation matrices ``(..., 3, 3)``."""
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        -1,
    ).reshape(q.shape[:-1] + (3, 3))


def matrix_to_quat(R: torch.Tensor) -> torch.Tensor:
    """Rotation matrices ``(..., 3, 3)`` -> quaternions (w, x, y, z) with w >= 0 (for inits and I/O).

    Shepperd's method: the largest of |w|, |x|, |y|, |z| comes from the diagonal and the others from
    sums and differences of the off-diagonal pairs divided by it. Taking every sign from the
    differences alone loses the relative signs of x, y, z near a half turn (the differences vanish), so
    a tilted Gaussian's axis came back mirrored.
    """
    m = R.double()
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    # 4 x the square of each component, then each candidate row built around one component (times 4 * it)
    sq = torch.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    cand = torch.stack([
        torch.stack([sq[..., 0], m21 - m12, m02 - m20, m10 - m01], -1),
        torch.stack([m21 - m12, sq[..., 1], m01 + m10, m02 + m20], -1),
        torch.stack([m02 - m20, m01 + m10, sq[..., 2], m12 + m21], -1),
        torch.stack([m10 - m01, m02 + m20, m12 + m21, sq[..., 3]], -1),
    ], -2)  # (..., 4, 4): row k = 4 q_k q
    k = sq.argmax(-1)
    q = torch.take_along_dim(cand, k[..., None, None].expand(k.shape + (1, 4)), dim=-2)[..., 0, :]
    q = q / q.norm(dim=-1, keepdim=True)
    q = torch.where(q[..., :1] < 0, -q, q)
    return q.to(R.dtype)


def project(verts: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Pinhole projection of camera-space points ``(T, N, 3)`` with K ``(3,3)`` or ``(T,3,3)`` -> pixels ``(T, N, 2)``."""
    if K.dim() == 2:
        K = K.expand(verts.shape[0], 3, 3)
    z = verts[..., 2:3].clamp_min(1e-6)
    xy = verts[..., :2] / z
    fx, fy = K[:, 0, 0, None], K[:, 1, 1, None]
    cx, cy = K[:, 0, 2, None], K[:, 1, 2, None]
    skew = K[:, 0, 1, None]
    u = fx * xy[..., 0] + skew * xy[..., 1] + cx
    v = fy * xy[..., 1] + cy
    return torch.stack([u, v], -1)


def project_np(points: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pinhole projection in numpy: ``(..., 3)`` camera-space points, K ``(..., 3, 3)`` broadcastable against them ->
    ``(..., 2)`` pixels (x = column, y = row); the homogeneous divide by ``K @ p``'s third entry, no clamping."""
    p = np.einsum("...ij,...j->...i", K, points)
    return p[..., :2] / p[..., 2:3]


def to_numpy(x, dtype=np.float64) -> np.ndarray:
    """A tensor (detached, copied to the CPU) or anything array-like as a numpy array of ``dtype``."""
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=dtype)


def rt_to_homogeneous(rt: torch.Tensor) -> torch.Tensor:
    """``(..., 3, 4)`` -> ``(..., 4, 4)``."""
    bottom = torch.zeros(rt.shape[:-2] + (1, 4), dtype=rt.dtype, device=rt.device)
    bottom[..., 0, 3] = 1
    return torch.cat([rt, bottom], -2)


def look_at_rotation(forward: torch.Tensor, down: torch.Tensor) -> torch.Tensor:
    """Rows of the world-to-camera rotation (OpenCV) for a camera looking along ``forward`` with ``down`` ~ +y."""
    z = forward / forward.norm()
    x = torch.linalg.cross(down, z)
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    return torch.stack([x, y, z], 0)
