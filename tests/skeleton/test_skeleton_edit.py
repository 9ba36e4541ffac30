"""Skeleton edits (s3o_warp.skeleton.edit): bone shifting (eq. 5), fitting bones to parts, growth, upsampling,
merging (eqs. 8-9), pruning, and the precisions' round trip through the model's quaternions and log-scales."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh
from s3o_warp.kernels.skinning import skinning_weights
from skeleton_cases import chain, hard_weights, segment_cloud

from s3o_warp.geometry import axis_angle_to_matrix, matrix_to_quat, quat_to_matrix
from s3o_warp.skeleton.edit import (
    fit_bones_to_parts,
    grow_skeleton,
    merge_bones,
    precision_to_quat_scales,
    prune_short_bones,
    shift_bones,
    upsample_skeleton,
)
from s3o_warp.skeleton.joints import bone_endpoints, parent_anchors
from s3o_warp.skeleton.measures import (
    bone_lengths,
    motion_similarity,
    part_extents,
    tree_joints,
)

# -------------------------------------------------------------------------------------------------
# merging (eqs. 8-9) and pruning
# -------------------------------------------------------------------------------------------------


def test_merge_together_merges_and_different_does_not():
    """Chain 0-1-2: 0 and 1 move together, 2 differently -> 0 and 1 merge (eq. 8 with t_o)."""
    X, W = chain()
    C = shift_bones(X, W, np.zeros((3, 3)))
    Q = np.stack([np.eye(3) * (b + 1) for b in range(3)])
    parents = np.array([-1, 0, 1])
    rng = np.random.default_rng(4)
    d = rng.normal(size=(6, 2)) * 3
    a = np.deg2rad(5)  # bone 1: slower and 5 degrees off -> cosine 0.996 in every frame
    F = np.stack([d, 0.8 * d @ np.array([[np.cos(a), np.sin(a)], [-np.sin(a), np.cos(a)]]),
                  d @ np.array([[0.0, 1], [-1, 0]])], 1)
    Sim = motion_similarity(torch.tensor(F).float(), torch.ones(6, 3, dtype=torch.bool)).numpy()
    assert abs(Sim[0, 1] - np.cos(a)) < 1e-5
    e = merge_bones(Sim, W, C, Q, parents, t_o=0.95)
    assert e.num_bones == 2 and e.changed
    assert e.parents.tolist() == [-1, 0]
    assert [i for i, _ in e.sources[0]] == [0, 1] and e.sources[1] == [(2, 1.0)]
    assert e.kept.tolist() == [False, True]
    # stricter threshold than the pair's similarity: nothing merges
    assert not merge_bones(Sim, W, C, Q, parents, t_o=0.999).changed
    # merging a middle pair of a chain 0-1-2-3 re-hangs the child: still a tree, order kept
    Sim4 = np.full((4, 4), 0.5)
    Sim4[1, 2] = Sim4[2, 1] = 0.99
    W4 = np.concatenate([W, W[:, :1]], 1) / 2
    e4 = merge_bones(Sim4, W4, np.zeros((4, 3)), np.stack([np.eye(3)] * 4), np.array([-1, 0, 1, 2]))
    assert e4.parents.tolist() == [-1, 0, 1] and [[i for i, _ in s] for s in e4.sources] == [[0], [1, 2], [3]]
    # non-neighbours never merge even when they move together: 0 and 2 (both moving like d)
    F3 = np.stack([d, d @ np.array([[0.0, 1], [-1, 0]]), d], 1)
    Sim3 = motion_similarity(torch.tensor(F3).float(), torch.ones(6, 3, dtype=torch.bool)).numpy()
    assert not merge_bones(Sim3, W, C, Q, parents).changed


def test_merge_is_greedy_and_log_space_weights_do_not_overflow():
    """Each bone merges at most once per call (the paper's pairwise rule): of a chain whose bones all move
    together, only the first pair merges; the merge weights are a softmax of the weight masses, without
    overflow for thousands of vertices."""
    rng = np.random.default_rng(5)
    N = 5000
    labels = rng.choice(3, N, p=[0.5, 0.3, 0.2])
    W = rng.dirichlet(np.ones(3), N) * 0.2 + hard_weights(labels, 3) * 0.8  # S ~ (2500, 1500, 1000)
    C = rng.normal(size=(3, 3))
    Q = np.stack([np.eye(3) * (b + 1) for b in range(3)])
    parents = np.array([-1, 0, 1])
    Sim = np.ones((3, 3))
    with np.errstate(over="raise"):
        g = merge_bones(Sim, W, C, Q, parents)
        soft = merge_bones(Sim, W, C, Q, parents, temperature=1000.0)
    assert g.num_bones == 2 and [[i for i, _ in src] for src in g.sources] == [[0, 1], [2]]
    for e in (g, soft):
        assert np.isfinite(e.centers).all() and np.isfinite(e.precisions).all()
        for src in e.sources:
            assert abs(sum(w for _, w in src) - 1) < 1e-12
    S = W.sum(0)[:2]
    for temp, e in ((1.0, g), (1000.0, soft)):
        z = S / temp
        w = np.exp(z - z.max()) / np.exp(z - z.max()).sum()  # softmax computed in log space
        np.testing.assert_allclose([wi for _, wi in e.sources[0]], w, rtol=1e-12)
        np.testing.assert_allclose(e.centers[0], w @ C[:2], rtol=1e-12)
        np.testing.assert_allclose(e.precisions[0], np.einsum("i,ijk->jk", w, Q[:2]), rtol=1e-12)
    assert [wi for _, wi in g.sources[0]][0] == 1.0  # temperature 1: the largest part wins outright
    assert 0.1 < [wi for _, wi in soft.sources[0]][1] < 0.9
    with pytest.raises(ValueError, match="temperature"):
        merge_bones(Sim, W, C, Q, parents, temperature=0.0)


def _short_middle(n_long=100, n_short=5):
    """Bones 0 | 1 | 2 along x with hard weights: 0 on [0, 1), 1 (short, few vertices) on [1, 1.05), 2 on [1.05, 2]."""
    rng = np.random.default_rng(21)
    X = np.concatenate([segment_cloud([0, 0, 0], [1, 0, 0], n_long, 0.05, rng),
                        segment_cloud([1, 0, 0], [1.05, 0, 0], n_short, 0.05, rng),
                        segment_cloud([1.05, 0, 0], [2, 0, 0], n_long, 0.05, rng)])
    W = hard_weights(np.repeat([0, 1, 2], [n_long, n_short, n_long]), 3)
    C = shift_bones(X, W, np.zeros((3, 3)))
    Q = np.stack([np.eye(3) * (b + 1) for b in range(3)])
    return X, W, C, Q


def test_prune_short_bones_merges_into_the_parent():
    """A short inner bone is merged into its parent (the long one wins: its centre, precision and motion)."""
    X, W, C, Q = _short_middle()
    E = bone_endpoints(X, W, tree_joints(np.array([-1, 0, 1])))
    L = bone_lengths(E, X)
    assert L[1] < 0.1 < 0.4 < min(L[0], L[2])  # the middle bone is the short one
    e = prune_short_bones(L, 0.2, W, C, Q, np.array([-1, 0, 1]), extents=np.array([1.0, 0.05, 1.0]))
    assert e.changed and e.num_bones == 2 and e.parents.tolist() == [-1, 0]
    assert [i for i, _ in e.sources[0]] == [0, 1] and e.sources[1] == [(2, 1.0)]
    np.testing.assert_allclose(e.centers[0], C[0], atol=1e-12)  # mass 100 vs 5: bone 0 wins outright
    np.testing.assert_allclose(e.precisions[0], Q[0], atol=1e-12)
    assert e.extents.tolist() == [1.0, 1.0]
    # nothing shorter than the limit: unchanged; a limit of 0 prunes only empty bones
    assert not prune_short_bones(np.array([1.0, 0.5, 1.0]), 0.2, W, C, Q, np.array([-1, 0, 1])).changed
    assert not prune_short_bones(np.zeros(3), 0.0, W, C, Q, np.array([-1, 0, 1])).changed  # none empty
    # a chain of short bones collapses into the long bone it hangs from; the long child re-hangs on it
    lab4 = W.argmax(1)
    lab4[-50:] = 3  # the far half of bone 2's vertices go to bone 3
    W4 = hard_weights(lab4, 4)
    C4, Q4 = np.concatenate([C, C[:1]]), np.concatenate([Q, Q[:1]])
    e4 = prune_short_bones(np.array([1.0, 0.02, 0.01, 1.0]), 0.1, W4, C4, Q4, np.array([-1, 0, 1, 2]))
    assert [[i for i, _ in s] for s in e4.sources] == [[0, 1, 2], [3]] and e4.parents.tolist() == [-1, 0]
    # a short root merges with its longest child
    er = prune_short_bones(np.array([0.01, 0.5, 1.0]), 0.1, W, C, Q, np.array([-1, 0, 0]))
    assert [[i for i, _ in s] for s in er.sources] == [[0, 2], [1]] and er.parents.tolist() == [-1, 0]
    # a short end bone that owns vertices (a tail tip, a hoof) is kept; one that owns none is merged
    assert not prune_short_bones(np.array([1.0, 1.0, 0.01]), 0.1, W, C, Q, np.array([-1, 0, 1])).changed
    W_empty = W.copy()
    W_empty[:, 1] += W_empty[:, 2]
    W_empty[:, 2] = 0.0  # bone 2 owns nothing
    ee = prune_short_bones(np.array([1.0, 1.0, 0.0]), 0.1, W_empty, C, Q, np.array([-1, 0, 1]))
    assert [[i for i, _ in s] for s in ee.sources] == [[0], [1, 2]]
    # an empty inner bone goes whatever its length (its joints fall back to far-apart borders), also at limit 0
    W_mid = W.copy()
    W_mid[:, 0] += W_mid[:, 1]
    W_mid[:, 1] = 0.0  # bone 1 owns nothing
    for limit in (0.1, 0.0):
        em = prune_short_bones(np.array([1.0, 0.8, 1.0]), limit, W_mid, C, Q, np.array([-1, 0, 1]))
        assert [[i for i, _ in s] for s in em.sources] == [[0, 1], [2]] and em.parents.tolist() == [-1, 0]
    # ... and a short bone whose only child owns nothing is an end bone: it stays, the empty child goes
    ee = prune_short_bones(np.array([1.0, 0.01, 0.0]), 0.1, W_empty, C, Q, np.array([-1, 0, 1]))
    assert [[i for i, _ in s] for s in ee.sources] == [[0], [1, 2]]
    # a lone bone has nothing to merge with
    assert not prune_short_bones(np.array([0.0]), 0.1, W[:, :1] * 0, C[:1], Q[:1], np.array([-1])).changed
    with pytest.raises(ValueError, match="min_length"):
        prune_short_bones(L, -1.0, W, C, Q, np.array([-1, 0, 1]))


# -------------------------------------------------------------------------------------------------
# shifting (eq. 5), growth, upsampling
# -------------------------------------------------------------------------------------------------


def test_shift_moves_centre_to_part_centroid():
    rng = np.random.default_rng(6)
    X = rng.normal(size=(30, 3))
    labels = np.r_[np.zeros(10, int), np.ones(20, int)]
    W = hard_weights(labels, 3, soft=0.2)  # bone 2 owns no vertex
    C = rng.normal(size=(3, 3))
    out = shift_bones(X, W, C)
    np.testing.assert_allclose(out[0], X[:10].mean(0))
    np.testing.assert_allclose(out[1], X[10:].mean(0))
    np.testing.assert_array_equal(out[2], C[2])


def test_fit_bones_to_parts_moves_a_tail_bone_onto_its_tilted_part():
    """A body capsule along x and a tail capsule rising from its end; the tail bone starts on the horizontal chord
    below the tail (as a lift from a 2D chord leaves it), so the body's wide Gaussian owns the tail. Fitted to
    the tail's labelled faces, the bone sits at their area centroid, along their axis, radii kept, and owns them."""
    body = trimesh.creation.capsule(height=1.6, radius=0.25, count=[16, 16])
    body.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))  # along x
    tail = trimesh.creation.capsule(height=0.5, radius=0.04, count=[12, 12])
    tilt = np.radians(35.0)
    axis = np.array([-np.cos(tilt), np.sin(tilt), 0.0])
    R = trimesh.geometry.align_vectors([0, 0, 1], axis)
    tail.apply_transform(R)
    tail.apply_translation(np.array([-1.05, 0.0, 0.0]) + 0.3 * axis)
    mesh = trimesh.util.concatenate([body, tail])
    parts = np.r_[np.zeros(len(body.faces), int), np.ones(len(tail.faces), int)]
    tail_verts = np.arange(len(body.vertices), len(mesh.vertices))
    r_long, r_short = 0.3, 0.04

    def ellipsoid_q(direction, radii):
        d = np.asarray(direction, float) / np.linalg.norm(direction)
        return 2.0 * (np.eye(3) / radii[1] ** 2 + (1 / radii[0] ** 2 - 1 / radii[1] ** 2) * np.outer(d, d))

    C = np.array([[0.0, 0.0, 0.0], [-1.35, 0.0, 0.0]])  # the tail bone on the horizontal chord
    Q = np.stack([ellipsoid_q([1, 0, 0], (1.1, 0.3)), ellipsoid_q([1, 0, 0], (r_long, r_short))])

    def owners(C, Q):
        f32 = dict(dtype=torch.float32)
        W = skinning_weights(torch.as_tensor(mesh.vertices, **f32), torch.as_tensor(C, **f32), torch.as_tensor(Q, **f32))
        return W.argmax(1).numpy()

    assert (owners(C, Q)[tail_verts] == 1).mean() < 0.5  # the chord's bone misses its part
    C2, Q2, moved = fit_bones_to_parts(mesh.vertices, mesh.faces, parts, C, Q, min_faces=4)
    assert moved.all()
    tri = mesh.vertices[mesh.faces[parts == 1]]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    np.testing.assert_allclose(C2[1], (area[:, None] * tri.mean(1)).sum(0) / area.sum(), atol=1e-12)
    lam, U = np.linalg.eigh(Q2[1])
    np.testing.assert_allclose(lam, np.linalg.eigvalsh(Q[1]), rtol=1e-10)  # radii kept
    assert abs(U[:, 0] @ axis) > 0.999  # long axis along the tail
    # the outer half of the tail (the base half shares the body's Gaussian): before, the body's; after, the tail's
    along = (mesh.vertices[tail_verts] - np.array([-1.05, 0.0, 0.0])) @ axis
    outer = tail_verts[along > 0.3]
    assert (owners(C, Q)[outer] == 1).mean() < 0.2
    assert (owners(C2, Q2)[outer] == 1).mean() > 0.95
    # a part with fewer faces than min_faces keeps its bone; so does a bone no face names
    C3, Q3, moved3 = fit_bones_to_parts(mesh.vertices, mesh.faces, np.where(parts == 1, 5, 0), C, Q, min_faces=4)
    assert moved3.tolist() == [True, False]
    np.testing.assert_array_equal(C3[1], C[1])
    np.testing.assert_array_equal(Q3[1], Q[1])
    with pytest.raises(ValueError, match="face_parts"):
        fit_bones_to_parts(mesh.vertices, mesh.faces, parts[:-1], C, Q)


