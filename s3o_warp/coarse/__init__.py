"""Phase 1 coarse model initialisation (paper 3.2): 2D skeleton -> canonical frame -> 3D ellipsoids.

Pure functions on numpy arrays; the optimisation that fits the coarse shape sits on top of them.

Typical use::

    from s3o_warp.coarse import (CoarseSettings, canonical_frame, skeleton_2d, part_masks,
                                 lift_to_3d, ellipsoid_union_mesh, init_bones)

    t, ratios = canonical_frame(masks)              # the most side-on frame
    skel = skeleton_2d(masks[t])                    # junction/endpoint graph, pixels
    parts = part_masks(masks[t], skel)              # (E, H, W) part silhouettes
    coarse = lift_to_3d(skel, K, depth=3.0)         # ellipsoids in the object frame
    verts, faces = ellipsoid_union_mesh(coarse)     # ~2000-vertex watertight mesh
    bones = init_bones(coarse)                      # Gaussian bones, kinematic tree, joints
"""

from s3o_warp.coarse.lift import (
    Bones,
    Coarse3D,
    ellipsoid_field,
    ellipsoid_union_mesh,
    init_bones,
    lift_to_3d,
)
from s3o_warp.coarse.skeleton2d import (
    ENDPOINT,
    ISOLATED,
    JUNCTION,
    CoarseSettings,
    Skeleton2D,
    canonical_frame,
    leg_pairs,
    leg_stride,
    part_masks,
    skeleton_2d,
    symmetric_pairs,
)

__all__ = [
    "ENDPOINT",
    "ISOLATED",
    "JUNCTION",
    "Bones",
    "Coarse3D",
    "CoarseSettings",
    "Skeleton2D",
    "canonical_frame",
    "ellipsoid_field",
    "ellipsoid_union_mesh",
    "init_bones",
    "leg_pairs",
    "leg_stride",
    "lift_to_3d",
    "part_masks",
    "skeleton_2d",
    "symmetric_pairs",
]
