"""Signed distance and closest point on a closed triangle mesh by BVH query (``wp.Mesh``), forward only.

For each query point p the op returns the distance to the nearest point c of the surface, negative
when p is inside, the face holding c and c's barycentric weights on that face's three vertices
(``c = w0 v[f0] + w1 v[f1] + w2 v[f2]``). Inside/outside comes from the fast generalised winding
number (Barill et al. 2018; ``wp.mesh_query_point_sign_winding_number``, the mesh built with
``support_winding_number=True``): inside when the winding number exceeds one half, which stays right
on slightly open or self-intersecting meshes. Nothing here is differentiable: it is used for mesh
resampling (``s3o_warp.resample``), where no gradient flows. The dense twin is
``s3o_warp.reference.sdf.closest_point_naive``.

``ray_hit`` casts rays against the same kind of BVH (``wp.mesh_query_ray``): the nearest hit along each
ray, for centring joints inside the body (``s3o_warp.skeleton.joints.centre_in_body``); its twin is
``s3o_warp.reference.sdf.ray_hit_naive``.
"""

from __future__ import annotations

import logging

import torch
import warp as wp

from ._warp import check_shape, stream_of, to_wp, wp_device

__all__ = ["closest_point", "ray_hit"]

log = logging.getLogger(__name__)

wp.set_module_options({"enable_backward": False})  # BVH queries: forward only

_FAR = 1.0e18  # "no distance limit": its square still fits a float32 (an infinite bound would overflow)


@wp.kernel
def closest_point_kernel(
    mesh: wp.uint64,
    points: wp.array(dtype=wp.vec3),
    max_dist: float,
    accuracy: float,
    # outputs
    distance: wp.array(dtype=float),
    face: wp.array(dtype=wp.int64),
    bary: wp.array(dtype=wp.vec3),
):
    """Per-point thread: nearest surface point, its face and barycentrics, winding-number sign."""
    i = wp.tid()
    p = points[i]
    q = wp.mesh_query_point_sign_winding_number(mesh, p, max_dist, accuracy, 0.5)
    if q.result:
        c = wp.mesh_eval_position(mesh, q.face, q.u, q.v)
        d = wp.length(c - p)
        if q.sign < 0.0:
            d = -d
        distance[i] = d
        face[i] = wp.int64(q.face)
        # Warp's convention: c = u v0 + v v1 + (1 - u - v) v2
        bary[i] = wp.vec3(q.u, q.v, 1.0 - q.u - q.v)
    else:  # no usable (non-sliver) face at all
        distance[i] = max_dist
        face[i] = wp.int64(-1)
        bary[i] = wp.vec3(0.0, 0.0, 0.0)