def _limb(length, n=200, seed=7):
    """Torso blob at the origin (bone 0) and a limb from x=1 to x=1+length (bone 1, a leaf)."""
    rng = np.random.default_rng(seed)
    torso = rng.normal(0, 0.3, (300, 3))
    limb = segment_cloud([1, 0, 0], [1 + length, 0, 0], n, 0.05, rng)
    X = np.concatenate([torso, limb])
    W = hard_weights(np.r_[np.zeros(300, int), np.ones(n, int)], 2, soft=0.02)
    return X, W


def test_grow_splits_stretched_end_part_in_order():
    X0, W0 = _limb(1.0)
    ref = part_extents(X0, W0)
    X, W = _limb(3.0)  # the limb grew past 2x its initial extent
    C = shift_bones(X, W, np.zeros((2, 3)))
    Q = np.stack([np.eye(3)] * 2)
    parents = np.array([-1, 0])
    anchors = parent_anchors(parents, [[0, 1]], [[1.0, 0, 0]])
    assert np.isnan(anchors[0]).all() and anchors[1].tolist() == [1, 0, 0]
    e = grow_skeleton(X, W, C, Q, parents, ref, growth_factor=2.0, sections=3, anchors=anchors)
    assert e.num_bones == 4
    assert e.parents.tolist() == [-1, 0, 1, 2]  # parent -> section 1 -> section 2 -> section 3
    xs = e.centers[1:, 0]
    assert (np.diff(xs) > 0.5).all() and 1.0 < xs[0] < xs[-1] < 4.0  # in order along the growth direction
    assert [s[0][0] for s in e.sources] == [0, 1, 1, 1] and e.kept.tolist() == [True, False, False, False]
    assert e.joints.tolist() == [[1, 2], [2, 3]]
    # equal-count sections: about a third of the limb's vertices each (argmax labels of the limb)
    lab = np.argmin(np.abs(X[300:, 0, None] - xs[None]), 1)
    assert np.bincount(lab).min() > 50
    # the references are updated: growing again right away does nothing
    assert e.extents is not None and (e.extents[1:] < part_extents(X, W)[1]).all()
    # the torso is not a leaf and the limb did not stretch enough -> identity
    assert not grow_skeleton(X, W, C, Q, parents, ref * 2, growth_factor=2.0).changed


