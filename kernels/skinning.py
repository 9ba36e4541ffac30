"""Gaussian skinning weights and linear blend skinning (paper eq. 3) as differentiable torch ops.

Two ops, each a Warp forward kernel plus hand-written Warp adjoint kernels (no tape: the forward
kernels accumulate in dynamic loops over bones, which Warp's generated backward does not replay):

* :func:`skinning_weights` -- ``W[n, b] = softmax_b(-1/2 (x_n - c_b)^T Q_b (x_n - c_b))``. A Warp
  kernel over (N, B) computes the logits, ``torch.softmax`` normalises them (max-shifted, so a bone
  far from every vertex gets weights ~0 and never NaN).
* :func:`blend_skinning` -- ``X_n^t = T_0^t (sum_b W[n, b] T_b^t) X_n^0``. The root is folded into
  the bones in torch first (``M_b^t = [R_0 R_b | R_0 t_b]``, T*B tiny 3x4 products that torch
  differentiates), then a Warp kernel blends ``sum_b W[n, b] M_b^t`` per (frame, vertex) and applies
  it; ``t_0`` is added last. Backward: per-vertex threads loop over bones and frames for dX and dW
  (via ``h_nb = sum_t M_tb^T g_tn``, so nothing but the inputs is saved from the forward);
  per-(chunk, frame, bone) threads loop over the chunk's vertices for dM (no atomics; chunk partial
  sums are added in torch; one chunk on the CPU, many on CUDA).
"""

from __future__ import annotations

import torch
import warp as wp

from ._warp import check_float, check_shape, same_device, stream_of, to_wp, wp_device

__all__ = ["skinning_weights", "blend_skinning"]

# Every adjoint here is written by hand; skip Warp's generated backward (halves compile time).
wp.set_module_options({"enable_backward": False})

mat34 = wp.types.matrix(shape=(3, 4), dtype=wp.float32)
"""A rigid (or affine) transform ``[R | t]`` that maps ``x -> R x + t``."""

_CUDA_CHUNK = 256  # vertices per partial sum of the per-bone reductions on CUDA


# ----------------------------------------------------------------------------------------------
# Kernels: Gaussian logits
# ----------------------------------------------------------------------------------------------


@wp.kernel
def compute_logits_kernel(
    verts: wp.array(dtype=wp.vec3),
    centers: wp.array(dtype=wp.vec3),
    precisions: wp.array(dtype=wp.mat33),
    # outputs
    logits: wp.array2d(dtype=wp.float32),
):
    """logits[n, b] = -1/2 d^T Q_b d with d = x_n - c_b."""
    n, b = wp.tid()
    d = verts[n] - centers[b]
    logits[n, b] = -0.5 * wp.dot(d, precisions[b] * d)


@wp.kernel
def grad_logits_verts_kernel(
    verts: wp.array(dtype=wp.vec3),
    centers: wp.array(dtype=wp.vec3),
    precisions: wp.array(dtype=wp.mat33),
    grad_logits: wp.array2d(dtype=wp.float32),
    # outputs
    grad_verts: wp.array(dtype=wp.vec3),
):
    """Per-vertex thread: dL/dx_n = -1/2 sum_b g[n, b] (Q_b + Q_b^T) d_nb."""
    n = wp.tid()
    x = verts[n]
    acc = wp.vec3()
    for b in range(centers.shape[0]):
        d = x - centers[b]
        q = precisions[b]
        acc = acc - 0.5 * grad_logits[n, b] * (q * d + wp.transpose(q) * d)
    grad_verts[n] = acc


@wp.kernel
def grad_logits_bones_kernel(
    verts: wp.array(dtype=wp.vec3),
    centers: wp.array(dtype=wp.vec3),
    precisions: wp.array(dtype=wp.mat33),
    grad_logits: wp.array2d(dtype=wp.float32),
    chunk: int,
    # outputs
    grad_centers: wp.array2d(dtype=wp.vec3),
    grad_precisions: wp.array2d(dtype=wp.mat33),
):
    """Per-(chunk s, bone b) thread: partial sums over the chunk's vertices of dL/dc_b and dL/dQ_b."""
    s, b = wp.tid()
    c = centers[b]
    q = precisions[b]
    qs = q + wp.transpose(q)
    n0 = s * chunk
    n1 = wp.min(n0 + chunk, verts.shape[0])
    gc = wp.vec3()
    gq = wp.mat33()
    for n in range(n0, n1):
        d = verts[n] - c
        g = grad_logits[n, b]
        gc = gc + 0.5 * g * (qs * d)
        gq = gq - 0.5 * g * wp.outer(d, d)
    grad_centers[s, b] = gc
    grad_precisions[s, b] = gq