def _mesh_on(name: str, verts: torch.Tensor, faces: torch.Tensor, dev: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """Checked float32 vertices and int32 faces of a query mesh on ``dev`` (shared input rules of the ops)."""
    check_shape(name, "verts", verts, (None, 3))
    check_shape(name, "faces", faces, (None, 3))
    if not verts.dtype.is_floating_point:
        raise TypeError(f"{name}(): verts must be a float tensor, got {verts.dtype}")
    if faces.dtype.is_floating_point or faces.dtype == torch.bool:
        raise TypeError(f"{name}(): faces must be an integer tensor, got {faces.dtype}")
    if verts.shape[0] == 0 or faces.shape[0] == 0:
        raise ValueError(f"{name}(): the mesh is empty ({verts.shape[0]} vertices, {faces.shape[0]} faces)")
    v = verts.detach().to(device=dev, dtype=torch.float32).contiguous()
    f = faces.detach().to(device=dev, dtype=torch.int32).contiguous()
    lo, hi = int(f.min()), int(f.max())
    if lo < 0 or hi >= v.shape[0]:
        raise ValueError(f"{name}(): faces index vertices {lo}..{hi} but verts has {v.shape[0]}")
    return v, f


def closest_point(
    verts: torch.Tensor,
    faces: torch.Tensor,
    points: torch.Tensor,
    device: str | torch.device | None = None,
    accuracy: float = 2.0,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Signed distance, closest face and barycentrics of each query point on a triangle mesh.

    One BVH (``wp.Mesh``, float32, built per call) and one closest-point query per point; the sign
    is the winding number's (negative inside), so the mesh should be closed and consistently wound
    (counter-clockwise seen from outside); a slightly open one still gets a sensible sign.
    Faces that Warp judges slivers (area below 1e-6 x the sum of squared edge lengths) are never
    returned as closest.

    Args:
        verts: ``(N, 3)`` float vertices (any float dtype; queried in float32).
        faces: ``(F, 3)`` integer vertex indices.
        points: ``(M, 3)`` float query points.
        device: where to run (``"cpu"``, ``"cuda:0"``...); default ``points.device``. Inputs are
            moved there; outputs come back on ``points.device``.
        accuracy: the fast winding number's far-field accuracy (Warp's ``accuracy``, larger = more
            exact and slower; 2 is Warp's default).

    Returns:
        ``(distance, face, bary)``: ``(M,)`` float32 signed distance (negative inside), ``(M,)`` int64
        index of the face holding the closest point, ``(M, 3)`` float32 barycentric weights (sum 1)
        of that face's vertices ``faces[face, 0..2]``. Concretely, the closest point of ``points[m]``
        is ``(bary[m, :, None] * verts[faces[face[m]]]).sum(0)``. A mesh whose every face is a
        sliver gives ``distance = 1e18``, ``face = -1``, ``bary = 0``.

    Raises:
        ValueError: wrong shapes, empty verts or faces, face indices out of range.
        TypeError: non-float verts/points or non-integer faces.
    """
    name = "closest_point"
    check_shape(name, "points", points, (None, 3))
    if not points.dtype.is_floating_point:
        raise TypeError(f"{name}(): points must be a float tensor, got {points.dtype}")
    out_device = points.device
    dev = torch.device(device) if device is not None else points.device
    v, f = _mesh_on(name, verts, faces, dev)
    p = points.detach().to(device=dev, dtype=torch.float32).contiguous()
    m = p.shape[0]
    distance = torch.empty(m, dtype=torch.float32, device=dev)
    face = torch.empty(m, dtype=torch.int64, device=dev)
    bary = torch.empty((m, 3), dtype=torch.float32, device=dev)
    if m == 0:
        return distance.to(out_device), face.to(out_device), bary.to(out_device)
    indices = f.reshape(-1)
    with stream_of(p):
        mesh = wp.Mesh(points=to_wp(v, wp.vec3), indices=to_wp(indices), support_winding_number=True)
        wp.launch(
            closest_point_kernel,
            dim=m,
            inputs=[mesh.id, to_wp(p, wp.vec3), _FAR, float(accuracy)],
            outputs=[to_wp(distance), to_wp(face), to_wp(bary, wp.vec3)],
            device=wp_device(p),
        )
        if p.is_cuda:  # the BVH dies with this function: let the launch finish first
            wp.synchronize_stream(wp.stream_from_torch(p.device))
    del mesh, v, indices
    return distance.to(out_device), face.to(out_device), bary.to(out_device)


@wp.kernel
def ray_hit_kernel(
    mesh: wp.uint64,
    origins: wp.array(dtype=wp.vec3),
    dirs: wp.array(dtype=wp.vec3),
    max_t: float,
    # outputs
    t_hit: wp.array(dtype=float),
    face: wp.array(dtype=wp.int64),
):
    """Per-ray thread: distance along the (unit) direction to the nearest face, either side."""
    i = wp.tid()
    q = wp.mesh_query_ray(mesh, origins[i], dirs[i], max_t)
    if q.result:
        t_hit[i] = q.t
        face[i] = wp.int64(q.face)
    else:
        t_hit[i] = max_t
        face[i] = wp.int64(-1)


def ray_hit(
    verts: torch.Tensor,
    faces: torch.Tensor,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    max_t: float = _FAR,
    device: str | torch.device | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Nearest intersection of each ray ``origins[m] + t dirs[m]`` (t >= 0) with a triangle mesh.

    Args:
        verts: ``(N, 3)`` float vertices; faces: ``(F, 3)`` integer indices.
        origins: ``(M, 3)`` float ray starts; dirs: ``(M, 3)`` float directions (normalised here).
        max_t: farthest distance searched.
        device: where to run (default ``origins.device``); outputs come back there.

    Returns:
        ``(t, face)``: ``(M,)`` float32 distance to the hit (``max_t`` when the ray misses) and ``(M,)``
        int64 face hit (-1 on a miss). Faces count from both sides (a ray from inside hits the wall).

    Raises:
        ValueError: wrong shapes, empty mesh, face indices out of range, a zero direction.
        TypeError: non-float coordinates or non-integer faces.
    """
    name = "ray_hit"
    check_shape(name, "origins", origins, (None, 3))
    check_shape(name, "dirs", dirs, (origins.shape[0], 3))
    if not (origins.dtype.is_floating_point and dirs.dtype.is_floating_point):
        raise TypeError(f"{name}(): origins and dirs must be float tensors")
    out_device = origins.device
    dev = torch.device(device) if device is not None else origins.device
    v, f = _mesh_on(name, verts, faces, dev)
    o = origins.detach().to(device=dev, dtype=torch.float32).contiguous()
    d = dirs.detach().to(device=dev, dtype=torch.float32)
    norm = torch.linalg.vector_norm(d, dim=1, keepdim=True)
    if bool((norm <= 0).any()):
        raise ValueError(f"{name}(): every direction must be non-zero")
    d = (d / norm).contiguous()
    m = o.shape[0]
    t_hit = torch.empty(m, dtype=torch.float32, device=dev)
    face = torch.empty(m, dtype=torch.int64, device=dev)
    if m == 0:
        return t_hit.to(out_device), face.to(out_device)
    indices = f.reshape(-1)
    with stream_of(o):
        mesh = wp.Mesh(points=to_wp(v, wp.vec3), indices=to_wp(indices))
        wp.launch(ray_hit_kernel, dim=m, inputs=[mesh.id, to_wp(o, wp.vec3), to_wp(d, wp.vec3), float(max_t)],
                  outputs=[to_wp(t_hit), to_wp(face)], device=wp_device(o))
        if o.is_cuda:
            wp.synchronize_stream(wp.stream_from_torch(o.device))
    del mesh, v, indices
    return t_hit.to(out_device), face.to(out_device)