def test_upsample_splits_every_bone_along_principal_axis():
    X, W = chain()
    C = shift_bones(X, W, np.zeros((3, 3)))
    Q = np.stack([np.eye(3)] * 3)
    e = upsample_skeleton(X, W, C, Q, np.array([-1, 0, 1]))
    assert e.num_bones == 6
    # each old bone b -> new bones 2b (nearer its parent) and 2b+1; chained through the tree
    assert e.parents.tolist() == [-1, 0, 1, 2, 3, 4]
    assert (np.diff(e.centers[:, 0]) > 0).all()
    assert [s[0][0] for s in e.sources] == [0, 0, 1, 1, 2, 2]
    # the halves are thinner along x than across
    for Qb in e.precisions:
        assert Qb[0, 0] > 0 and np.all(np.linalg.eigvalsh(Qb) > 0)


# -------------------------------------------------------------------------------------------------
# precisions
# -------------------------------------------------------------------------------------------------


def test_precision_round_trip():
    rng = np.random.default_rng(11)
    R = axis_angle_to_matrix(torch.tensor(rng.normal(size=(4, 3)))).numpy()
    s = rng.normal(size=(4, 3))
    Q = np.transpose(R, (0, 2, 1)) @ (np.exp(s)[..., None] * R)  # V^T diag(exp s) V with V = R
    q, ls = precision_to_quat_scales(Q)
    V = quat_to_matrix(torch.tensor(q)).numpy()
    np.testing.assert_allclose(np.transpose(V, (0, 2, 1)) @ (np.exp(ls)[..., None] * V), Q, atol=1e-10)


