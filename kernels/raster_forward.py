"""Warp kernels of the rasteriser's forward passes: tile binning, soft silhouette, z-buffer.

All kernels take projected 2D vertex positions ``xy`` (T, V) vec2 in pixels (the centre of pixel
(column c, row r) is at (c, r)) and never differentiate themselves: the gradients of the soft
silhouette are written by hand in ``raster_backward.py`` (its own Warp module), and those of the
z-buffer's barycentrics come from torch (see ``raster.py``). Bins ("tiles") are numbered
``t * bins_per_frame + ty * ntx + tx``.
"""

from __future__ import annotations

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func
def cross2_func(u: wp.vec2, v: wp.vec2):
    """z component of the 2D cross product u x v."""
    return u[0] * v[1] - u[1] * v[0]


@wp.func
def segment_sq_dist_func(p: wp.vec2, a: wp.vec2, b: wp.vec2):
    """Squared distance from p to segment ab, the parameter s in [0, 1] of the closest point
    q = a + s (b - a), and p - q."""
    e = b - a
    ee = wp.dot(e, e)
    s = float(0.0)
    if ee > 0.0:
        s = wp.clamp(wp.dot(p - a, e) / ee, 0.0, 1.0)
    diff = p - (a + s * e)
    return wp.dot(diff, diff), s, diff


@wp.func
def triangle_sq_dist_func(p: wp.vec2, a: wp.vec2, b: wp.vec2, c: wp.vec2):
    """Squared distance d^2 from p to the boundary of triangle abc, the nearest edge k (edge k runs
    from vertex k to vertex k+1 mod 3, first one on ties), its parameter s, p - q, and whether p is
    strictly inside (three edge functions of one sign, either winding)."""
    d2, s, diff = segment_sq_dist_func(p, a, b)
    k = int(0)
    d2b, sb, diffb = segment_sq_dist_func(p, b, c)
    if d2b < d2:
        d2 = d2b
        s = sb
        diff = diffb
        k = 1
    d2c, sc, diffc = segment_sq_dist_func(p, c, a)
    if d2c < d2:
        d2 = d2c
        s = sc
        diff = diffc
        k = 2
    w0 = cross2_func(b - a, p - a)
    w1 = cross2_func(c - b, p - b)
    w2 = cross2_func(a - c, p - c)
    inside = (w0 > 0.0 and w1 > 0.0 and w2 > 0.0) or (w0 < 0.0 and w1 < 0.0 and w2 < 0.0)
    return d2, k, s, diff, inside


@wp.func
def outside_box_func(p: wp.vec2, a: wp.vec2, b: wp.vec2, c: wp.vec2, radius: float):
    """True when p lies outside the bbox of triangle abc widened by radius (a cheap early-out)."""
    if p[0] < wp.min(wp.min(a[0], b[0]), c[0]) - radius or p[0] > wp.max(wp.max(a[0], b[0]), c[0]) + radius:
        return True
    return p[1] < wp.min(wp.min(a[1], b[1]), c[1]) - radius or p[1] > wp.max(wp.max(a[1], b[1]), c[1]) + radius


@wp.func
def log_one_minus_coverage_func(p: wp.vec2, a: wp.vec2, b: wp.vec2, c: wp.vec2, inv_sigma: float, cutoff: float):
    """log(1 - D) for one face, D = sigmoid(delta d^2 / sigma); 0 when the face is left out
    (outside with d^2 >= cutoff). Stable: log(1 - D) = -softplus(x)."""
    d2, k, s, diff, inside = triangle_sq_dist_func(p, a, b, c)
    out = float(0.0)
    if inside or d2 < cutoff:
        x = d2 * inv_sigma
        if not inside:
            x = -x
        out = -(wp.max(x, 0.0) + wp.log(1.0 + wp.exp(-wp.abs(x))))
    return out


