"""s3o-warp: shape, physical skeleton, skinning and motion of an articulated object from one video."""

__version__ = "0.1.0"
