"""Hand-written adjoints of the soft silhouette (own Warp module, ``enable_backward=False``).

Warp's generated backward does not replay dynamic loops, so the per-pixel sum over faces cannot be
taped; the adjoint is written out instead. With x_j = delta_j d_j^2 / sigma and
A = 1 - exp(S), S = sum_j log(1 - sigmoid(x_j)):

    dA/dx_j = exp(S) sigmoid(x_j) = (1 - A) D_j        (no division, so no trouble at D_j -> 1)

and d^2 = |p - q|^2 with q = v_k + s (v_{k+1} - v_k) the closest point of the nearest edge k. By the
envelope theorem ds does not contribute, so dd^2/dv_k = -2 (1 - s)(p - q), dd^2/dv_{k+1} = -2 s (p - q).
Gradients of faces on either side of a shared edge nearly cancel, so they are summed in float64.
"""

from __future__ import annotations

import warp as wp

from .raster_forward import outside_box_func, triangle_sq_dist_func

wp.set_module_options({"enable_backward": False})


@wp.func
def coverage_sq_dist_grad_func(p: wp.vec2, a: wp.vec2, b: wp.vec2, c: wp.vec2, g: float, inv_sigma: float, cutoff: float):
    """Adjoints (float64) of a, b, c for upstream dA/dS-weight g = dL/dA exp(S) at pixel p."""
    d2, k, s, diff, inside = triangle_sq_dist_func(p, a, b, c)
    ga = wp.vec2d()
    gb = wp.vec2d()
    gc = wp.vec2d()
    if inside or d2 < cutoff:
        x = d2 * inv_sigma
        sgn = inv_sigma
        if not inside:
            x = -x
            sgn = -inv_sigma
        dd2 = g * sgn / (1.0 + wp.exp(-x))  # dL/dd^2 = g D_j delta_j / sigma
        g0 = wp.vec2d(-2.0 * dd2 * (1.0 - s) * diff)
        g1 = wp.vec2d(-2.0 * dd2 * s * diff)
        if k == 0:
            ga = g0
            gb = g1
        elif k == 1:
            gb = g0
            gc = g1
        else:
            gc = g0
            ga = g1
    return ga, gb, gc


@wp.kernel
def soft_silhouette_grad_kernel(
    xy: wp.array2d(dtype=wp.vec2),
    faces: wp.array(dtype=wp.vec3i),
    bin_faces: wp.array(dtype=wp.int32),
    entry_bin: wp.array(dtype=wp.int32),
    gpix: wp.array3d(dtype=float),
    tile: int,
    ntx: int,
    bins_per_frame: int,
    width: int,
    height: int,
    inv_sigma: float,
    cutoff: float,
    # outputs
    entry_grad: wp.array2d(dtype=wp.vec2d),
):
    """One thread per (tile, face) entry of the CSR lists: loop over the tile's pixels and sum, in
    float64 and without atomics, the adjoints of the face's three projected vertices."""
    e = wp.tid()
    bn = entry_bin[e]
    f = bin_faces[e]
    t = bn // bins_per_frame
    rem = bn - t * bins_per_frame
    ty = rem // ntx
    tx = rem - ty * ntx
    r0 = ty * tile
    c0 = tx * tile
    r1 = wp.min(r0 + tile, height)
    c1 = wp.min(c0 + tile, width)
    i = faces[f]
    a = xy[t, i[0]]
    b = xy[t, i[1]]
    c = xy[t, i[2]]
    ga = wp.vec2d()
    gb = wp.vec2d()
    gc = wp.vec2d()
    for r in range(r0, r1):
        for col in range(c0, c1):
            g = gpix[t, r, col]
            if g != 0.0:
                da, db, dc = coverage_sq_dist_grad_func(wp.vec2(float(col), float(r)), a, b, c, g, inv_sigma, cutoff)
                ga += da
                gb += db
                gc += dc
    entry_grad[e, 0] = ga
    entry_grad[e, 1] = gb
    entry_grad[e, 2] = gc


@wp.kernel
def soft_silhouette_grad_naive_kernel(
    xy: wp.array2d(dtype=wp.vec2),
    faces: wp.array(dtype=wp.vec3i),
    front: wp.array2d(dtype=wp.int32),
    gpix: wp.array3d(dtype=float),
    radius: float,
    inv_sigma: float,
    cutoff: float,
    # outputs
    grad_xy: wp.array2d(dtype=wp.vec2d),
):
    """SoftRas-style O(pixels x faces) adjoint: each pixel re-visits every face and adds its
    vertex adjoints atomically into a float64 (T, V) buffer."""
    t, r, col = wp.tid()
    g = gpix[t, r, col]
    if g == 0.0:
        return
    p = wp.vec2(float(col), float(r))
    for f in range(faces.shape[0]):
        if front[t, f] == 0:
            continue
        i = faces[f]
        a = xy[t, i[0]]
        b = xy[t, i[1]]
        c = xy[t, i[2]]
        if outside_box_func(p, a, b, c, radius):
            continue
        da, db, dc = coverage_sq_dist_grad_func(p, a, b, c, g, inv_sigma, cutoff)
        wp.atomic_add(grad_xy, t, i[0], da)
        wp.atomic_add(grad_xy, t, i[1], db)
        wp.atomic_add(grad_xy, t, i[2], dc)
