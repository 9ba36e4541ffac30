"""The views from every side and the surface figures: each against a dense twin or a known answer, and on
controls (the truth scores at the top, the truth frozen in one pose clearly lower)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation
from eval_scene import cam_from_world, rot, two_box_sequence

from s3o_warp.evaluation.shape import Similarity, frame_similarities, sample_surface, sample_surface_faces, shape_metrics
from s3o_warp.evaluation.views import (
    body_axes,
    body_width_ratio,
    left_right_pairs,
    mesh_smoothness,
    novel_view_iou,
    roughness,
    silhouette,
    surface_quality,
    turn_error,
    width_ratios,
)

IDENTITY = Similarity(1.0, np.eye(3), np.zeros(3))


def test_silhouette_matches_point_in_triangle_at_pixel_centres():
    rng = np.random.default_rng(0)
    pts = rng.random((30, 2)) * 40.0
    faces = rng.integers(0, 30, (12, 3))
    img = silhouette(pts, faces, np.zeros(2), 0.25, 161)
    rr, cc = np.mgrid[0:161, 0:161]
    q = 0.25 * np.stack([cc.ravel(), rr.ravel()], 1).astype(np.float64)
    dense = np.zeros(q.shape[0], bool)
    for a, b, c in pts[faces]:  # barycentric sign test, the twin
        def side(p0, p1):
            return (p1[0] - p0[0]) * (q[:, 1] - p0[1]) - (p1[1] - p0[1]) * (q[:, 0] - p0[0])
        s1, s2, s3 = side(a, b), side(b, c), side(c, a)
        dense |= ((s1 >= 0) & (s2 >= 0) & (s3 >= 0)) | ((s1 <= 0) & (s2 <= 0) & (s3 <= 0))
    dense = dense.reshape(161, 161)
    inter, union = (img.astype(bool) & dense).sum(), (img.astype(bool) | dense).sum()
    assert dense.sum() > 3000 and inter / dense.sum() > 0.99  # every pixel centre inside is filled
    assert inter / union > 0.93  # the raster rule differs on the edges' pixels only


def test_sample_surface_faces_gives_sample_surfaces_points_on_their_faces():
    m = trimesh.creation.icosphere(2)
    p, f = sample_surface_faces(m.vertices, m.faces, 500, [3, 1])
    assert np.array_equal(p, sample_surface(m.vertices, m.faces, 500, [3, 1]))
    tri = m.vertices[m.faces[f]]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert np.abs(((p - tri[:, 0]) * n).sum(-1)).max() < 1e-9  # each point lies in its face's plane


def test_body_axes_follow_the_worlds_up_and_the_bodys_length():
    box = trimesh.creation.box(extents=(3.0, 1.0, 0.5)).vertices  # long along world x, up is y
    R = rot("y", 0.7) @ rot("z", 0.3)
    c2w = np.eye(4)[None].repeat(2, 0)
    c2w[:, :3, :3] = R
    c2w[:, :3, 3] = [0.1, 0.2, 5.0]
    cam = np.stack([box @ R.T + c2w[0, :3, 3]] * 2)
    ax = body_axes(cam, c2w)
    fwd_world = np.array([1.0, 0.0, 0.0])
    up_world = np.array([0.0, 1.0, 0.0])
    assert abs(ax["top"][0, 0] @ (R @ fwd_world)) == pytest.approx(1.0)  # the top view's first axis: the length
    assert abs(ax["front"][0, 1] @ (R @ up_world)) == pytest.approx(1.0)
    extent = {k: np.ptp(cam[0] @ a[0].T, axis=0) for k, a in ax.items()}
    assert sorted(extent["top"]) == pytest.approx([0.5, 3.0]) and sorted(extent["front"]) == pytest.approx([0.5, 1.0])
    assert sorted(extent["side"]) == pytest.approx([1.0, 3.0])


def test_truth_scores_one_and_frozen_truth_lower():
    verts, faces, _, _ = two_box_sequence(T=6)
    c2w = cam_from_world(6)
    truth = novel_view_iou(verts, faces, verts, faces, c2w, [IDENTITY] * 6)
    assert truth["mean"] == 1.0 and truth["frames"] == [0, 1, 2, 3, 4, 5]
    frozen = np.repeat(verts[:1], 6, 0)
    _, sim = shape_metrics(frozen, faces, verts, faces, n_points=500)
    seq = novel_view_iou(frozen, faces, verts, faces, c2w, [sim] * 6)
    sims = frame_similarities(frozen, faces, verts, faces, sim, n_points=800)
    own = novel_view_iou(frozen, faces, verts, faces, c2w, sims)
    assert novel_view_iou(frozen, faces, verts, faces, c2w, [IDENTITY] * 6)["per_frame"]["top"][0] == 1.0
    assert seq["mean"] < 0.7 and own["mean"] < 0.97 and seq["mean"] < own["mean"]
    # a wrong width shows from above and from the front, not from the side
    thin = verts.copy()
    centre = thin.mean(1, keepdims=True)
    depth = np.einsum("tva,ta->tv", thin - centre, c2w[:, :3, 2])  # along the world's z: the boxes' width
    thin -= 0.6 * depth[..., None] * c2w[:, None, :3, 2]
    blade = novel_view_iou(thin, faces, verts, faces, c2w, [IDENTITY] * 6)["per_view"]
    assert blade["side"] > 0.99 and blade["top"] < 0.7 and blade["front"] < 0.7


def test_roughness_is_zero_on_a_smooth_sphere_and_high_on_a_crumpled_one():
    m = trimesh.creation.icosphere(3)
    assert roughness(m.vertices, m.faces) == 0.0
    rng = np.random.default_rng(1)
    crumpled = m.vertices * (1.0 + 0.15 * rng.standard_normal((len(m.vertices), 1)))
    assert roughness(crumpled, m.faces) > 0.2
    # the twin: angle between the two faces' normals, edge by edge
    n = m.face_normals
    adj = m.face_adjacency
    dense = np.degrees(np.arccos(np.clip((n[adj[:, 0]] * n[adj[:, 1]]).sum(-1), -1, 1)))
    assert roughness(m.vertices, m.faces, angle_deg=10.0) == pytest.approx((dense > 10.0).mean())
    # split along seams: vertices at one place merge, so the figure does not change
    split = m.vertices[m.faces].reshape(-1, 3)
    assert roughness(split, np.arange(len(split)).reshape(-1, 3), angle_deg=10.0) == pytest.approx((dense > 10.0).mean())


def test_surface_quality_of_the_truth_and_of_a_bumpy_copy():
    m = trimesh.creation.icosphere(3)
    v = np.stack([m.vertices + [0, 0, 5]] * 3)
    q = surface_quality(v, m.faces, v, m.faces, [IDENTITY] * 3, n_points=2000)
    assert q["fscore"] == {"1%": 1.0, "2%": 1.0} and q["normal_consistency"] == pytest.approx(1.0, abs=1e-9)
    rng = np.random.default_rng(2)
    bumpy = v * (1.0 + 0.03 * rng.standard_normal((3, len(m.vertices), 1)))
    b = surface_quality(bumpy, m.faces, v, m.faces, [IDENTITY] * 3, n_points=2000)
    assert b["fscore"]["1%"] < b["fscore"]["2%"] < 1.0
    assert b["normal_consistency"] < 0.95 and b["roughness"]["pred"] > b["roughness"]["truth"] == 0.0
    assert math.isfinite(b["normal_consistency"])


def test_mesh_smoothness_of_a_cube_against_its_edges():
    """A triangulated cube: 12 of its 18 interior edges are 90-degree folds, 6 are flat diagonals."""
    m = trimesh.creation.box()
    got = mesh_smoothness(m.vertices, m.faces)
    assert got["roughness"] == pytest.approx(12 / 18)
    assert got["normal_consistency"] == pytest.approx(6 / 18, abs=1e-12)
    flat = trimesh.creation.icosphere(3)
    assert mesh_smoothness(flat.vertices, flat.faces)["normal_consistency"] > 0.99


def test_body_width_ratio_of_an_ellipsoid_and_its_cut_out():
    """An ellipsoid 4 long, 1 high and 0.6 wide across the plane z = 0: the middle slab is about 0.6 / 1 across; the
    same flattened onto the plane is a cut-out (0)."""
    m = trimesh.creation.icosphere(4)
    v = m.vertices * np.array([2.0, 0.5, 0.3])
    assert body_width_ratio(v, np.array([0.0, 0.0, 1.0])) == pytest.approx(0.6, abs=0.03)
    assert body_width_ratio(v + [0, 0, 5.0], np.array([0.0, 0.0, 2.0]), 5.0) == pytest.approx(0.6, abs=0.03)
    assert body_width_ratio(v * [1, 1, 0], np.array([0.0, 0.0, 1.0])) == 0.0


def test_left_right_pairs_read_the_usual_side_markers():
    names = ["Foot.L", "Body", "Foot.R", "b_LeftLeg01_015", "b_RightLeg01_019", "shoulder_fl", "shoulder_fr",
             "ear_l", "ear_r", "Tail", "Palm"]
    assert sorted(left_right_pairs(names)) == [(0, 2), (3, 4), (5, 6), (7, 8)]
    assert left_right_pairs(["Body", "Tail", "Leg"]) == []


def test_body_axes_take_the_side_from_the_left_and_right_joints():
    """A biped with its arms out spans more from hand to hand than from front to back: the vertices' principal
    direction is its side axis, and only the named left/right joints give the views their right labels."""
    m = trimesh.creation.box(extents=(0.6, 1.0, 3.0))  # world: 0.6 front-back (x), 1 up, 3 hand to hand (z)
    c2w = np.eye(4)[None].repeat(2, 0)
    c2w[:, 2, 3] = 5.0
    cam = np.stack([m.vertices + [0, 0, 5.0]] * 2)
    joints = np.stack([np.array([[0.0, 0.0, 1.4], [0.0, 0.0, -1.4], [0.0, 0.5, 0.0]]) + [0, 0, 5.0]] * 2)
    names = ["Hand.L", "Hand.R", "Head"]
    by_vertices = body_axes(cam, c2w)
    by_joints = body_axes(cam, c2w, joints, names)
    z = np.array([0.0, 0.0, 1.0])
    assert abs(by_joints["front"][0, 0] @ z) == pytest.approx(1.0)  # from the front: hand to hand across
    assert abs(by_vertices["front"][0, 0] @ z) == pytest.approx(0.0, abs=1e-9)  # the vertices' reading: side-on
    assert body_axes(cam, c2w, joints, ["A", "B", "C"])["front"] == pytest.approx(by_vertices["front"])


def test_width_ratios_tell_a_cut_out_from_the_body():
    """The truth against itself scores its own ratio; flattened across its side axis it scores near 0."""
    T = 3
    m = trimesh.creation.icosphere(3)
    body = m.vertices * np.array([2.0, 0.6, 0.5])  # long along world x, 0.6 up (y), 0.5 to the side (z)
    c2w = np.stack([np.eye(4)] * T)
    c2w[:, 2, 3] = 5.0
    cam = np.stack([body + [0, 0, 5.0]] * T)
    flat = np.stack([body * [1, 1, 0.05] + [0, 0, 5.0]] * T)
    same = width_ratios(cam, cam, c2w, [IDENTITY] * T)
    assert same["pred"] == pytest.approx(same["truth"]) and same["truth"] == pytest.approx(0.5 / 0.6, abs=0.05)
    assert width_ratios(flat, cam, c2w, [IDENTITY] * T)["pred"] < 0.1


def _turned(verts, c2w, deg):
    """Each frame of ``verts`` turned by ``deg[t]`` degrees about the world's vertical through its centroid
    (counter-clockwise seen from above)."""
    out = np.empty(verts.shape, np.float64)
    for t, (v, a) in enumerate(zip(np.asarray(verts, np.float64), deg)):
        up = c2w[t, :3, :3] @ [0.0, 1.0, 0.0]  # world +y in this frame's camera space
        c = v.mean(0)
        out[t] = (v - c) @ Rotation.from_rotvec(math.radians(a) * up).as_matrix().T + c
    return out


def test_turn_error_of_given_alignments_is_their_angle_about_the_vertical():
    """Each frame's own alignment turns k t degrees about the vertical further than the sequence's (itself a tilt):
    the prediction is turned -k t against the truth; the rotation about another axis counts in the angle alone."""
    T, k = 6, 5.0
    c2w = cam_from_world(T)
    seq_R = Rotation.from_euler("xyz", [10.0, -20.0, 5.0], degrees=True)
    sim = Similarity(1.3, seq_R.as_matrix(), np.array([0.1, 0.0, 0.2]))
    up = c2w[:, :3, :3] @ [0.0, 1.0, 0.0]
    sims = [Similarity(1.3, (Rotation.from_rotvec(math.radians(k * t) * up[t]) * seq_R).as_matrix(), np.zeros(3))
            for t in range(T)]
    r = turn_error(sim, sims, c2w)
    assert r["per_frame_deg"] == pytest.approx([k * t for t in range(T)], abs=1e-6)
    assert r["vertical_deg"] == pytest.approx([-k * t for t in range(T)], abs=1e-6)
    end = k * (T - 1)
    assert (r["end_deg"], r["end_vertical_deg"], r["drift_vertical_deg"]) == pytest.approx((end, -end, -end))
    assert r["mean_deg"] == pytest.approx(k * (T - 1) / 2) and r["max_deg"] == pytest.approx(k * (T - 1))
    tilt = [Similarity(1.0, (Rotation.from_euler("x", 30.0, degrees=True) * seq_R).as_matrix(), np.zeros(3))] * T
    r = turn_error(sim, tilt, c2w)  # 30 degrees about the camera's x: no turn about the vertical
    assert r["end_deg"] == pytest.approx(30.0) and r["vertical_deg"] == pytest.approx([0.0] * T, abs=1e-6)
    assert "vertical_deg" not in turn_error(sim, sims)


def test_turn_error_reads_a_prediction_turned_over_the_clip():
    """The truth turned by k (t - 2.5) degrees about the vertical in frame t: the sequence's alignment sits near the
    middle, each frame's own takes its turn out, and the reading is the known turn; the truth itself reads 0."""
    T, k = 6, 4.0
    verts, faces, _, _ = two_box_sequence(T=T)
    c2w = cam_from_world(T)
    known = np.array([k * (t - (T - 1) / 2) for t in range(T)])
    pred = _turned(verts, c2w, known)
    _, sim = shape_metrics(pred, faces, verts, faces, n_points=500)
    r = turn_error(sim, frame_similarities(pred, faces, verts, faces, sim, n_points=2000), c2w)
    vertical = np.array(r["vertical_deg"])
    assert vertical - vertical.mean() == pytest.approx(known - known.mean(), abs=1.0)  # the turn, frame by frame
    assert vertical == pytest.approx(known, abs=1.5)  # and the sequence's alignment in the middle
    assert r["per_frame_deg"] == pytest.approx(np.abs(known), abs=1.5)
    assert r["end_deg"] == pytest.approx(k * (T - 1) / 2, abs=1.5) and r["end_vertical_deg"] > 0
    assert r["drift_vertical_deg"] == pytest.approx(k * (T - 1), abs=1.0)
    _, sim = shape_metrics(verts, faces, verts, faces, n_points=500)
    exact = turn_error(sim, frame_similarities(verts, faces, verts, faces, sim, n_points=2000), c2w)
    assert exact["max_deg"] < 1e-3 and max(map(abs, exact["vertical_deg"])) < 1e-3