@wp.kernel
def count_tile_faces_kernel(
    xy: wp.array2d(dtype=wp.vec2),
    faces: wp.array(dtype=wp.vec3i),
    front: wp.array2d(dtype=wp.int32),
    radius: float,
    width: int,
    height: int,
    tile: int,
    ntx: int,
    bins_per_frame: int,
    # outputs
    face_tiles: wp.array2d(dtype=wp.vec4i),
    bin_count: wp.array(dtype=wp.int32),
):
    """Per (frame, face): the tile range (tx0, tx1, ty0, ty1) of its bbox widened by ``radius``
    (empty when tx1 < tx0), and +1 to the count of every tile in it."""
    t, f = wp.tid()
    face_tiles[t, f] = wp.vec4i(0, -1, 0, -1)
    if front[t, f] == 0:
        return
    i = faces[f]
    a = xy[t, i[0]]
    b = xy[t, i[1]]
    c = xy[t, i[2]]
    fw = float(width)
    fh = float(height)
    xmin = wp.clamp(wp.min(wp.min(a[0], b[0]), c[0]) - radius, -1.0, fw)
    xmax = wp.clamp(wp.max(wp.max(a[0], b[0]), c[0]) + radius, -1.0, fw)
    ymin = wp.clamp(wp.min(wp.min(a[1], b[1]), c[1]) - radius, -1.0, fh)
    ymax = wp.clamp(wp.max(wp.max(a[1], b[1]), c[1]) + radius, -1.0, fh)
    c0 = wp.max(int(wp.ceil(xmin)), 0)
    c1 = wp.min(int(wp.floor(xmax)), width - 1)
    r0 = wp.max(int(wp.ceil(ymin)), 0)
    r1 = wp.min(int(wp.floor(ymax)), height - 1)
    if c0 > c1 or r0 > r1:
        return
    tx0 = c0 // tile
    tx1 = c1 // tile
    ty0 = r0 // tile
    ty1 = r1 // tile
    face_tiles[t, f] = wp.vec4i(tx0, tx1, ty0, ty1)
    for ty in range(ty0, ty1 + 1):
        for tx in range(tx0, tx1 + 1):
            wp.atomic_add(bin_count, t * bins_per_frame + ty * ntx + tx, 1)


@wp.kernel
def fill_tile_faces_kernel(
    face_tiles: wp.array2d(dtype=wp.vec4i),
    bin_start: wp.array(dtype=wp.int32),
    ntx: int,
    bins_per_frame: int,
    # outputs
    bin_cursor: wp.array(dtype=wp.int32),
    bin_faces: wp.array(dtype=wp.int32),
    entry_bin: wp.array(dtype=wp.int32),
):
    """CSR fill: write face f into every tile of its range (slot order sorted afterwards)."""
    t, f = wp.tid()
    rng = face_tiles[t, f]
    for ty in range(rng[2], rng[3] + 1):
        for tx in range(rng[0], rng[1] + 1):
            bn = t * bins_per_frame + ty * ntx + tx
            slot = bin_start[bn] + wp.atomic_add(bin_cursor, bn, 1)
            bin_faces[slot] = f
            entry_bin[slot] = bn


