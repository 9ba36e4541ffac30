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

from .raster_forward import outside_box_func, perspective_barycentrics_func, triangle_sq_dist_func

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


@wp.func
def cross2_adj_func(u: wp.vec2, v: wp.vec2, g: float):
    """Adjoints (du, dv) of cross(u, v) = u.x v.y - u.y v.x for upstream g."""
    return wp.vec2(g * v[1], -g * v[0]), wp.vec2(-g * u[1], g * u[0])


@wp.kernel
def barycentrics_grad_kernel(
    xy: wp.array2d(dtype=wp.vec2),
    z: wp.array2d(dtype=float),
    faces: wp.array(dtype=wp.vec3i),
    face_index: wp.array3d(dtype=wp.int32),
    g_bary: wp.array3d(dtype=wp.vec3),
    g_depth: wp.array3d(dtype=float),
    # outputs (accumulated)
    g_xy: wp.array2d(dtype=wp.vec2d),
    g_z: wp.array2d(dtype=wp.float64),
):
    """Adjoint of ``barycentrics_kernel``: with q_i = l_i / z_i, s = sum q, b = q / s, depth = 1 / s,

        dL/dq_i = (g_b_i - g_b . b) / s - g_depth / s^2,   dL/dl_i = dL/dq_i / z_i,   dL/dz_i = -dL/dq_i q_i / z_i,

    and l_i = e_i / area2 through the edge functions' cross products; summed per vertex in float64."""
    t, r, cpix = wp.tid()
    f = face_index[t, r, cpix]
    if f < 0:
        return
    i = faces[f]
    a = xy[t, i[0]]
    b = xy[t, i[1]]
    c = xy[t, i[2]]
    p = wp.vec2(float(cpix), float(r))
    zv = wp.vec3(z[t, i[0]], z[t, i[1]], z[t, i[2]])
    area2, lam, q = perspective_barycentrics_func(p, a, b, c, zv)
    s = q[0] + q[1] + q[2]
    bw = q / s
    gb = g_bary[t, r, cpix]
    gq = (gb - wp.vec3(wp.dot(gb, bw))) / s - wp.vec3(g_depth[t, r, cpix] / (s * s))
    gl = wp.vec3(gq[0] / zv[0], gq[1] / zv[1], gq[2] / zv[2])
    ge = gl / area2
    garea = -wp.dot(gl, lam) / area2
    # area2 = cross(b - a, c - a)
    gu, gv = cross2_adj_func(b - a, c - a, garea)
    ga = -gu - gv
    gbv = gu
    gc = gv
    # e0 = cross(c - b, p - b), e1 = cross(a - c, p - c), e2 = cross(b - a, p - a)
    gu, gv = cross2_adj_func(c - b, p - b, ge[0])
    gc = gc + gu
    gbv = gbv - gu - gv
    gu, gv = cross2_adj_func(a - c, p - c, ge[1])
    ga = ga + gu
    gc = gc - gu - gv
    gu, gv = cross2_adj_func(b - a, p - a, ge[2])
    gbv = gbv + gu
    ga = ga - gu - gv
    wp.atomic_add(g_xy, t, i[0], wp.vec2d(ga))
    wp.atomic_add(g_xy, t, i[1], wp.vec2d(gbv))
    wp.atomic_add(g_xy, t, i[2], wp.vec2d(gc))
    wp.atomic_add(g_z, t, i[0], wp.float64(-gq[0] * q[0] / zv[0]))
    wp.atomic_add(g_z, t, i[1], wp.float64(-gq[1] * q[1] / zv[1]))
    wp.atomic_add(g_z, t, i[2], wp.float64(-gq[2] * q[2] / zv[2]))


@wp.kernel
def interpolate_grad_kernel(
    attr: wp.array3d(dtype=float),
    per_frame: int,
    faces: wp.array(dtype=wp.vec3i),
    face_index: wp.array3d(dtype=wp.int32),
    bary: wp.array3d(dtype=wp.vec3),
    g_out: wp.array4d(dtype=float),
    want_attr: int,
    # outputs (g_attr accumulated in float64; g_bary written per pixel)
    g_attr: wp.array3d(dtype=wp.float64),
    g_bary: wp.array3d(dtype=wp.vec3),
):
    """Adjoint of ``interpolate_kernel``: dL/dattr[v_i] += b_i g_out, dL/db_i = g_out . attr[v_i]."""
    t, r, c = wp.tid()
    f = face_index[t, r, c]
    if f < 0:
        g_bary[t, r, c] = wp.vec3(0.0)
        return
    ta = t * per_frame
    i = faces[f]
    w = bary[t, r, c]
    gw = wp.vec3(0.0)
    for ch in range(g_out.shape[3]):
        g = g_out[t, r, c, ch]
        gw = gw + wp.vec3(g * attr[ta, i[0], ch], g * attr[ta, i[1], ch], g * attr[ta, i[2], ch])
        if want_attr != 0:
            wp.atomic_add(g_attr, ta, i[0], ch, wp.float64(w[0] * g))
            wp.atomic_add(g_attr, ta, i[1], ch, wp.float64(w[1] * g))
            wp.atomic_add(g_attr, ta, i[2], ch, wp.float64(w[2] * g))
    g_bary[t, r, c] = gw
