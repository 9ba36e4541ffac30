"""Small synthetic frames, masks and sequence folders shared by the data tests (test_data_*.py)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

H, W = 60, 80


def texture(h: int, w: int, seed: int = 0) -> np.ndarray:
    """Smooth random RGB texture (uint8): good for optical flow."""
    rng = np.random.default_rng(seed)
    noise = rng.random((h // 4 + 2, w // 4 + 2, 3)).astype(np.float32)
    big = cv2.resize(noise, (w + 8, h + 8), interpolation=cv2.INTER_CUBIC)[4 : 4 + h, 4 : 4 + w]
    return np.clip(big * 255, 0, 255).astype(np.uint8)


def shift(img: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """Content moves by (+dx, +dy): out(x) = img(x - d)."""
    m = np.float32([[1, 0, dx], [0, 1, dy]])
    return cv2.warpAffine(img, m, (img.shape[1], img.shape[0]), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


def rect_mask(x0: int, y0: int, x1: int, y1: int, h: int = H, w: int = W) -> np.ndarray:
    m = np.zeros((h, w), np.uint8)
    m[y0 : y1 + 1, x0 : x1 + 1] = 255
    return m


def write_seq(root: Path, n: int = 3, names=None, mask_names=None, ext: str = ".png") -> Path:
    """root/images + root/masks with n textured frames and a moving rectangle mask."""
    (root / "images").mkdir(parents=True)
    (root / "masks").mkdir()
    names = names or [f"{k:05d}" for k in range(n)]
    mask_names = mask_names or names
    base = texture(H, W)
    for k, (a, b) in enumerate(zip(names, mask_names)):
        cv2.imwrite(str(root / "images" / f"{a}{ext}"), cv2.cvtColor(shift(base, k, 0), cv2.COLOR_RGB2BGR))
        cv2.imwrite(str(root / "masks" / f"{b}.png"), rect_mask(20 + k, 15, 50 + k, 40))
    return root


def listing(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))