# ----------------------------------------------------------------------------------------------
# Kernels: linear blend skinning with root folded into the bones
# ----------------------------------------------------------------------------------------------


@wp.kernel
def blend_vertices_kernel(
    verts: wp.array(dtype=wp.vec3),
    weights: wp.array2d(dtype=wp.float32),
    transforms: wp.array2d(dtype=mat34),
    # outputs
    posed: wp.array2d(dtype=wp.vec3),
):
    """Per-(frame t, vertex n) thread: A = sum_b W[n, b] M[t, b]; posed[t, n] = A [x_n; 1]."""
    t, n = wp.tid()
    a = mat34()
    for b in range(weights.shape[1]):
        a = a + weights[n, b] * transforms[t, b]
    x = verts[n]
    posed[t, n] = a * wp.vec4(x[0], x[1], x[2], 1.0)


@wp.kernel
def grad_blend_vertices_kernel(
    verts: wp.array(dtype=wp.vec3),
    weights: wp.array2d(dtype=wp.float32),
    transforms: wp.array2d(dtype=mat34),
    grad_posed: wp.array2d(dtype=wp.vec3),
    # outputs
    grad_verts: wp.array(dtype=wp.vec3),
    grad_weights: wp.array2d(dtype=wp.float32),
):
    """Per-vertex thread, with h_nb = sum_t M_tb^T g_tn (a 4-vector):

    dW[n, b] = h_nb . [x_n; 1] and dx_n = sum_b W[n, b] h_nb[:3].
    """
    n = wp.tid()
    x = verts[n]
    xh = wp.vec4(x[0], x[1], x[2], 1.0)
    gx = wp.vec4()
    for b in range(transforms.shape[1]):
        h = wp.vec4()
        for t in range(grad_posed.shape[0]):
            h = h + wp.transpose(transforms[t, b]) * grad_posed[t, n]
        grad_weights[n, b] = wp.dot(h, xh)
        gx = gx + weights[n, b] * h
    grad_verts[n] = wp.vec3(gx[0], gx[1], gx[2])


@wp.kernel
def grad_blend_transforms_kernel(
    verts: wp.array(dtype=wp.vec3),
    weights_t: wp.array2d(dtype=wp.float32),
    grad_posed: wp.array2d(dtype=wp.vec3),
    chunk: int,
    # outputs
    grad_transforms: wp.array3d(dtype=mat34),
):
    """Per-(chunk s, frame t, bone b) thread: dM[t, b] partial = sum_n W[n, b] g_tn [x_n; 1]^T.

    ``weights_t`` is W transposed, ``(B, N)``, so that the loop over n reads it contiguously.
    """
    s, t, b = wp.tid()
    n0 = s * chunk
    n1 = wp.min(n0 + chunk, verts.shape[0])
    r0 = wp.vec4()
    r1 = wp.vec4()
    r2 = wp.vec4()
    for n in range(n0, n1):
        x = verts[n]
        wx = weights_t[b, n] * wp.vec4(x[0], x[1], x[2], 1.0)
        g = grad_posed[t, n]
        r0 = r0 + g[0] * wx
        r1 = r1 + g[1] * wx
        r2 = r2 + g[2] * wx
    # rows of the 3x4 adjoint (row-wise accumulators vectorise better than a mat34 outer product)
    grad_transforms[s, t, b] = mat34(
        r0[0], r0[1], r0[2], r0[3], r1[0], r1[1], r1[2], r1[3], r2[0], r2[1], r2[2], r2[3]
    )


# ----------------------------------------------------------------------------------------------
# torch ops
# ----------------------------------------------------------------------------------------------


def _chunking(n: int, device: torch.device) -> tuple[int, int]:
    """(chunk, count): one chunk on the CPU (Warp runs one thread), _CUDA_CHUNK-vertex ones on CUDA."""
    if device.type == "cpu" or n == 0:
        return max(n, 1), 1
    return _CUDA_CHUNK, (n + _CUDA_CHUNK - 1) // _CUDA_CHUNK