def test_precision_round_trip_of_tilted_limbs():
    """Thin Gaussians along tilted directions (a tail, a neck), two equal short axes: eigh's axes often make a
    half turn, where a quaternion taking its signs from the off-diagonal differences mirrors the long axis."""
    a = np.linspace(-np.pi, np.pi, 73)
    long_axis = np.stack([np.cos(a), np.sin(a), np.where(np.arange(len(a)) % 2 == 0, 0.0, 0.3 * np.sin(3 * a))], 1)
    long_axis /= np.linalg.norm(long_axis, axis=1, keepdims=True)
    Q = 2.0 * (np.eye(3) / 0.03**2 + (1 / 0.2**2 - 1 / 0.03**2) * long_axis[:, :, None] * long_axis[:, None, :])
    q, ls = precision_to_quat_scales(Q)
    V = quat_to_matrix(torch.tensor(q)).numpy()
    back = np.transpose(V, (0, 2, 1)) @ (np.exp(ls)[..., None] * V)
    np.testing.assert_allclose(back, Q, rtol=0, atol=1e-8 * np.abs(Q).max())
    # the coarse model's path: eigh's axes as float32 rows into S3OModel's quaternions
    lam, U = np.linalg.eigh(Q)
    V = np.transpose(U, (0, 2, 1)).copy()
    V[np.linalg.det(V) < 0, 2] *= -1
    q32 = matrix_to_quat(torch.as_tensor(V, dtype=torch.float32))
    V32 = quat_to_matrix(q32.double()).numpy()
    back = np.transpose(V32, (0, 2, 1)) @ (lam[..., None] * V32)
    np.testing.assert_allclose(back, Q, rtol=0, atol=1e-5 * np.abs(Q).max())


def test_matrix_to_quat_round_trips_half_turns():
    g = torch.Generator().manual_seed(3)
    axis = torch.nn.functional.normalize(torch.randn(600, 3, generator=g, dtype=torch.float64), dim=1)
    angle = torch.cat([torch.full((200,), np.pi, dtype=torch.float64),
                       np.pi - 1e-4 * torch.rand(200, generator=g, dtype=torch.float64),
                       np.pi * torch.rand(200, generator=g, dtype=torch.float64)])
    R = axis_angle_to_matrix(axis * angle[:, None])
    q = matrix_to_quat(R)
    torch.testing.assert_close(quat_to_matrix(q), R, rtol=0, atol=1e-12)
    assert (q[:, 0] >= 0).all()
    torch.testing.assert_close(q.norm(dim=1), torch.ones(600, dtype=torch.float64))
