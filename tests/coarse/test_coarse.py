"""Phase 1 coarse initialisation: 2D skeleton graph, canonical frame, part masks, lift, mesh, bones.

The synthetic quadruped is drawn with OpenCV (torso ellipse, two V-shaped leg pairs, neck + head,
thin tail). Its skeleton, as the drawing implies: 6 endpoints (4 feet, head, tail) and 4 junctions
(shoulder, hip, and each leg pair's fork just below the torso); with a larger merge factor each
fork merges into its torso junction, leaving 2 junctions (shoulder, hip) of degree 4.
"""

from __future__ import annotations

import logging

import cv2
import numpy as np
import pytest
import trimesh

from s3o_warp.coarse.lift import ellipsoid_field, ellipsoid_union_mesh, init_bones, lift_to_3d
from s3o_warp.coarse.skeleton2d import (
    ENDPOINT,
    JUNCTION,
    CoarseSettings,
    canonical_frame,
    front_view,
    leg_pairs,
    leg_stride,
    part_masks,
    mirror_pairs,
    skeleton_2d,
    symmetric_pairs,
)
from s3o_warp.errors import ConfigError, InputError

FEET = [(86, 215), (132, 215), (190, 215), (236, 215)]
HEAD = (268, 55)
TAIL = (38, 82)
K = np.array([[310.0, 0.0, 150.0], [0.0, 290.0, 128.0], [0.0, 0.0, 1.0]])


