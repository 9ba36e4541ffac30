"""Mesh regularisers as differentiable torch ops: dynamic rigidity (eq. 1-2), ARAP, Laplacian (eq. 17),
symmetry (eq. 16), plus the ``mesh_edges`` helper.

The heavy per-element work runs in Warp kernels with hand-written adjoints (no tape, no atomics):

* per-vertex skinning entropy ``H_i`` (a loop over bones) and its elementwise adjoint;
* per-(frame pair, edge) length change ``| ||x_i^t - x_j^t|| - ||x_i^{t+1} - x_j^{t+1}|| |`` and its
  adjoint per-(frame, edge) with respect to the edge vector; the scatter from edges to vertices is a
  torch ``index_add_``;
* the umbrella Laplacian ``delta_i = x_i - mean_{j in N_i} x_j`` over a CSR neighbour list, whose
  adjoint is a gather over the same (symmetric) list;
* a brute-force nearest-neighbour search (forward only; the arg-min is not differentiated).

The small O(E) and O(N) combinations around them (rigidity ``R_ij``, means, squares) are torch.
"""

from __future__ import annotations

import math

import torch
import warp as wp

from ._warp import (
    check_float,
    cached,
    check_shape,
    frame_chunks,
    index_bounds,
    map_chunks,
    same_device,
    stream_of,
    to_wp,
    wp_device,
)

__all__ = ["mesh_edges", "dynamic_rigidity_loss", "arap_loss", "laplacian_loss", "symmetry_loss"]

# Every adjoint here is written by hand; skip Warp's generated backward (halves compile time).
wp.set_module_options({"enable_backward": False})

ENTROPY_EPS = 1e-8
"""Weights are clamped to at least this inside ``log2`` so that ``W log2 W -> 0`` for ``W -> 0``."""

_INV_LN2 = 1.0 / math.log(2.0)


# ----------------------------------------------------------------------------------------------
# Kernels
# ----------------------------------------------------------------------------------------------


@wp.kernel
def compute_entropy_kernel(
    weights: wp.array2d(dtype=wp.float32),
    eps: float,
    # outputs
    entropy: wp.array(dtype=wp.float32),
):
    """Per-vertex thread: H_n = -sum_b W[n, b] log2(max(W[n, b], eps))."""
    n = wp.tid()
    h = float(0.0)
    for b in range(weights.shape[1]):
        w = weights[n, b]
        h -= w * wp.log2(wp.max(w, eps))
    entropy[n] = h


@wp.kernel
def grad_entropy_kernel(
    weights: wp.array2d(dtype=wp.float32),
    grad_entropy: wp.array(dtype=wp.float32),
    eps: float,
    inv_ln2: float,
    # outputs
    grad_weights: wp.array2d(dtype=wp.float32),
):
    """Per-(vertex, bone) thread: dH_n/dW = -(log2(max(W, eps)) + [W >= eps] / ln 2)."""
    n, b = wp.tid()
    w = weights[n, b]
    d = wp.log2(wp.max(w, eps))
    if w >= eps:
        d += inv_ln2
    grad_weights[n, b] = -grad_entropy[n] * d


@wp.func
def edge_length(verts: wp.array2d(dtype=wp.vec3), t: int, i: int, j: int):
    return wp.length(verts[t, i] - verts[t, j])


@wp.func
def sign_of(x: float):
    s = float(0.0)
    if x > 0.0:
        s = 1.0
    elif x < 0.0:
        s = -1.0
    return s


@wp.kernel
def compute_edge_stretch_kernel(
    verts: wp.array2d(dtype=wp.vec3),
    edges: wp.array(dtype=wp.vec2i),
    # outputs
    stretch: wp.array2d(dtype=wp.float32),
):
    """Per-(frame pair t, edge e) thread: | ||x_i^t - x_j^t|| - ||x_i^{t+1} - x_j^{t+1}|| |."""
    t, e = wp.tid()
    ij = edges[e]
    stretch[t, e] = wp.abs(edge_length(verts, t, ij[0], ij[1]) - edge_length(verts, t + 1, ij[0], ij[1]))