class _SkinningLogitsFn(torch.autograd.Function):
    @staticmethod
    def forward(ctx, verts, centers, precisions):
        ctx.save_for_backward(verts, centers, precisions)
        n, b = verts.shape[0], centers.shape[0]
        logits = torch.empty((n, b), dtype=torch.float32, device=verts.device)
        dev = wp_device(verts)
        with stream_of(verts):
            wp.launch(
                compute_logits_kernel,
                dim=(n, b),
                inputs=[to_wp(verts, wp.vec3), to_wp(centers, wp.vec3), to_wp(precisions, wp.mat33)],
                outputs=[to_wp(logits)],
                device=dev,
            )
        return logits

    @staticmethod
    def backward(ctx, grad_logits):
        verts, centers, precisions = ctx.saved_tensors
        n, b = verts.shape[0], centers.shape[0]
        dev = wp_device(verts)
        g = to_wp(grad_logits.contiguous())
        wv, wc, wq = to_wp(verts, wp.vec3), to_wp(centers, wp.vec3), to_wp(precisions, wp.mat33)
        gv = gc = gq = None
        with stream_of(verts):
            if ctx.needs_input_grad[0]:
                gv = torch.empty_like(verts)
                wp.launch(
                    grad_logits_verts_kernel,
                    dim=n,
                    inputs=[wv, wc, wq, g],
                    outputs=[to_wp(gv, wp.vec3)],
                    device=dev,
                )
            if ctx.needs_input_grad[1] or ctx.needs_input_grad[2]:
                chunk, count = _chunking(n, verts.device)
                pc = torch.empty((count, b, 3), dtype=torch.float32, device=verts.device)
                pq = torch.empty((count, b, 3, 3), dtype=torch.float32, device=verts.device)
                wp.launch(
                    grad_logits_bones_kernel,
                    dim=(count, b),
                    inputs=[wv, wc, wq, g, chunk],
                    outputs=[to_wp(pc, wp.vec3), to_wp(pq, wp.mat33)],
                    device=dev,
                )
                gc = pc.sum(0) if ctx.needs_input_grad[1] else None
                gq = pq.sum(0) if ctx.needs_input_grad[2] else None
        return gv, gc, gq


class _BlendFn(torch.autograd.Function):
    @staticmethod
    def forward(ctx, verts, weights, transforms):
        ctx.save_for_backward(verts, weights, transforms)
        t, n = transforms.shape[0], verts.shape[0]
        posed = torch.empty((t, n, 3), dtype=torch.float32, device=verts.device)
        with stream_of(verts):
            wp.launch(
                blend_vertices_kernel,
                dim=(t, n),
                inputs=[to_wp(verts, wp.vec3), to_wp(weights), to_wp(transforms, mat34)],
                outputs=[to_wp(posed, wp.vec3)],
                device=wp_device(verts),
            )
        return posed

    @staticmethod
    def backward(ctx, grad_posed):
        verts, weights, transforms = ctx.saved_tensors
        t, b, n = transforms.shape[0], transforms.shape[1], verts.shape[0]
        dev = wp_device(verts)
        g = to_wp(grad_posed.contiguous(), wp.vec3)
        wv, ww = to_wp(verts, wp.vec3), to_wp(weights)
        gv = gw = gm = None
        with stream_of(verts):
            if ctx.needs_input_grad[0] or ctx.needs_input_grad[1]:
                gv = torch.empty_like(verts)
                gw = torch.empty_like(weights)
                wp.launch(
                    grad_blend_vertices_kernel,
                    dim=n,
                    inputs=[wv, ww, to_wp(transforms, mat34), g],
                    outputs=[to_wp(gv, wp.vec3), to_wp(gw)],
                    device=dev,
                )
            if ctx.needs_input_grad[2]:
                chunk, count = _chunking(n, verts.device)
                part = torch.empty((count, t, b, 3, 4), dtype=torch.float32, device=verts.device)
                wp.launch(
                    grad_blend_transforms_kernel,
                    dim=(count, t, b),
                    inputs=[wv, to_wp(weights.t().contiguous()), g, chunk],
                    outputs=[to_wp(part, mat34)],
                    device=dev,
                )
                gm = part.sum(0) if count > 1 else part[0]
        return (
            gv if ctx.needs_input_grad[0] else None,
            gw if ctx.needs_input_grad[1] else None,
            gm,
        )