def quadruped(h: int = 240, w: int = 320, front_overlap: bool = False, feet=FEET) -> np.ndarray:
    """front_overlap: both front legs drawn to one foot (a side view where they hide each other)."""
    m = np.zeros((h, w), np.uint8)
    cv2.ellipse(m, (160, 115), (75, 32), 0, 0, 360, 1, -1)
    for hip_x, (fa, fb) in ((108, feet[:2]), (212, feet[2:])):
        if front_overlap and hip_x == 212:
            fa = fb = ((fa[0] + fb[0]) // 2, fa[1])
        cv2.line(m, (hip_x, 125), fa, 1, 14)
        cv2.line(m, (hip_x, 125), fb, 1, 14)
    cv2.line(m, (222, 100), (262, 62), 1, 18)
    cv2.circle(m, HEAD, 17, 1, -1)
    cv2.line(m, (90, 105), TAIL, 1, 7)
    return m.astype(bool)


def ellipse(h=120, w=200, angle=10.0) -> np.ndarray:
    m = np.zeros((h, w), np.uint8)
    cv2.ellipse(m, (100, 60), (80, 30), angle, 0, 360, 1, -1)
    return m.astype(bool)


@pytest.fixture(scope="module")
def quad():
    m = quadruped()
    return m, skeleton_2d(m)


@pytest.fixture(scope="module")
def lifted(quad):
    m, sk = quad
    return m, sk, lift_to_3d(sk, K, 3.0)


@pytest.fixture(scope="module")
def mesh(lifted):
    _, _, c = lifted
    return ellipsoid_union_mesh(c)


def _nearest(nodes: np.ndarray, p) -> tuple[int, float]:
    d = np.linalg.norm(nodes - np.asarray(p, float), axis=1)
    return int(np.argmin(d)), float(d.min())


# --------------------------------------------------------------------------------------------------
# 2D skeleton


def test_quadruped_skeleton_counts_and_places(quad):
    m, sk = quad
    assert len(sk.endpoints) == 6
    assert len(sk.junctions) == 4
    deg = sk.degree()
    assert (deg[sk.endpoints] == 1).all() and (deg[sk.junctions] >= 3).all()
    # the medial axis stops about one radius short of a tip; each drawn tip has its own endpoint
    found = set()
    for tip in [*FEET, HEAD, TAIL]:
        i, d = _nearest(sk.nodes[sk.endpoints], tip)
        assert d < 12.0, (tip, d)
        found.add(i)
    assert len(found) == 6
    # root = the widest junction = a torso junction (shoulder or hip), not a leg fork
    assert sk.node_type[sk.root] == JUNCTION
    assert sk.node_radius[sk.root] == sk.node_radius[sk.junctions].max() > 20
    # the two feet of each pair hang from one fork junction
    for pair in (FEET[:2], FEET[2:]):
        feet = [sk.endpoints[_nearest(sk.nodes[sk.endpoints], f)[0]] for f in pair]
        forks = [[v if u == foot else u for u, v in sk.edges if foot in (u, v)][0] for foot in feet]
        assert forks[0] == forks[1] and sk.node_type[forks[0]] == JUNCTION
    # leg radius ~ half the drawn thickness (14 px)
    leg_edges = [e for e, (u, v) in enumerate(sk.edges) if sk.nodes[[u, v], 1].max() > 200]
    assert len(leg_edges) == 4
    np.testing.assert_allclose(sk.edge_radius[leg_edges], 7.0, atol=1.5)


def test_merge_factor_merges_forks_into_torso_junctions():
    sk = skeleton_2d(quadruped(), merge_factor=1.2)
    assert len(sk.endpoints) == 6
    assert len(sk.junctions) == 2
    assert sorted(sk.degree()[sk.junctions].tolist()) == [4, 4]  # torso + 2 legs + neck / tail


def test_paths_are_connected_chains_between_their_nodes(quad):
    _, sk = quad
    assert len(sk.paths) == len(sk.edges) == len(sk.edge_radius) == len(sk.edge_length)
    for p, (u, v), length in zip(sk.paths, sk.edges, sk.edge_length):
        steps = np.abs(np.diff(p, axis=0))
        assert steps.max() <= 1 and (steps.sum(axis=1) > 0).all()  # 8-connected, no repeats
        for end, n in ((p[0], u), (p[-1], v)):
            assert np.linalg.norm(end - sk.nodes[n]) <= max(1.5, sk.node_radius[n])
        np.testing.assert_allclose(length, np.linalg.norm(np.diff(p, axis=0), axis=1).sum())


def test_plain_ellipse_has_two_endpoints_no_junction():
    m = ellipse()
    for method in ("skeletonize", "medial_axis"):
        sk = skeleton_2d(m, CoarseSettings(skeleton_method=method))
        assert len(sk.endpoints) == 2 and len(sk.junctions) == 0, method
        assert sk.root == -1 and len(sk.edges) == 1
        # along the major axis (10 degrees), both sides of the centre
        d = sk.nodes - [100, 60]
        assert np.all(np.abs(d[:, 1] - np.tan(np.deg2rad(10)) * d[:, 0]) < 4)
        assert d[:, 0].min() < -30 and d[:, 0].max() > 30


def test_jagged_ellipse_spurs_are_pruned():
    m = ellipse().astype(np.uint8)
    rng = np.random.default_rng(0)
    ys, xs = np.nonzero(m)
    border = np.nonzero(cv2.morphologyEx(m, cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8)))
    pick = rng.choice(len(border[0]), 40, replace=False)
    for r, c in zip(border[0][pick], border[1][pick]):
        cv2.circle(m, (int(c), int(r)), 3, 1, -1)  # bumps that grow spurs on the medial axis
    raw = skeleton_2d(m.astype(bool), CoarseSettings(smooth_sigma=0, prune_factor=0, spur_protrusion=0, merge_factor=0))
    sk = skeleton_2d(m.astype(bool), CoarseSettings(smooth_sigma=0))
    assert len(raw.endpoints) > 2  # the bumps really make spurs ...
    assert len(sk.endpoints) == 2 and len(sk.junctions) == 0  # ... and pruning removes them


def test_disc_gives_no_edge_and_lift_refuses():
    m = np.zeros((64, 64), np.uint8)
    cv2.circle(m, (32, 32), 20, 1, -1)
    sk = skeleton_2d(m.astype(bool))
    assert sk.node_type.tolist() == ["isolated"] and len(sk.edges) == 0
    np.testing.assert_allclose(sk.nodes[0], [32, 32], atol=1.5)
    assert sk.extent_ratio() == 1.0
    with pytest.raises(InputError, match="no edge"):
        lift_to_3d(sk, K, 2.0)


def test_skeleton_input_errors():
    with pytest.raises(InputError, match="no foreground"):
        skeleton_2d(np.zeros((10, 10), bool))
    with pytest.raises(InputError, match=r"2D \(H, W\)"):
        skeleton_2d(np.ones((2, 10, 10), bool))
    with pytest.raises(ConfigError, match="prune_factor"):
        skeleton_2d(quadruped(), prune_factor=-1)
    with pytest.raises(ConfigError, match="skeleton_method"):
        CoarseSettings(skeleton_method="thin")