@wp.kernel
def grad_edge_stretch_kernel(
    verts: wp.array2d(dtype=wp.vec3),
    edges: wp.array(dtype=wp.vec2i),
    grad_stretch: wp.array2d(dtype=wp.float32),
    # outputs
    grad_edge: wp.array2d(dtype=wp.vec3),
):
    """Per-(frame t, edge e) thread: gradient w.r.t. the edge vector d = x_i^t - x_j^t (gathers terms t-1, t).

    Written edge-major, ``grad_edge[e, t]``, so that the scatter to vertices adds contiguous rows.

    The derivative of a zero-length edge's length is taken as 0 (as torch's norm does), and of |0| as 0.
    """
    t, e = wp.tid()
    ij = edges[e]
    d = verts[t, ij[0]] - verts[t, ij[1]]
    lt = wp.length(d)
    u = wp.vec3()
    if lt > 0.0:
        u = d / lt
    c = float(0.0)
    num_t = verts.shape[0]
    if t + 1 < num_t:
        c += grad_stretch[t, e] * sign_of(lt - edge_length(verts, t + 1, ij[0], ij[1]))
    if t > 0:
        c -= grad_stretch[t - 1, e] * sign_of(edge_length(verts, t - 1, ij[0], ij[1]) - lt)
    grad_edge[e, t] = c * u


@wp.kernel
def compute_umbrella_kernel(
    verts: wp.array(dtype=wp.vec3),
    offsets: wp.array(dtype=wp.int32),
    neighbours: wp.array(dtype=wp.int32),
    # outputs
    delta: wp.array(dtype=wp.vec3),
):
    """Per-vertex thread: delta_i = x_i - mean_{j in N_i} x_j (0 for a vertex with no neighbours)."""
    i = wp.tid()
    k0 = offsets[i]
    k1 = offsets[i + 1]
    if k1 == k0:
        delta[i] = wp.vec3()
        return
    s = wp.vec3()
    for k in range(k0, k1):
        s = s + verts[neighbours[k]]
    delta[i] = verts[i] - s / float(k1 - k0)


@wp.kernel
def grad_umbrella_kernel(
    offsets: wp.array(dtype=wp.int32),
    neighbours: wp.array(dtype=wp.int32),
    grad_delta: wp.array(dtype=wp.vec3),
    # outputs
    grad_verts: wp.array(dtype=wp.vec3),
):
    """Per-vertex thread: dx_k = g_k - sum_{i in N_k} g_i / |N_i| (the neighbour relation is symmetric)."""
    k = wp.tid()
    k0 = offsets[k]
    k1 = offsets[k + 1]
    if k1 == k0:
        grad_verts[k] = wp.vec3()
        return
    s = wp.vec3()
    for m in range(k0, k1):
        i = neighbours[m]
        s = s + grad_delta[i] / float(offsets[i + 1] - offsets[i])
    grad_verts[k] = grad_delta[k] - s


@wp.kernel
def find_nearest_kernel(
    queries: wp.array(dtype=wp.vec3),
    points: wp.array(dtype=wp.vec3),
    # outputs
    nearest: wp.array(dtype=wp.int32),
):
    """Per-query thread, brute force: index of the closest point (the first one on ties)."""
    q = wp.tid()
    x = queries[q]
    best = float(3.0e38)
    arg = int(0)
    for j in range(points.shape[0]):
        d = wp.length_sq(points[j] - x)
        if d < best:
            best = d
            arg = j
    nearest[q] = arg


# ----------------------------------------------------------------------------------------------
# autograd Functions
# ----------------------------------------------------------------------------------------------


