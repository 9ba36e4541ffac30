"""Camera paths for synthetic shots: an orbit around the moving animal, or a pan from a fixed spot.

Conventions: world = the model's object frame (+y up); cameras are OpenCV (+x right, +y down,
+z forward); ``cam_from_world`` (T, 4, 4) maps world points to camera points; ``K`` (3, 3) has the
principal point at the image centre ((W - 1) / 2, (H - 1) / 2) in full-frame pixels. Azimuth is
measured about +y from +z toward +x: azimuth 0 looks at the animal's right flank (+z side) with its
head (+x) to the image's right, azimuth 90 looks at its face; elevation lifts the camera above the
horizontal plane through the target.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import InputError


def intrinsics(image_size: tuple[int, int], fov_deg: float = 45.0) -> np.ndarray:
    """(3, 3) float64 pinhole K for ``image_size`` = (H, W) with a horizontal field of view in degrees."""
    h, w = image_size
    f = 0.5 * w / math.tan(math.radians(fov_deg) / 2)
    return np.array([[f, 0.0, (w - 1) / 2.0], [0.0, f, (h - 1) / 2.0], [0.0, 0.0, 1.0]])


def look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """(T, 4, 4) OpenCV world-to-camera matrices of cameras at ``eye`` (T, 3) looking at ``target`` (T, 3)."""
    eye, target = np.atleast_2d(eye).astype(np.float64), np.atleast_2d(target).astype(np.float64)
    fwd = target - eye
    fwd /= np.linalg.norm(fwd, axis=-1, keepdims=True)
    right = np.cross(fwd, np.asarray(up, dtype=np.float64))
    norm = np.linalg.norm(right, axis=-1, keepdims=True)
    if np.any(norm < 1e-8):
        raise InputError("camera path: the view direction is parallel to up; use --elev between -89 and 89 degrees")
    right /= norm
    down = np.cross(fwd, right)
    rot = np.stack([right, down, fwd], axis=1)  # rows: camera axes in world
    m = np.tile(np.eye(4), (eye.shape[0], 1, 1))
    m[:, :3, :3] = rot
    m[:, :3, 3] = -np.einsum("tab,tb->ta", rot, eye)
    return m


def _direction(azim_deg: np.ndarray, elev_deg: float) -> np.ndarray:
    a, e = np.radians(azim_deg), math.radians(elev_deg)
    return np.stack([np.sin(a) * math.cos(e), np.full_like(a, math.sin(e)), np.cos(a) * math.cos(e)], -1)


def smooth_targets(verts: np.ndarray) -> np.ndarray:
    """(T, 3) look-at points: the per-frame vertex centroid, fitted by a straight line in time."""
    c = verts.mean(axis=1).astype(np.float64)
    if c.shape[0] < 3:
        return np.repeat(c.mean(0, keepdims=True), c.shape[0], 0)
    t = np.arange(c.shape[0], dtype=np.float64)
    design = np.stack([np.ones_like(t), t], 1)
    coef, *_ = np.linalg.lstsq(design, c, rcond=None)
    return design @ coef


def camera_path(verts: np.ndarray, image_size: tuple[int, int], kind: str = "orbit",
                azim: tuple[float, float] = (-30.0, 30.0), elev: float = 10.0, fov_deg: float = 45.0,
                fill: float = 0.9) -> tuple[np.ndarray, np.ndarray]:
    """Cameras that keep the animal framed.

    Args:
        verts: (T, V, 3) posed vertices in world (object) coordinates.
        image_size: (H, W) pixels.
        kind: "orbit" (azimuth sweeps A0 -> A1 linearly over the clip around the moving target) or
            "pan" (the camera stays where the orbit starts, at azimuth A0 around the clip's mean
            target, and turns to follow the animal; A1 is unused).
        azim: (A0, A1) degrees.
        elev: degrees above the horizontal.
        fov_deg: horizontal field of view, degrees.
        fill: fraction of the shorter image half-side that the animal's bounding sphere spans.

    Returns:
        K (3, 3) float64 and cam_from_world (T, 4, 4) float64.
    """
    if kind not in ("orbit", "pan"):
        raise InputError(f"camera path: unknown kind {kind!r}; use 'orbit' or 'pan'")
    if not -89.0 <= elev <= 89.0:
        raise InputError(f"camera path: elevation {elev} degrees out of range; use --elev between -89 and 89")
    num_t = verts.shape[0]
    k = intrinsics(image_size, fov_deg)
    h, w = image_size
    target = smooth_targets(verts)
    radius = float(np.max(np.linalg.norm(verts - target[:, None], axis=-1)))
    half = math.atan(fill * 0.5 * min(h, w) / k[0, 0])
    dist = radius / math.sin(half)
    if kind == "orbit":
        az = np.linspace(azim[0], azim[1], num_t) if num_t > 1 else np.array([float(azim[0])])
        eye = target + dist * _direction(az, elev)
    else:
        centre = target.mean(0)
        span = np.linalg.norm(target[-1] - target[0])
        eye = np.repeat(centre[None] + (dist + 0.5 * span) * _direction(np.array([azim[0]]), elev), num_t, 0)
    return k, look_at(eye, target)