def test_uint8_mask_same_as_bool(quad):
    m, sk = quad
    sk8 = skeleton_2d(m.astype(np.uint8) * 255)
    np.testing.assert_array_equal(sk8.nodes, sk.nodes)
    np.testing.assert_array_equal(sk8.edges, sk.edges)


# --------------------------------------------------------------------------------------------------
# canonical frame and part masks


def _warp(m: np.ndarray, angle: float = 0.0, sx: float = 1.0) -> np.ndarray:
    h, w = m.shape
    A = cv2.getRotationMatrix2D((w / 2, h / 2), angle, 1.0)
    A[:, :2] = A[:, :2] @ np.diag([sx, 1.0])
    A[:, 2] += (1 - sx) * w / 2 * A[:, 0]
    return cv2.warpAffine(m.astype(np.uint8), A, (w, h), flags=cv2.INTER_NEAREST) > 0


def test_canonical_frame_picks_side_view(quad):
    m, sk = quad
    big = np.zeros((320, 320), bool)
    big[40:280] = m
    frames = [_warp(big, 90), _warp(big, 0, 0.45), big, _warp(big, 35), _warp(big, -20, 0.7),
              np.zeros_like(big)]
    t, ratios = canonical_frame(frames, progress=False)
    assert t == 2
    assert ratios.shape == (6,) and ratios[5] == 0
    assert ratios[2] > 1.2 * np.max(np.delete(ratios, 2))
    p = sk.pixels()  # the definition: inclusive pixel extents of the skeleton paths
    np.testing.assert_allclose(ratios[2], (np.ptp(p[:, 0]) + 1) / (np.ptp(p[:, 1]) + 1))
    # shrinking the masks first (speed) keeps the choice and roughly the ratios
    t_small, r_small = canonical_frame(frames, CoarseSettings(canonical_size=160), progress=False)
    assert t_small == 2
    np.testing.assert_allclose(r_small, ratios, rtol=0.15)
    with pytest.raises(InputError, match="every mask is empty"):
        canonical_frame([np.zeros((8, 8), bool)], progress=False)


def test_leg_pairs_are_symmetric_pairs_ending_low(quad):
    m, sk = quad
    pairs = symmetric_pairs(sk, CoarseSettings())
    assert len(pairs) == 2 and leg_pairs(sk, CoarseSettings()) == 2
    # upside down the same pairs end at the top (like ears): still symmetric, not legs
    up = skeleton_2d(m[::-1])
    assert len(symmetric_pairs(up, CoarseSettings())) == 2 and leg_pairs(up, CoarseSettings()) == 0
    # overlapping front legs leave one pair
    assert leg_pairs(skeleton_2d(quadruped(front_overlap=True)), CoarseSettings()) == 1