def skinning_weights(verts: torch.Tensor, centers: torch.Tensor, precisions: torch.Tensor) -> torch.Tensor:
    """Normalised Gaussian skinning weights ``W[n, b] = softmax_b(-1/2 (x_n - c_b)^T Q_b (x_n - c_b))``.

    ``Q_b`` is bone b's precision (inverse covariance) matrix, ``c_b`` its Gaussian centre (paper
    sec. 3.1). The softmax is max-shifted, so a bone far from every vertex gets weights ~0, never
    NaN. Gradients flow to all three inputs; the gradient to ``precisions`` is the plain derivative of
    the formula (not symmetrised), ``-1/2 sum_n g[n, b] d d^T``.

    Args:
        verts: ``(N, 3)`` float32 vertex positions (canonical object frame).
        centers: ``(B, 3)`` float32 bone Gaussian centres (same frame and units).
        precisions: ``(B, 3, 3)`` float32 precision matrices (inverse squared units).

    Returns:
        ``(N, B)`` float32 weights; each row sums to 1. Same device as the inputs.

    Raises:
        ValueError: wrong shapes or inputs on different devices.
        TypeError: a non-float32 input.
    """
    name = "skinning_weights"
    check_shape(name, "verts", verts, (None, 3))
    check_shape(name, "centers", centers, (None, 3))
    check_shape(name, "precisions", precisions, (centers.shape[0], 3, 3))
    if centers.shape[0] == 0:
        raise ValueError(f"{name}(): need at least one bone, got centers of shape {tuple(centers.shape)}")
    for arg, t in (("verts", verts), ("centers", centers), ("precisions", precisions)):
        check_float(name, arg, t)
    same_device(name, verts, centers, precisions)
    logits = _SkinningLogitsFn.apply(verts.contiguous(), centers.contiguous(), precisions.contiguous())
    return torch.softmax(logits, dim=1)


def blend_skinning(
    verts: torch.Tensor, weights: torch.Tensor, bone_rt: torch.Tensor, root_rt: torch.Tensor
) -> torch.Tensor:
    """Linear blend skinning, paper eq. 3: ``X_n^t = T_0^t (sum_b W[n, b] T_b^t) X_n^0``.

    A 3x4 ``[R | t]`` maps ``x -> R x + t``. Bones rotating about their own centres is the model's
    business (it folds the pivot into ``t``). ``weights`` are used as given (not renormalised).
    Gradients flow to every input.

    Args:
        verts: ``(N, 3)`` float32 canonical (rest) vertices ``X^0``, object frame.
        weights: ``(N, B)`` float32 skinning weights ``W``.
        bone_rt: ``(T, B, 3, 4)`` float32 per-frame bone transforms ``T_b^t`` (object frame).
        root_rt: ``(T, 3, 4)`` float32 per-frame root transforms ``T_0^t`` (object to camera).

    Returns:
        ``(T, N, 3)`` float32 posed vertices ``X^t`` in the root's target frame (camera space).

    Raises:
        ValueError: wrong shapes or inputs on different devices.
        TypeError: a non-float32 input.
    """
    name = "blend_skinning"
    check_shape(name, "verts", verts, (None, 3))
    check_shape(name, "weights", weights, (verts.shape[0], None))
    check_shape(name, "bone_rt", bone_rt, (None, weights.shape[1], 3, 4))
    check_shape(name, "root_rt", root_rt, (bone_rt.shape[0], 3, 4))
    for arg, t in (("verts", verts), ("weights", weights), ("bone_rt", bone_rt), ("root_rt", root_rt)):
        check_float(name, arg, t)
    same_device(name, verts, weights, bone_rt, root_rt)
    # Fold the root into the bones: M_b^t = [R_0 R_b | R_0 t_b] (T*B 3x4 products; torch differentiates).
    transforms = torch.matmul(root_rt[:, None, :, :3], bone_rt)
    posed = _BlendFn.apply(verts.contiguous(), weights.contiguous(), transforms.contiguous())
    return posed + root_rt[:, None, :, 3]