class _EntropyFn(torch.autograd.Function):
    @staticmethod
    def forward(ctx, weights):
        ctx.save_for_backward(weights)
        h = torch.empty(weights.shape[0], dtype=torch.float32, device=weights.device)
        with stream_of(weights):
            wp.launch(
                compute_entropy_kernel,
                dim=weights.shape[0],
                inputs=[to_wp(weights), ENTROPY_EPS],
                outputs=[to_wp(h)],
                device=wp_device(weights),
            )
        return h

    @staticmethod
    def backward(ctx, grad_h):
        (weights,) = ctx.saved_tensors
        gw = torch.empty_like(weights)
        with stream_of(weights):
            wp.launch(
                grad_entropy_kernel,
                dim=tuple(weights.shape),
                inputs=[to_wp(weights), to_wp(grad_h.contiguous()), ENTROPY_EPS, _INV_LN2],
                outputs=[to_wp(gw)],
                device=wp_device(weights),
            )
        return gw


class _EdgeStretchFn(torch.autograd.Function):
    @staticmethod
    def forward(ctx, verts, edges):
        ctx.save_for_backward(verts, edges)
        t, e = verts.shape[0], edges.shape[0]
        s = torch.empty((t - 1, e), dtype=torch.float32, device=verts.device)
        with stream_of(verts):
            wp.launch(
                compute_edge_stretch_kernel,
                dim=(t - 1, e),
                inputs=[to_wp(verts, wp.vec3), to_wp(edges, wp.vec2i)],
                outputs=[to_wp(s)],
                device=wp_device(verts),
            )
        return s

    @staticmethod
    def backward(ctx, grad_s):
        verts, edges = ctx.saved_tensors
        t, e = verts.shape[0], edges.shape[0]
        ge = torch.empty((e, t, 3), dtype=torch.float32, device=verts.device)
        with stream_of(verts):
            wp.launch(
                grad_edge_stretch_kernel,
                dim=(t, e),
                inputs=[to_wp(verts, wp.vec3), to_wp(edges, wp.vec2i), to_wp(grad_s.contiguous())],
                outputs=[to_wp(ge, wp.vec3)],
                device=wp_device(verts),
            )
        n = verts.shape[1]
        gv = torch.zeros((n, t * 3), dtype=torch.float32, device=verts.device)
        idx = edges.long()
        ge = ge.view(e, t * 3)
        gv.index_add_(0, idx[:, 0], ge)
        gv.index_add_(0, idx[:, 1], ge, alpha=-1.0)
        return gv.view(n, t, 3).transpose(0, 1).contiguous(), None


class _UmbrellaFn(torch.autograd.Function):
    @staticmethod
    def forward(ctx, verts, offsets, neighbours):
        ctx.save_for_backward(offsets, neighbours)
        delta = torch.empty_like(verts)
        with stream_of(verts):
            wp.launch(
                compute_umbrella_kernel,
                dim=verts.shape[0],
                inputs=[to_wp(verts, wp.vec3), to_wp(offsets), to_wp(neighbours)],
                outputs=[to_wp(delta, wp.vec3)],
                device=wp_device(verts),
            )
        return delta

    @staticmethod
    def backward(ctx, grad_delta):
        offsets, neighbours = ctx.saved_tensors
        gv = torch.empty_like(grad_delta)
        with stream_of(grad_delta):
            wp.launch(
                grad_umbrella_kernel,
                dim=grad_delta.shape[0],
                inputs=[to_wp(offsets), to_wp(neighbours), to_wp(grad_delta.contiguous(), wp.vec3)],
                outputs=[to_wp(gv, wp.vec3)],
                device=wp_device(grad_delta),
            )
        return gv, None, None