@wp.kernel
def render_soft_silhouette_kernel(
    xy: wp.array2d(dtype=wp.vec2),
    faces: wp.array(dtype=wp.vec3i),
    bin_start: wp.array(dtype=wp.int32),
    bin_count: wp.array(dtype=wp.int32),
    bin_faces: wp.array(dtype=wp.int32),
    tile: int,
    ntx: int,
    bins_per_frame: int,
    inv_sigma: float,
    cutoff: float,
    # outputs
    log_trans: wp.array3d(dtype=float),
):
    """Per pixel (t, r, c): S = sum over its tile's faces of log(1 - D_j), so A = 1 - exp(S)."""
    t, r, c = wp.tid()
    bn = t * bins_per_frame + (r // tile) * ntx + c // tile
    p = wp.vec2(float(c), float(r))
    acc = float(0.0)
    start = bin_start[bn]
    for k in range(start, start + bin_count[bn]):
        i = faces[bin_faces[k]]
        acc += log_one_minus_coverage_func(p, xy[t, i[0]], xy[t, i[1]], xy[t, i[2]], inv_sigma, cutoff)
    log_trans[t, r, c] = acc


@wp.kernel
def render_soft_silhouette_naive_kernel(
    xy: wp.array2d(dtype=wp.vec2),
    faces: wp.array(dtype=wp.vec3i),
    front: wp.array2d(dtype=wp.int32),
    radius: float,
    inv_sigma: float,
    cutoff: float,
    # outputs
    log_trans: wp.array3d(dtype=float),
):
    """SoftRas-style O(pixels x faces): every pixel visits every face (bbox early-out only)."""
    t, r, c = wp.tid()
    p = wp.vec2(float(c), float(r))
    acc = float(0.0)
    for f in range(faces.shape[0]):
        if front[t, f] == 0:
            continue
        i = faces[f]
        a = xy[t, i[0]]
        b = xy[t, i[1]]
        cc = xy[t, i[2]]
        if outside_box_func(p, a, b, cc, radius):
            continue
        acc += log_one_minus_coverage_func(p, a, b, cc, inv_sigma, cutoff)
    log_trans[t, r, c] = acc


@wp.func
def edge_row_func(u: wp.vec2, v: wp.vec2, inv_area2: float):
    """Row (A, B, C) of the edge function of edge u -> v over twice the signed area:
    l(p) = A p.x + B p.y + C = cross(v - u, p - u) / area2."""
    e = v - u
    return wp.vec3(-e[1] * inv_area2, e[0] * inv_area2, (e[1] * u[0] - e[0] * u[1]) * inv_area2)


@wp.kernel
def setup_raster_faces_kernel(
    xy: wp.array2d(dtype=wp.vec2),
    z: wp.array2d(dtype=float),
    faces: wp.array(dtype=wp.vec3i),
    front: wp.array2d(dtype=wp.int32),
    # outputs
    bary_rows: wp.array2d(dtype=wp.mat33),
    inv_z: wp.array2d(dtype=wp.vec3),
):
    """Per (frame, face): rows of the screen barycentrics l = M (x, y, 1) and 1 / z of the
    vertices, so the per-pixel test is 9 multiply-adds. Faces behind the camera or of zero area get
    a matrix that covers no pixel (l = -1)."""
    t, f = wp.tid()
    i = faces[f]
    a = xy[t, i[0]]
    b = xy[t, i[1]]
    c = xy[t, i[2]]
    area2 = cross2_func(b - a, c - a)
    if front[t, f] == 0 or area2 == 0.0:
        bary_rows[t, f] = wp.mat33(0.0, 0.0, -1.0, 0.0, 0.0, -1.0, 0.0, 0.0, -1.0)
        inv_z[t, f] = wp.vec3(0.0)
        return
    s = 1.0 / area2
    r0 = edge_row_func(b, c, s)
    r1 = edge_row_func(c, a, s)
    r2 = edge_row_func(a, b, s)
    bary_rows[t, f] = wp.mat33(r0[0], r0[1], r0[2], r1[0], r1[1], r1[2], r2[0], r2[1], r2[2])
    inv_z[t, f] = wp.vec3(1.0 / z[t, i[0]], 1.0 / z[t, i[1]], 1.0 / z[t, i[2]])


@wp.kernel
def rasterize_faces_kernel(
    bary_rows: wp.array2d(dtype=wp.mat33),
    inv_z: wp.array2d(dtype=wp.vec3),
    bin_start: wp.array(dtype=wp.int32),
    bin_count: wp.array(dtype=wp.int32),
    bin_faces: wp.array(dtype=wp.int32),
    tile: int,
    ntx: int,
    bins_per_frame: int,
    # outputs
    face_index: wp.array3d(dtype=wp.int32),
):
    """Z-buffer per pixel: nearest tile face whose projection covers the pixel centre (all screen
    barycentrics >= 0, non-zero area), perspective-correct depth 1 / sum_i l_i / z_i; strict <
    keeps the lower face id on equal depth because tile lists are sorted by face id. -1 for
    background."""
    t, r, c = wp.tid()
    bn = t * bins_per_frame + (r // tile) * ntx + c // tile
    p = wp.vec3(float(c), float(r), 1.0)
    best_z = float(1.0e38)
    best_f = int(-1)
    start = bin_start[bn]
    for k in range(start, start + bin_count[bn]):
        f = bin_faces[k]
        lam = bary_rows[t, f] * p
        if lam[0] >= 0.0 and lam[1] >= 0.0 and lam[2] >= 0.0:
            iz = wp.dot(lam, inv_z[t, f])
            if iz > 0.0:
                zz = 1.0 / iz
                if zz < best_z:
                    best_z = zz
                    best_f = f
    face_index[t, r, c] = best_f


@wp.func
def screen_edges_func(p: wp.vec2, a: wp.vec2, b: wp.vec2, c: wp.vec2):
    """Edge functions (e0, e1, e2) of the edges opposite a, b, c at p; their sum is twice the signed area."""
    return wp.vec3(cross2_func(c - b, p - b), cross2_func(a - c, p - c), cross2_func(b - a, p - a))


@wp.func
def perspective_barycentrics_func(p: wp.vec2, a: wp.vec2, b: wp.vec2, c: wp.vec2, z: wp.vec3):
    """At pixel p of triangle abc with camera depths z: twice its signed area, the screen barycentrics
    l_i = e_i / area2 and q_i = l_i / z_i (the perspective-correct ones are q / sum q, the depth 1 / sum q)."""
    area2 = cross2_func(b - a, c - a)
    lam = screen_edges_func(p, a, b, c) / area2
    return area2, lam, wp.vec3(lam[0] / z[0], lam[1] / z[1], lam[2] / z[2])


@wp.kernel
def barycentrics_kernel(
    xy: wp.array2d(dtype=wp.vec2),
    z: wp.array2d(dtype=float),
    faces: wp.array(dtype=wp.vec3i),
    face_index: wp.array3d(dtype=wp.int32),
    # outputs
    bary: wp.array3d(dtype=wp.vec3),
    depth: wp.array3d(dtype=float),
):
    """Per pixel of the z-buffer: perspective-correct barycentrics b_i = (l_i / z_i) / s and depth 1 / s,
    s = sum_k l_k / z_k, of the visible face (screen barycentrics l_i = e_i / twice the area); 0 on background."""
    t, r, c = wp.tid()
    f = face_index[t, r, c]
    if f < 0:
        bary[t, r, c] = wp.vec3(0.0)
        depth[t, r, c] = 0.0
        return
    i = faces[f]
    _area2, _lam, q = perspective_barycentrics_func(wp.vec2(float(c), float(r)), xy[t, i[0]], xy[t, i[1]], xy[t, i[2]],
                                                    wp.vec3(z[t, i[0]], z[t, i[1]], z[t, i[2]]))
    s = q[0] + q[1] + q[2]
    bary[t, r, c] = q / s
    depth[t, r, c] = 1.0 / s


@wp.kernel
def interpolate_kernel(
    attr: wp.array3d(dtype=float),
    per_frame: int,
    faces: wp.array(dtype=wp.vec3i),
    face_index: wp.array3d(dtype=wp.int32),
    bary: wp.array3d(dtype=wp.vec3),
    # outputs
    out: wp.array4d(dtype=float),
):
    """out[t, r, c, :] = sum_i bary_i attr[t', faces[f, i], :] (t' = t, or 0 for one attribute set for all
    frames); 0 on background."""
    t, r, c = wp.tid()
    f = face_index[t, r, c]
    C = out.shape[3]
    if f < 0:
        for ch in range(C):
            out[t, r, c, ch] = 0.0
        return
    ta = t * per_frame
    i = faces[f]
    w = bary[t, r, c]
    for ch in range(C):
        out[t, r, c, ch] = w[0] * attr[ta, i[0], ch] + w[1] * attr[ta, i[1], ch] + w[2] * attr[ta, i[2], ch]
