"""The public differentiable ops of s3o-warp (Warp kernels behind torch autograd), in one place.

Shapes: T frames, V/N vertices, F faces, B bones, E edges, H x W image. Camera space is OpenCV
(+x right, +y down, +z forward); the centre of pixel (c, r) is at (c, r). See each op's docstring.
"""

from s3o_warp.kernels._warp import set_index_bounds
from s3o_warp.kernels.nearest import nearest_point
from s3o_warp.kernels.raster import (
    interpolate,
    rasterize,
    soft_silhouette,
    soft_silhouette_naive,
)
from s3o_warp.kernels.regularisers import (
    arap_loss,
    dynamic_rigidity_loss,
    laplacian_loss,
    mesh_edges,
    symmetry_loss,
)
from s3o_warp.kernels.sdf import closest_point, ray_hit
from s3o_warp.kernels.skinning import blend_skinning, skinning_weights
from s3o_warp.kernels.visibility import VisibilityContext, vertex_visibility

__all__ = [
    "VisibilityContext",
    "arap_loss",
    "blend_skinning",
    "closest_point",
    "dynamic_rigidity_loss",
    "interpolate",
    "laplacian_loss",
    "mesh_edges",
    "nearest_point",
    "rasterize",
    "ray_hit",
    "set_index_bounds",
    "skinning_weights",
    "soft_silhouette",
    "soft_silhouette_naive",
    "symmetry_loss",
    "vertex_visibility",
]