def _nearest(queries: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """``(N,)`` int64 index of the point nearest to each query (brute force Warp kernel, no gradient; on the CPU the
    queries in ranges side by side)."""
    idx = torch.empty(queries.shape[0], dtype=torch.int32, device=queries.device)
    q, pts = queries.detach().contiguous(), to_wp(points.detach(), wp.vec3)

    def launch(s: slice) -> None:
        with stream_of(queries):
            wp.launch(find_nearest_kernel, dim=s.stop - s.start, inputs=[to_wp(q[s], wp.vec3), pts],
                      outputs=[to_wp(idx[s])], device=wp_device(queries))

    map_chunks(launch, frame_chunks(queries, queries.shape[0]))
    return idx.long()


# ----------------------------------------------------------------------------------------------
# Validation helpers
# ----------------------------------------------------------------------------------------------


def _check_index(name: str, arg: str, idx: torch.Tensor, cols: int, num_verts: int) -> torch.Tensor:
    """Check an integer index tensor ``(K, cols)`` with values in [0, num_verts); return it as int32."""
    check_shape(name, arg, idx, (None, cols))
    if idx.dtype.is_floating_point or idx.dtype == torch.bool or idx.is_complex():
        raise TypeError(f"{name}(): {arg} must be an integer tensor, got {idx.dtype}")
    lo, hi = index_bounds(idx, (0, num_verts - 1)) if idx.numel() else (0, 0)
    if lo < 0 or hi >= num_verts:
        raise ValueError(f"{name}(): {arg} indices must lie in [0, {num_verts}) (the vertex count), got [{lo}, {hi}]")
    return idx.to(torch.int32).contiguous()


def _check_verts(name: str, verts: torch.Tensor, batched: bool) -> None:
    check_shape(name, "verts", verts, (None, None, 3) if batched else (None, 3))
    check_float(name, "verts", verts)


# ----------------------------------------------------------------------------------------------
# Public ops
# ----------------------------------------------------------------------------------------------


def mesh_edges(faces: torch.Tensor) -> torch.Tensor:
    """Unique undirected edges of a triangle mesh.

    Args:
        faces: ``(F, 3)`` integer vertex indices.

    Returns:
        ``(E, 2)`` int64 edges, each stored once as ``(i, j)`` with ``i < j``, sorted
        lexicographically; same device as ``faces``.

    Raises:
        ValueError: ``faces`` is not ``(F, 3)``.
        TypeError: ``faces`` is not an integer tensor.
    """
    check_shape("mesh_edges", "faces", faces, (None, 3))
    if faces.dtype.is_floating_point or faces.dtype == torch.bool:
        raise TypeError(f"mesh_edges(): faces must be an integer tensor, got {faces.dtype}")
    f = faces.long()
    e = f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    lo, hi = torch.minimum(e[:, 0], e[:, 1]), torch.maximum(e[:, 0], e[:, 1])
    keep = lo != hi  # degenerate faces repeat a vertex
    lo, hi = lo[keep], hi[keep]
    if lo.numel() == 0:
        return torch.zeros((0, 2), dtype=torch.int64, device=faces.device)
    # unique on one int64 key per edge (torch.unique(dim=0) is ~50x slower on the CPU)
    base = int(hi.max()) + 1
    key = torch.unique(lo * base + hi)
    return torch.stack([key // base, key % base], dim=1)


def _edge_weighted_stretch(name: str, verts: torch.Tensor, edges: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Validate (T, N, 3) verts and (E, 2) edges; return (edges int32, per-edge sum over t of stretch)."""
    _check_verts(name, verts, batched=True)
    if verts.shape[0] < 2:
        raise ValueError(f"{name}(): verts must hold at least 2 frames (T >= 2), got shape {tuple(verts.shape)}")
    edges32 = _check_index(name, "edges", edges, 2, verts.shape[1])
    if edges32.shape[0] == 0:
        raise ValueError(f"{name}(): edges is empty; pass mesh_edges(faces) of a mesh with at least one face")
    same_device(name, verts, edges)
    s = _EdgeStretchFn.apply(verts.contiguous(), edges32)
    return edges32, s.sum(0)


def dynamic_rigidity_loss(
    verts: torch.Tensor, edges: torch.Tensor, weights: torch.Tensor, lam: float = 0.1
) -> torch.Tensor:
    """Dynamic rigidity (DR), paper eq. 1-2 with the correction to eq. 1 that docs/method.md gives.

    ``H_i = -sum_b W[i, b] log2 W[i, b]`` is vertex i's skinning entropy (W clamped to
    ``ENTROPY_EPS`` inside the log); ``R_ij = 1 / ((H_i + lam) (H_j + lam))`` is the rigidity of
    mesh edge (i, j) (large inside a bone, small near joints; the paper's eq. 1 prints the negative
    entropy, which crosses zero). The loss is the mean over consecutive frames and edges:
    ``L = 1 / ((T-1) E) sum_t sum_(i,j) R_ij | ||x_i^t - x_j^t|| - ||x_i^{t+1} - x_j^{t+1}|| |``.
    Gradients flow to ``verts`` and ``weights``.

    Args:
        verts: ``(T, N, 3)`` float32 posed vertices per frame (any frame, consistent units), T >= 2.
        edges: ``(E, 2)`` integer mesh edges (e.g. :func:`mesh_edges`), E >= 1.
        weights: ``(N, B)`` float32 skinning weights (rows summing to 1).
        lam: ``lambda``, the stabiliser added to the entropy.

    Returns:
        Scalar float32 tensor (units of length).

    Raises:
        ValueError: wrong shapes, out-of-range or empty edges, T < 2, lam <= 0, mixed devices.
        TypeError: non-float32 verts/weights or non-integer edges.
    """
    name = "dynamic_rigidity_loss"
    if not lam > 0:
        raise ValueError(f"{name}(): lam must be > 0 (it keeps R_ij finite), got {lam}")
    _check_verts(name, verts, batched=True)
    check_shape(name, "weights", weights, (verts.shape[1], None))
    check_float(name, "weights", weights)
    same_device(name, verts, edges, weights)
    edges32, per_edge = _edge_weighted_stretch(name, verts, edges)
    h = _EntropyFn.apply(weights.contiguous()) + lam
    idx = edges32.long()
    rigidity = 1.0 / (h[idx[:, 0]] * h[idx[:, 1]])
    return (rigidity * per_edge).sum() / ((verts.shape[0] - 1) * edges32.shape[0])


def arap_loss(verts: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """As-rigid-as-possible baseline: :func:`dynamic_rigidity_loss` with ``R_ij = 1`` on every edge.

    ``L = 1 / ((T-1) E) sum_t sum_(i,j) | ||x_i^t - x_j^t|| - ||x_i^{t+1} - x_j^{t+1}|| |``. Note: LASR's
    ARAP compares *squared* edge lengths; we keep DR's non-squared ``|.|`` form so that the ablation
    DR vs ARAP differs only in ``R``. Gradients flow to ``verts``.

    Args:
        verts: ``(T, N, 3)`` float32 posed vertices per frame, T >= 2.
        edges: ``(E, 2)`` integer mesh edges, E >= 1.

    Returns:
        Scalar float32 tensor (units of length).

    Raises:
        ValueError: wrong shapes, out-of-range or empty edges, T < 2, mixed devices.
        TypeError: non-float32 verts or non-integer edges.
    """
    edges32, per_edge = _edge_weighted_stretch("arap_loss", verts, edges)
    return per_edge.sum() / ((verts.shape[0] - 1) * edges32.shape[0])


def _csr_neighbours(edges: torch.Tensor, num_verts: int) -> tuple[torch.Tensor, torch.Tensor]:
    """CSR of the symmetric neighbour relation: (offsets (N+1,) int32, neighbours (2E,) int32)."""
    src = torch.cat([edges[:, 0], edges[:, 1]])
    dst = torch.cat([edges[:, 1], edges[:, 0]])
    order = torch.argsort(src, stable=True)
    counts = torch.bincount(src, minlength=num_verts)
    offsets = torch.zeros(num_verts + 1, dtype=torch.int64, device=edges.device)
    offsets[1:] = torch.cumsum(counts, 0)
    return offsets.to(torch.int32), dst[order].to(torch.int32).contiguous()


def laplacian_loss(verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Laplacian smoothing, paper eq. 17, with the uniform (umbrella) Laplacian.

    ``L = 1/N sum_i || x_i - 1/|N_i| sum_{j in N_i} x_j ||^2`` where ``N_i`` are i's neighbours along
    mesh edges. A vertex in no face contributes 0 (it still counts in N). Gradients flow to ``verts``.

    Args:
        verts: ``(N, 3)`` float32 vertices (e.g. the canonical mesh ``X^0``).
        faces: ``(F, 3)`` integer triangle indices.

    Returns:
        Scalar float32 tensor (squared units of length).

    Raises:
        ValueError: wrong shapes, out-of-range faces, mixed devices.
        TypeError: non-float32 verts or non-integer faces.
    """
    name = "laplacian_loss"
    _check_verts(name, verts, batched=False)
    _check_index(name, "faces", faces, 3, verts.shape[0])
    same_device(name, verts, faces)
    offsets, neighbours = cached(faces, f"umbrella_csr_{verts.shape[0]}",  # the faces change only at a resampling
                                 lambda: _csr_neighbours(mesh_edges(faces), verts.shape[0]))
    delta = _UmbrellaFn.apply(verts.contiguous(), offsets, neighbours)
    return (delta * delta).sum() / max(verts.shape[0], 1)


def symmetry_loss(verts: torch.Tensor, plane: tuple) -> torch.Tensor:
    """Symmetry, paper eq. 16: ``L = 1/N sum_i min_j || v_j - phi(v_i) ||^2``.

    ``phi`` reflects across the plane ``{x : n . x = offset}`` with ``n`` the normalised ``normal``:
    ``phi(v) = v - 2 (n . v - offset) n``. The nearest vertex ``j`` to each reflected vertex is found
    by a brute-force Warp kernel (O(N^2), fine for N <= 5000) and not differentiated; gradients flow
    through ``v_j`` and ``v_i`` (and the plane, if its tensors require grad).

    Args:
        verts: ``(N, 3)`` float32 vertices (canonical object frame).
        plane: ``(normal, offset)``: ``normal`` a ``(3,)`` tensor or sequence (nonzero, need not be
            unit length), ``offset`` a float or 0-d tensor (signed distance of the plane from the origin
            along the normalised normal).

    Returns:
        Scalar float32 tensor (squared units of length).

    Raises:
        ValueError: wrong shapes, a zero or non-finite normal, a malformed plane, mixed devices.
        TypeError: non-float32 verts.
    """
    name = "symmetry_loss"
    _check_verts(name, verts, batched=False)
    if verts.shape[0] == 0:
        raise ValueError(f"{name}(): verts is empty, got shape {tuple(verts.shape)}")
    try:
        normal, offset = plane
    except (TypeError, ValueError):
        raise ValueError(f"{name}(): plane must be a pair (normal (3,), offset), got {type(plane).__name__}") from None
    normal = torch.as_tensor(normal, dtype=torch.float32, device=verts.device)
    offset = torch.as_tensor(offset, dtype=torch.float32, device=verts.device)
    if normal.shape != (3,) or offset.dim() != 0:
        raise ValueError(
            f"{name}(): plane must be (normal of shape (3,), scalar offset), got normal {tuple(normal.shape)} "
            f"and offset {tuple(offset.shape)}"
        )
    norm = cached(normal, "norm", lambda: float(torch.linalg.vector_norm(normal.detach())))  # one read per plane
    if not math.isfinite(norm) or norm == 0.0:
        raise ValueError(f"{name}(): plane normal must be finite and nonzero, got {normal.tolist()}")
    same_device(name, verts, normal, offset)
    n = normal / torch.linalg.vector_norm(normal)
    reflected = verts - 2.0 * ((verts @ n) - offset)[:, None] * n
    idx = _nearest(reflected.contiguous(), verts.contiguous())
    return ((verts[idx] - reflected) ** 2).sum() / verts.shape[0]
