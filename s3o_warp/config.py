"""One configuration dataclass tree for every hyper-parameter, with its default.

Precedence: defaults < preset < ``--config`` TOML < command-line flags. Every field has a one-line
docstring (the comment under it) that becomes its ``--help`` text.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class DataConfig:
    """How a sequence is read, cropped and given optical flow (``s3o_warp.video``)."""

    object_id: int | None = None
    """For palette (multi-object) masks such as DAVIS-2017: the object's palette index; None = any non-zero / > 127."""
    crop_size: int = 256
    """Working resolution: each frame's square crop is resized to crop_size x crop_size pixels."""
    crop_scale: float = 1.2
    """Side of the square crop as a multiple of the mask bounding box's longer side."""
    flow_preset: str = "medium"
    """OpenCV DIS optical-flow preset: ultrafast, fast or medium."""
    flow_fb_sigma: float = 1.0
    """Forward-backward consistency: confidence = exp(-|f + b(x + f)|^2 / (2 sigma^2)), sigma in crop pixels."""


@dataclass
class Config:
    """Root of the configuration tree."""

    data: DataConfig = field(default_factory=DataConfig)
    seed: int = 0
    """Seed for every random choice."""