def test_leg_stride_and_the_canonical_frame_prefer_feet_apart():
    """leg_stride = the closest leg pair's feet distance / the skeleton's longer extent; among competing frames
    with as many leg pairs, the widest stride wins over a slightly more horizontal frame (just after a crossing)."""
    s = CoarseSettings()
    wide = skeleton_2d(quadruped())
    p = wide.pixels()
    extent = max(np.ptp(p[:, 0]), np.ptp(p[:, 1])) + 1
    # both pairs' feet are 46 px apart; the skeleton's leaf ends sit at the feet (lines end at the foot centres)
    assert leg_pairs(wide, s) == 2
    np.testing.assert_allclose(leg_stride(wide, s), 46.0 / extent, rtol=0.05)
    close = [(97, 215), (121, 215), (201, 215), (225, 215)]  # each pair's feet 24 px apart
    narrow = skeleton_2d(quadruped(feet=close))
    assert leg_pairs(narrow, s) == 2
    np.testing.assert_allclose(leg_stride(narrow, s), 24.0 / extent, rtol=0.1)
    assert leg_stride(skeleton_2d(ellipse()), s) == 0.0  # no leg pairs

    def framed(m):
        big = np.zeros((320, 320), bool)
        big[40:280] = m
        return big

    frames = [framed(quadruped(feet=close)), _warp(framed(quadruped()), 0, 0.95)]
    t, ratios = canonical_frame(frames, progress=False)
    assert ratios[0] > ratios[1] > 0.9 * ratios[0]
    assert t == 1
    # 0 turns the stride rule off (the ratio decides); strides within the tolerance of the widest tie
    assert canonical_frame(frames, CoarseSettings(canonical_stride_tolerance=0.0), progress=False)[0] == 0
    assert canonical_frame(frames, CoarseSettings(canonical_stride_tolerance=0.5), progress=False)[0] == 0
    assert canonical_frame(frames, CoarseSettings(canonical_stride_tolerance=0.6), progress=False)[0] == 1
    # feet clearly apart (34 px, 0.74 of the widest) in the more horizontal frame: the default keeps the ratio's
    # choice and excludes only near-crossings; 0.8 would prefer the wider stride
    apart = [(92, 215), (126, 215), (196, 215), (230, 215)]
    frames = [framed(quadruped(feet=apart)), _warp(framed(quadruped()), 0, 0.95)]
    strides = [leg_stride(skeleton_2d(f), s) for f in frames]
    assert 0.65 < strides[0] / strides[1] < 0.8, strides
    assert canonical_frame(frames, progress=False)[0] == 0
    assert canonical_frame(frames, CoarseSettings(canonical_stride_tolerance=0.8), progress=False)[0] == 1
    with pytest.raises(ConfigError, match="canonical_stride_tolerance"):
        CoarseSettings(canonical_stride_tolerance=1.5)


def test_canonical_frame_prefers_legs_apart_among_near_side_views():
    """The most horizontal frame hides a leg; a frame 0.95x as horizontal shows all four apart."""
    def framed(m):
        big = np.zeros((320, 320), bool)
        big[40:280] = m
        return big

    hidden, apart = framed(quadruped(front_overlap=True)), _warp(framed(quadruped()), 0, 0.95)
    frames = [_warp(hidden, 90), hidden, apart]
    t, ratios = canonical_frame(frames, progress=False)
    assert ratios[1] > ratios[2] > 0.9 * ratios[1]
    assert t == 2
    # tolerance 1 is S3O's rule (the most horizontal); a clearly less horizontal frame does not compete
    assert canonical_frame(frames, CoarseSettings(canonical_tolerance=1.0), progress=False)[0] == 1
    squeezed = [_warp(hidden, 90), hidden, _warp(framed(quadruped()), 0, 0.8)]
    assert canonical_frame(squeezed, progress=False)[0] == 1
    with pytest.raises(ConfigError, match="canonical_tolerance"):
        CoarseSettings(canonical_tolerance=0.0)


def test_part_masks_cover_foreground_once_and_nearest(quad):
    m, sk = quad
    parts = part_masks(m, sk)
    assert parts.shape == (len(sk.edges), *m.shape) and parts.dtype == bool
    np.testing.assert_array_equal(parts.sum(axis=0), m.astype(int))
    assert parts.reshape(len(parts), -1).any(axis=1).all()
    # reference: brute-force distance of every foreground pixel to every edge's path
    ys, xs = np.nonzero(m)
    pix = np.stack([xs, ys], axis=1).astype(np.float64)
    dmin = np.stack([
        np.min(np.linalg.norm(pix[:, None, :] - p[None].astype(np.float64), axis=2), axis=1) for p in sk.paths
    ], axis=1)  # (P, E)
    label = np.argmax(parts[:, ys, xs], axis=0)
    np.testing.assert_allclose(dmin[np.arange(len(pix)), label], dmin.min(axis=1), atol=1e-9)
    with pytest.raises(InputError, match="differs"):
        part_masks(m[:-1], sk)


# --------------------------------------------------------------------------------------------------
# lift


