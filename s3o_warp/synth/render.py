"""Shade synthetic frames with the project's rasteriser (``s3o_warp.kernels.raster``).

Foreground: per-pixel Lambert + ambient shading (a light fixed in camera space, above-left of the
camera) of the vertex base colour, modulated by a procedural 3D texture evaluated at the visible
point's rest-pose (object-space) coordinates, so the texture sticks to the surface and optical flow
has something to track. Background: an environment at infinity (sky/ground gradient plus a
direction-dependent pattern) looked up by each pixel's world-space ray, so it moves with the camera
like a distant scene. Masks are the rasteriser's coverage (``face_index >= 0``).
"""

from __future__ import annotations

import numpy as np
import torch

from ..kernels.raster import interpolate, rasterize
from .model import vertex_normals


class SolidTexture:
    """A seeded procedural 3D pattern: a sum of random plane waves, squashed to [0, 1].

    Args:
        scale: object size (e.g. the rest mesh's bounding-box diagonal); wavelengths are 2-15 % of it.
        seed: fixes the waves.
        waves: number of plane waves.
    """

    def __init__(self, scale: float, seed: int, waves: int = 12):
        rng = np.random.default_rng(seed + 7919)
        dirs = rng.normal(size=(waves, 3))
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        wavelength = scale * np.exp(rng.uniform(np.log(0.02), np.log(0.15), size=waves))
        self.freq = torch.as_tensor(dirs * (2 * np.pi / wavelength)[:, None], dtype=torch.float32)
        self.phase = torch.as_tensor(rng.uniform(0, 2 * np.pi, size=waves), dtype=torch.float32)

    def __call__(self, points: torch.Tensor) -> torch.Tensor:
        """(..., 3) object-space points -> (...,) pattern values in [0, 1]."""
        f, ph = self.freq.to(points.device), self.phase.to(points.device)
        n = torch.sin(points @ f.T + ph).sum(-1) / np.sqrt(f.shape[0] / 2.0)
        return 0.5 + 0.5 * torch.tanh(1.5 * n)


def background(k: np.ndarray, cam_from_world: np.ndarray, image_size: tuple[int, int], seed: int) -> np.ndarray:
    """(T, H, W, 3) float32 in [0, 1]: the environment seen along each pixel's world ray."""
    h, w = image_size
    rng = np.random.default_rng(seed + 104729)
    cols, rows = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pix = np.stack([cols, rows, np.ones_like(cols)], -1) @ np.linalg.inv(k).T  # (H, W, 3) camera rays
    rays = np.einsum("tba,hwb->thwa", cam_from_world[:, :3, :3], pix)  # R^T d: world rays
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    elev = np.arcsin(np.clip(rays[..., 1], -1, 1))
    azim = np.arctan2(rays[..., 0], rays[..., 2])
    sky = np.array([0.55, 0.68, 0.85]) + 0.08 * rng.uniform(-1, 1, 3)
    ground = np.array([0.42, 0.38, 0.30]) + 0.08 * rng.uniform(-1, 1, 3)
    up = np.clip(0.5 + elev / 0.3, 0.0, 1.0)[..., None]
    base = up * sky + (1 - up) * ground
    pattern = np.zeros(elev.shape)
    for _ in range(6):  # integer azimuth frequencies keep the pattern continuous around the circle
        a, e = rng.integers(6, 40), rng.uniform(6, 40)
        pattern += np.sin(a * azim + e * elev + rng.uniform(0, 2 * np.pi))
    pattern /= np.sqrt(3.0)
    return np.clip(base * (0.8 + 0.2 * np.tanh(pattern))[..., None], 0.0, 1.0).astype(np.float32)


def shade_chunk(verts_cam: np.ndarray, faces: np.ndarray, k: np.ndarray, cam_from_world: np.ndarray,
                rest_verts: np.ndarray, colors: np.ndarray, texture: SolidTexture,
                image_size: tuple[int, int], seed: int, device: str = "cpu"):
    """Render a chunk of frames.

    Args:
        verts_cam: (T, V, 3) camera-space vertices (OpenCV).
        faces: (F, 3) int.
        k: (3, 3) intrinsics.
        cam_from_world: (T, 4, 4) world-to-camera matrices (for the background's rays).
        rest_verts: (V, 3) rest-pose object coordinates (the texture's domain).
        colors: (V, 3) sRGB base colour in [0, 1].
        texture: the solid texture.
        image_size: (H, W).
        seed: background seed.
        device: torch device for the rasteriser ("cpu" or "cuda:0").

    Returns:
        image uint8 (T, H, W, 3) RGB, mask bool (T, H, W), face_index int32 (T, H, W),
        depth float32 (T, H, W) camera z (0 on background).
    """
    num_t = verts_cam.shape[0]
    normals = vertex_normals(verts_cam, faces)
    v = torch.as_tensor(np.ascontiguousarray(verts_cam), dtype=torch.float32, device=device)
    f = torch.as_tensor(np.ascontiguousarray(faces), dtype=torch.int32, device=device)
    kt = torch.as_tensor(k, dtype=torch.float32, device=device)
    with torch.no_grad():
        face_index, bary, depth = rasterize(v, f, kt, image_size)
        static = torch.as_tensor(np.concatenate([rest_verts, colors], 1), dtype=torch.float32, device=device)
        attr = torch.cat([static.expand(num_t, -1, -1),
                          torch.as_tensor(normals, dtype=torch.float32, device=device)], -1)
        pix = interpolate(attr.contiguous(), f, face_index, bary)  # (T, H, W, 9)
        pos, base, nrm = pix[..., :3], pix[..., 3:6], pix[..., 6:9]
        nrm = nrm / nrm.norm(dim=-1, keepdim=True).clamp_min(1e-8)
        h, w = image_size
        rows, cols = torch.meshgrid(torch.arange(h, device=device, dtype=torch.float32),
                                    torch.arange(w, device=device, dtype=torch.float32), indexing="ij")
        ray = torch.stack([(cols - kt[0, 2]) / kt[0, 0], (rows - kt[1, 2]) / kt[1, 1], torch.ones_like(cols)], -1)
        nrm = torch.where(((nrm * ray).sum(-1, keepdim=True) > 0), -nrm, nrm)  # two-sided: face the camera
        light = torch.tensor([-0.35, -0.6, -0.72], device=device)
        light = light / light.norm()
        lambert = (nrm * light).sum(-1).clamp_min(0.0)
        shade = 0.38 + 0.62 * lambert
        tex = texture(pos)
        fg = base * (0.55 + 0.45 * tex)[..., None] * shade[..., None]
        mask = face_index >= 0
        bg = torch.as_tensor(background(k, cam_from_world, image_size, seed), device=device)
        img = torch.where(mask[..., None], fg, bg).clamp(0.0, 1.0)
    image = (img * 255.0 + 0.5).to(torch.uint8).cpu().numpy()
    return image, mask.cpu().numpy(), face_index.cpu().numpy(), depth.cpu().numpy()
