"""Per-vertex visibility from the camera centre by BVH ray casting (``wp.Mesh``, refit, not rebuilt).

A vertex ``x`` (OpenCV camera space, camera centre at the origin, +z forward) is *visible* when it
lies in front of the camera (``z > 0``) and the segment from the origin towards it hits no face at
a distance below ``(1 - eps) ||x||`` (``eps`` is **relative**: it skips the faces that share the
vertex, which the ray meets at exactly ``||x||``).

All T frames live in one grouped BVH (``groups=`` the frame index, queried from
``wp.mesh_get_group_root``), so one launch casts every ray of every frame. The BVH is built once
per (topology, T) by :class:`VisibilityContext` and *refit* when the vertices move.
"""

from __future__ import annotations

import logging
from collections import OrderedDict

import torch
import warp as wp

from ._warp import check_float, check_shape, stream_of, to_wp, wp_device

__all__ = ["VisibilityContext", "vertex_visibility"]

log = logging.getLogger(__name__)

wp.set_module_options({"enable_backward": False})  # BVH queries: forward only

_CACHE_SIZE = 8
_cache: OrderedDict = OrderedDict()


@wp.kernel
def cast_visibility_kernel(
    mesh: wp.uint64,
    points: wp.array(dtype=wp.vec3),
    num_verts: int,
    eps: float,
    # outputs
    visible: wp.array2d(dtype=wp.bool),
):
    """Per-(frame t, vertex n) thread: any-hit ray from the origin towards vertex n of frame t."""
    t, n = wp.tid()
    p = points[t * num_verts + n]
    dist = wp.length(p)
    vis = bool(False)
    if p[2] > 0.0 and dist > 0.0:
        root = wp.mesh_get_group_root(mesh, t)
        hit = wp.mesh_query_ray_anyhit(mesh, wp.vec3(0.0, 0.0, 0.0), p / dist, dist * (1.0 - eps), root)
        vis = not hit
    visible[t, n] = vis