def test_lift_reprojects_nodes_and_places_symmetric_legs(lifted):
    m, sk, c = lifted
    np.testing.assert_allclose(c.project(c.nodes), sk.nodes, atol=1e-4, rtol=0)
    # the two leg pairs (and only they) are symmetric
    feet = {int(sk.endpoints[_nearest(sk.nodes[sk.endpoints], f)[0]]) for f in FEET}
    assert len(c.sym_pairs) == 2
    paired_leaves = set()
    for e1, e2 in c.sym_pairs:
        l1, l2 = [int(v if sk.node_type[v] == ENDPOINT else u) for u, v in sk.edges[[e1, e2]]]
        assert {l1, l2} <= feet
        np.testing.assert_allclose([c.nodes[l1, 2], c.nodes[l2, 2]], [-c.dz, c.dz], atol=1e-12)
        paired_leaves |= {l1, l2}
    assert paired_leaves == feet
    others = [n for n in range(len(c.nodes)) if n not in feet]
    np.testing.assert_allclose(c.nodes[others, 2], 0.0, atol=1e-12)  # main chain on the symmetry plane
    f = 0.5 * (K[0, 0] + K[1, 1])
    np.testing.assert_allclose(c.dz, CoarseSettings().dz_fraction * sk.node_radius[sk.root] * 3.0 / f)
    assert c.dz > 0
    normal, offset = c.symmetry_plane
    np.testing.assert_array_equal(normal, [0, 0, 1])
    assert offset == 0
    # root transform [I | C], C = the root junction back-projected at the depth
    T = c.root_transform
    np.testing.assert_array_equal(T[:3, :3], np.eye(3))
    np.testing.assert_allclose(T[:3, 3], 3.0 * np.linalg.solve(K, [*sk.nodes[sk.root], 1.0]))
    np.testing.assert_allclose(c.nodes[sk.root], 0.0, atol=1e-12)


HANDS = [(40, 92), (280, 92)]
PERSON_FEET = [(128, 228), (192, 228)]