class VisibilityContext:
    """A grouped BVH over T frames of one triangle topology, refit (never rebuilt) as vertices move.

    Concretely, ``ctx(verts)[t, n]`` is True when vertex n of frame t is seen from the camera centre.
    The context remembers its device and topology; calling it with vertices on another device is an
    error. The BVH is (re)built only when the frame or vertex count changes; ``num_builds`` and
    ``num_refits`` count both, and ``mesh`` is the live ``wp.Mesh`` (None before the first call).

    Args:
        faces: ``(F, 3)`` integer vertex indices (any integer dtype); its device is the context's.
    """

    def __init__(self, faces: torch.Tensor):
        check_shape("VisibilityContext", "faces", faces, (None, 3))
        if faces.dtype.is_floating_point or faces.dtype == torch.bool:
            raise TypeError(f"VisibilityContext(): faces must be an integer tensor, got {faces.dtype}")
        if faces.numel() and int(faces.min()) < 0:
            raise ValueError(f"VisibilityContext(): faces indices must be >= 0, got min {int(faces.min())}")
        self.device = faces.device
        self.faces = faces.detach().to(torch.int32).contiguous().clone()
        self._max_index = int(self.faces.max()) if self.faces.numel() else -1  # one sync, here only
        self.mesh: wp.Mesh | None = None
        self.num_builds = 0
        self.num_refits = 0
        self._shape: tuple[int, int] | None = None
        self._points = self._indices = self._groups = None

    def _build(self, num_frames: int, num_verts: int, verts: torch.Tensor) -> None:
        dev = wp_device(verts)
        f = self.faces.shape[0]
        offsets = torch.arange(num_frames, dtype=torch.int32, device=self.device) * num_verts
        indices = (self.faces[None] + offsets[:, None, None]).reshape(-1).contiguous()
        groups = torch.arange(num_frames, dtype=torch.int32, device=self.device).repeat_interleave(f).contiguous()
        self._points = wp.empty(num_frames * num_verts, dtype=wp.vec3, device=dev)
        wp.copy(self._points, to_wp(verts.reshape(-1, 3), wp.vec3))
        # Warp copies nothing here: keep the torch buffers alive as long as the mesh.
        self._indices, self._groups = indices, groups
        self.mesh = wp.Mesh(points=self._points, indices=to_wp(indices), groups=to_wp(groups))
        self._shape = (num_frames, num_verts)
        self.num_builds += 1
        log.debug("visibility BVH built: %d frames x %d faces on %s", num_frames, f, self.device)

    def __call__(self, verts: torch.Tensor, eps: float = 1e-3) -> torch.Tensor:
        """Visibility of every vertex of every frame.

        Args:
            verts: ``(T, N, 3)`` float32 vertices in OpenCV camera space (camera centre at the origin).
            eps: relative tolerance: a face hit nearer than ``(1 - eps)`` times the vertex's distance
                occludes it. In [0, 1).

        Returns:
            ``(T, N)`` bool, on the context's device; vertices with ``z <= 0`` are not visible.

        Raises:
            ValueError: wrong shape, vertices on another device, faces indexing past N, eps out of range.
            TypeError: non-float32 verts.
        """
        name = "vertex_visibility"
        check_shape(name, "verts", verts, (None, None, 3))
        check_float(name, "verts", verts)
        if verts.device != self.device:
            raise ValueError(
                f"{name}(): verts are on {verts.device} but this VisibilityContext's faces are on {self.device}"
            )
        if not 0.0 <= eps < 1.0:
            raise ValueError(f"{name}(): eps must lie in [0, 1) (a relative distance tolerance), got {eps}")
        num_frames, num_verts = verts.shape[0], verts.shape[1]
        if self._max_index >= num_verts:
            raise ValueError(
                f"{name}(): faces index vertex {self._max_index} but verts has only {num_verts} per frame"
            )
        verts = verts.detach().contiguous()
        visible = torch.zeros((num_frames, num_verts), dtype=torch.bool, device=self.device)
        if num_frames == 0 or num_verts == 0:
            return visible
        if self.faces.shape[0] == 0:
            return verts[..., 2] > 0
        with stream_of(verts):
            if self.mesh is None or self._shape != (num_frames, num_verts):
                self._build(num_frames, num_verts, verts)
            else:
                wp.copy(self._points, to_wp(verts.reshape(-1, 3), wp.vec3))
                self.mesh.refit()
                self.num_refits += 1
            wp.launch(
                cast_visibility_kernel,
                dim=(num_frames, num_verts),
                inputs=[self.mesh.id, self._points, num_verts, float(eps)],
                outputs=[to_wp(visible)],
                device=wp_device(verts),
            )
        return visible


def vertex_visibility(verts: torch.Tensor, faces: torch.Tensor, eps: float = 1e-3) -> torch.Tensor:
    """Per-vertex visibility from the camera centre (BVH any-hit ray cast), see :class:`VisibilityContext`.

    Keeps a small cache of contexts keyed on (device, ``faces.data_ptr()``, ``faces.shape``) and
    checks the cached topology still equals ``faces``, so repeated calls with the same faces refit
    one BVH instead of building a new one.

    Args:
        verts: ``(T, N, 3)`` float32 vertices in OpenCV camera space (camera at the origin, +z forward).
        faces: ``(F, 3)`` integer vertex indices, same device as ``verts``.
        eps: relative distance tolerance (a hit nearer than ``(1 - eps) ||x||`` occludes ``x``).

    Returns:
        ``(T, N)`` bool. Concretely, ``out[t, n]`` is True when vertex n of frame t has ``z > 0`` and
        no face lies between the camera centre and it.

    Raises:
        ValueError: wrong shapes, mixed devices, out-of-range faces or eps.
        TypeError: non-float32 verts or non-integer faces.
    """
    check_shape("vertex_visibility", "faces", faces, (None, 3))
    if faces.device != getattr(verts, "device", faces.device):
        raise ValueError(
            f"vertex_visibility(): all inputs must be on one device, got verts on {verts.device}, faces on {faces.device}"
        )
    key = (str(faces.device), faces.data_ptr(), tuple(faces.shape))
    ctx = _cache.get(key)
    if ctx is None or not torch.equal(ctx.faces, faces.to(torch.int32)):
        ctx = VisibilityContext(faces)
        _cache[key] = ctx
        while len(_cache) > _CACHE_SIZE:
            _cache.popitem(last=False)
    else:
        _cache.move_to_end(key)
    return ctx(verts, eps)