def person(arms_out: bool = True, h: int = 240, w: int = 320) -> np.ndarray:
    """A person seen from the front: head, torso, arms held out (or hanging), legs apart."""
    m = np.zeros((h, w), np.uint8)
    cv2.ellipse(m, (160, 110), (28, 50), 0, 0, 360, 1, -1)
    cv2.circle(m, (160, 38), 20, 1, -1)
    for (hx, hy), sx in zip(HANDS, (136, 184)):
        cv2.line(m, (sx, 84), (hx, hy) if arms_out else (sx - 60 * (sx < 160) + 60 * (sx > 160), 190), 1, 12)
    for fx, fy in PERSON_FEET:
        cv2.line(m, (160 + (fx - 160) // 4, 150), (fx, fy), 1, 16)
    return m.astype(bool)


def _leaf_end(sk, e) -> int:
    u, v = (int(x) for x in sk.edges[e])
    return v if sk.node_type[v] == ENDPOINT else u


def test_front_view_pairs_arms_and_legs_about_the_vertical():
    m = person()
    sk = skeleton_2d(m)
    s = CoarseSettings()
    pairs = mirror_pairs(sk, s)
    ends = [[sk.nodes[_leaf_end(sk, e)] for e in p] for p in pairs]
    hands = [[np.linalg.norm(e - np.array(h)) for e, h in zip(pe, HANDS)] for pe in ends]
    feet = [[np.linalg.norm(e - np.array(f)) for e, f in zip(pe, PERSON_FEET)] for pe in ends]
    assert len(pairs) == 2
    assert any(max(d) < 6 for d in hands) and any(max(d) < 8 for d in feet)  # each pair left first
    assert front_view(sk, s)
    # mirrored left-right: the same pairs, the left one still first
    sk2 = skeleton_2d(m[:, ::-1])
    assert len(mirror_pairs(sk2, s)) == 2 and front_view(sk2, s)
    # arms hanging: a front view that cannot be told from a side view's legs; the quadruped's pairs hang the same way
    assert not front_view(skeleton_2d(person(arms_out=False)), s)
    assert not front_view(skeleton_2d(quadruped()), s)
    # legs spread wider than 90 degrees still hang down: no front view (a side view's wide stride, or toes)
    wide = np.zeros((240, 320), np.uint8)
    cv2.ellipse(wide, (160, 95), (26, 55), 0, 0, 360, 1, -1)
    cv2.circle(wide, (160, 28), 18, 1, -1)
    for foot in ((50, 215), (270, 215)):
        cv2.line(wide, (160, 145), foot, 1, 14)
    sk_wide = skeleton_2d(wide.astype(bool))
    spread = [p for p in mirror_pairs(sk_wide, s)
              if float(np.dot(*[sk_wide.nodes[_leaf_end(sk_wide, e)] - sk_wide.nodes[
                  int(np.intersect1d(sk_wide.edges[p[0]], sk_wide.edges[p[1]])[0])] for e in p])) < 0]
    assert spread and not front_view(sk_wide, s)


def test_lift_of_a_front_view_mirrors_about_the_vertical_plane():
    m = person()
    sk = skeleton_2d(m)
    c = lift_to_3d(sk, K, 3.0)
    np.testing.assert_allclose(c.project(c.nodes), sk.nodes, atol=1e-4, rtol=0)
    np.testing.assert_allclose(c.nodes[:, 2], 0.0, atol=1e-12)  # the limbs are apart in x: nothing leaves z = 0
    assert c.dz == 0 and len(c.girdle_centres) == 0 and not np.any(c.edge_dz)
    normal, offset = c.symmetry_plane
    np.testing.assert_array_equal(normal, [1, 0, 0])
    assert offset == 0
    assert [tuple(p) for p in c.sym_pairs] == mirror_pairs(sk, CoarseSettings())
    for e1, e2 in c.sym_pairs:  # left of the plane first, mirror images within a few pixels' worth
        a, b = c.nodes[_leaf_end(sk, e1)], c.nodes[_leaf_end(sk, e2)]
        assert a[0] < 0 < b[0]
        np.testing.assert_allclose([-a[0], a[1]], b[:2], atol=0.1 * np.linalg.norm(b[:2]))


def test_lift_ellipsoids_follow_edges(lifted):
    _, sk, c = lifted
    R = c.rotations
    np.testing.assert_allclose(np.einsum("eji,ejk->eik", R, R), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    f = 0.5 * (K[0, 0] + K[1, 1])
    paired = set(c.sym_pairs.ravel().tolist())
    for e, (u, v) in enumerate(c.edges):
        pu, pv = c.nodes[u].copy(), c.nodes[v].copy()
        if e in paired:  # the whole limb sits off the plane: its junction end is shifted like its foot
            assert 0 < abs(c.edge_dz[e]) <= c.dz
            for p in (pu, pv):
                if p[2] == 0:
                    p[2] = c.edge_dz[e]
            assert np.sign(pu[2]) == np.sign(pv[2]) == np.sign(c.edge_dz[e])
        else:
            assert c.edge_dz[e] == 0
        a = pv - pu
        length = np.linalg.norm(a)
        np.testing.assert_allclose(c.centres[e], 0.5 * (pu + pv))
        np.testing.assert_allclose(R[e][:, 0], a / length, atol=1e-12)
        r = sk.edge_radius[e] * 3.0 / f
        np.testing.assert_allclose(c.radii[e], [0.5 * length + r, r, r])
        # both end nodes lie inside their ellipsoid (end_pad = 1 reaches r beyond them)
        for p in (pu, pv):
            q = np.linalg.norm(R[e].T @ (p - c.centres[e]) / c.radii[e])
            assert q < 1


def test_girdles_hold_parallel_limbs_apart_in_one_body(quad):
    m, sk = quad
    s = CoarseSettings(girdles=True)
    c = lift_to_3d(sk, K, 3.0, s)
    assert len(c.girdle_centres) == len(c.sym_pairs) == 2
    f = 0.5 * (K[0, 0] + K[1, 1])
    for (e1, e2), gc, gr in zip(c.sym_pairs, c.girdle_centres, c.girdle_radii):
        j = int(np.intersect1d(c.edges[e1], c.edges[e2])[0])
        np.testing.assert_allclose(gc, c.nodes[j])
        r_j = sk.node_radius[j] * 3.0 / f
        r_limb = max(sk.edge_radius[e1], sk.edge_radius[e2]) * 3.0 / f
        np.testing.assert_allclose(gr, [r_j, r_j, c.dz + r_limb])
        np.testing.assert_allclose(c.edge_dz[[e1, e2]], [-c.dz, c.dz])  # whole limb at +-dz: parallel
        assert np.allclose(c.centres[[e1, e2], 2], [-c.dz, c.dz])
    verts, faces = ellipsoid_union_mesh(c, target_vertices=1500, settings=s)
    tm = trimesh.Trimesh(verts, faces, process=False)
    assert tm.body_count == 1 and tm.is_watertight
    # a horizontal slice through the lower legs: the two legs of a pair are separate (a gap at z = 0)
    y_cut = np.percentile(verts[:, 1], 90)  # y points down: the lowest tenth of the vertices
    sec = tm.section(plane_origin=[0, y_cut, 0], plane_normal=[0, 1, 0])
    assert sec is not None
    loops = sec.discrete
    assert len(loops) == 4, len(loops)  # four leg cross-sections
    zs = sorted(float(np.mean(lp[:, 2])) for lp in loops)
    assert zs[0] < 0 and zs[1] < 0 and zs[2] > 0 and zs[3] > 0
    # the silhouette from the canonical view is still the mask's shape: girdles sit inside the body
    assert (_raster(c, verts, faces, m.shape) & ~m).sum() < 0.08 * m.sum()


def test_lift_input_errors(quad):
    _, sk = quad
    with pytest.raises(InputError, match="depth"):
        lift_to_3d(sk, K, 0.0)
    with pytest.raises(InputError, match=r"\(3, 3\)"):
        lift_to_3d(sk, K[:2], 1.0)
    with pytest.raises(InputError, match="fx, fy > 0"):
        lift_to_3d(sk, -K, 1.0)


def test_lift_plain_ellipse_centres_on_its_axis():
    sk = skeleton_2d(ellipse())
    c = lift_to_3d(sk, K, 2.0)
    assert c.root == -1 and c.root_edge == 0 and len(c.sym_pairs) == 0
    np.testing.assert_allclose(c.project(c.nodes), sk.nodes, atol=1e-4, rtol=0)
    # the origin (body centre) is the middle of the only edge
    np.testing.assert_allclose(c.nodes[0], -c.nodes[1], atol=0.02 * np.linalg.norm(c.nodes[0]))


# --------------------------------------------------------------------------------------------------
# union mesh


def _raster(c, verts, faces, shape) -> np.ndarray:
    uv = c.project(verts.astype(np.float64))
    img = np.zeros(shape, np.uint8)
    for tri in np.round(uv[faces] * 16).astype(np.int32):  # one polygon per call: no even-odd holes
        cv2.fillPoly(img, [tri], 1, shift=4)
    return img > 0


def test_union_mesh_watertight_near_target_covers_silhouette(lifted, mesh):
    m, sk, c = lifted
    verts, faces = mesh
    assert verts.dtype == np.float32 and faces.dtype == np.int32
    assert abs(len(verts) - 2000) <= 0.25 * 2000
    tm = trimesh.Trimesh(verts, faces, process=False)
    assert tm.is_watertight and tm.is_winding_consistent and tm.volume > 0
    assert tm.body_count == 1
    sil = _raster(c, verts, faces, m.shape)
    iou = (sil & m).sum() / (sil | m).sum()
    logging.getLogger(__name__).info("union mesh silhouette IoU %.3f", iou)
    assert iou > 0.6


def test_union_mesh_matches_implicit_union(lifted, mesh):
    _, _, c = lifted
    verts, faces = mesh
    tm = trimesh.Trimesh(verts, faces, process=False)
    smooth = CoarseSettings().smooth_max * c.radii[:, 1:].mean()
    # vertices sit on the zero level (up to the grid and Taubin smoothing)
    g = ellipsoid_field(c, verts.astype(np.float64), smooth)
    assert np.abs(g).max() < 0.4 * c.radii[:, 1:].min()  # Taubin moves the creases where girdles meet limbs most
    # volume = Monte-Carlo volume of {field > 0}
    rng = np.random.default_rng(1)
    lo, hi = verts.min(0) - 0.05, verts.max(0) + 0.05
    pts = rng.uniform(lo, hi, size=(200_000, 3))
    mc = (ellipsoid_field(c, pts, smooth) > 0).mean() * np.prod(hi - lo)
    np.testing.assert_allclose(tm.volume, mc, rtol=0.06)


def test_union_mesh_other_target(lifted):
    _, _, c = lifted
    verts, faces = ellipsoid_union_mesh(c, target_vertices=800)
    assert abs(len(verts) - 800) <= 0.25 * 800
    assert trimesh.Trimesh(verts, faces, process=False).is_watertight


# --------------------------------------------------------------------------------------------------
# bones


def test_init_bones_tree_rooted_at_torso(quad, lifted):
    _, sk, c = lifted
    b = init_bones(c)
    B = len(c.edges)
    assert b.centres.shape == (B, 3) and b.precisions.shape == (B, 3, 3) and b.lengths.shape == (B,)
    roots = np.flatnonzero(b.parents == -1)
    assert roots.tolist() == [c.root_edge]
    assert sk.root in c.edges[c.root_edge]
    # the root bone is the widest bone at the root junction: the torso (between shoulder and hip)
    u, v = c.edges[c.root_edge]
    assert sk.node_radius[u] > 20 and sk.node_radius[v] > 20
    # every bone reaches the root through its parents without a cycle
    for k in range(B):
        seen, x = set(), k
        while x != -1:
            assert x not in seen
            seen.add(x)
            x = b.parents[x]
    # joints: one per non-root bone, (parent, child) sharing the node at the joint position
    assert len(b.joints) == B - 1
    paired = set(c.sym_pairs.ravel().tolist())
    for (p, ch), n, pos in zip(b.joints, b.joint_nodes, b.joint_positions):
        assert b.parents[ch] == p
        assert n in c.edges[p] and n in c.edges[ch]
        # at the shared node; a paired limb's joint is shifted off the plane with the limb
        np.testing.assert_allclose(pos, c.nodes[n] + [0.0, 0.0, c.edge_dz[ch] if ch in paired else 0.0], atol=1e-12)
    # the joint node of a child bone is its end nearer the root junction (graph hops)
    hops = {sk.root: 0}
    frontier = [sk.root]
    while frontier:
        nxt = []
        for n in frontier:
            for u, v in c.edges:
                o = v if u == n else u if v == n else None
                if o is not None and o not in hops:
                    hops[o] = hops[n] + 1
                    nxt.append(o)
        frontier = nxt
    for (p, ch), n in zip(b.joints, b.joint_nodes):
        far = [x for x in c.edges[ch] if x != n][0]
        assert hops[n] < hops[far]
    # lengths: the ellipsoid axes (2 x (long semi-axis - end_pad r))
    np.testing.assert_allclose(b.lengths, 2 * (c.radii[:, 0] - c.radii[:, 1]), atol=1e-12)
    packed_b, packed_j = b.packed()
    assert packed_b.shape == (B, 13) and packed_j.shape == (B - 1, 5)


def test_init_bones_precision(lifted):
    _, _, c = lifted
    k = 3.0
    b = init_bones(c, CoarseSettings(precision_sharpness=k))
    np.testing.assert_allclose(b.centres, c.centres)
    # reference: Q = inverse of the covariance R diag(r^2 / k) R^T
    cov = np.einsum("eij,ej,ekj->eik", c.rotations, c.radii**2 / k, c.rotations)
    np.testing.assert_allclose(b.precisions, np.linalg.inv(cov), rtol=1e-9)
    # on the ellipsoid surface the Mahalanobis form equals k
    rng = np.random.default_rng(0)
    for e in range(len(c.edges)):
        d = rng.normal(size=(5, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        pts = (d * c.radii[e]) @ c.rotations[e].T
        np.testing.assert_allclose(np.einsum("ni,ij,nj->n", pts, b.precisions[e], pts), k, rtol=1e-9)


# --------------------------------------------------------------------------------------------------
# real masks


@pytest.mark.parametrize("frame", ["00000", "00050"])
def test_davis_cows_skeleton_sanity(shared_data, frame):
    path = shared_data / "davis" / "Annotations" / "480p" / "cows" / f"{frame}.png"
    if not path.is_file():
        pytest.skip(f"{path} not found")
    m = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) > 127
    sk = skeleton_2d(m)
    logging.getLogger(__name__).info("cows %s: %d endpoints, %d junctions, %d edges, extent ratio %.2f",
                                     frame, len(sk.endpoints), len(sk.junctions), len(sk.edges), sk.extent_ratio())
    assert len(sk.endpoints) >= 4 and len(sk.junctions) >= 1
    parts = part_masks(m, sk)
    np.testing.assert_array_equal(parts.sum(axis=0), m.astype(int))
    c = lift_to_3d(sk, np.array([[800.0, 0, 427], [0, 800, 240], [0, 0, 1]]), 5.0)
    np.testing.assert_allclose(c.project(c.nodes), sk.nodes, atol=1e-4, rtol=0)
