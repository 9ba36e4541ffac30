"""Joints (s3o_warp.skeleton.joints): joint positions over vertices and surface samples, bone ends and lengths,
and joint creation (eqs. 6-7): splitting a bone at the midpoint of its ends."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from s3o_warp.kernels.skinning import skinning_weights
from skeleton_cases import chain

from s3o_warp.geometry import axis_angle_to_matrix
from s3o_warp.skeleton.edit import shift_bones
from s3o_warp.skeleton.joints import (
    bone_endpoints,
    bone_halves,
    gaussian_weights,
    joint_positions,
    joint_selection,
    split_at_joints,
    surface_samples,
)
from s3o_warp.skeleton.measures import (
    assign_parts,
    bone_lengths,
    bone_lengths_per_frame,
    create_joints,
    tree_joints,
)

# -------------------------------------------------------------------------------------------------
# joint positions
# -------------------------------------------------------------------------------------------------


def test_joint_position_is_mean_of_shared_vertices_and_fallback():
    rng = np.random.default_rng(8)
    X = rng.normal(size=(40, 3))
    W = np.zeros((40, 3))
    W[:, 0] = 1
    W[5:12] = [0.45, 0.45, 0.1]  # shared by bones 0 and 1
    W[12:14] = [0.5, 0.39, 0.11]  # just below t_r for bone 1
    W[20:30] = [0.3, 0.0, 0.7]  # bones 0 and 2 never both >= 0.4
    W[20:23] = [0.35, 0.0, 0.65]
    J = joint_positions(X, W, [[0, 1], [0, 2]], t_r=0.4, fallback_count=3)
    np.testing.assert_allclose(J[0], X[5:12].mean(0))
    np.testing.assert_allclose(J[1], X[20:23].mean(0))  # the 3 vertices of largest min(W0, W2)
    Jt = joint_positions(np.stack([X, X + 1]), W, [[0, 1]])
    np.testing.assert_allclose(Jt[1, 0], X[5:12].mean(0) + 1)


def _tube(rings, k=6, radius=0.2):
    """A closed tube along z: ``k`` vertices on each ring at heights ``rings``, capped by one vertex at each end."""
    a = 2 * np.pi * np.arange(k) / k
    X = [[0, 0, rings[0] - radius]]
    for z in rings:
        X += [[radius * np.cos(t), radius * np.sin(t), z] for t in a]
    X.append([0, 0, rings[-1] + radius])
    X = np.asarray(X, float)
    F, n = [], len(rings)
    for i in range(k):
        j = (i + 1) % k
        F.append([0, 1 + j, 1 + i])
        for r in range(n - 1):
            p, q = 1 + r * k, 1 + (r + 1) * k
            F += [[p + i, p + j, q + j], [p + i, q + j, q + i]]
        F.append([len(X) - 1, 1 + (n - 1) * k + i, 1 + (n - 1) * k + j])
    return X, np.asarray(F, np.int64)


def test_surface_samples_cover_faces_evenly_with_gaussian_weights():
    X, F = _tube([0.0, 1.0, 2.0])
    C = np.array([[0, 0, 0.2], [0, 0, 1.8]])
    Q = np.stack([np.diag([1.0, 2.0, 3.0])] * 2)
    assert surface_samples(X, F, C, Q, 1) is None
    for L in (2, 4):
        s = surface_samples(X, F, C, Q, L)
        E = len(np.unique(np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), 1), axis=0))
        assert len(s.index) == len(X) + (L - 1) * E + len(F) * (L - 1) * (L - 2) // 2
        np.testing.assert_allclose(s.bary.sum(1), 1.0)
        assert (s.bary >= 0).all()
        P = np.einsum("sk,skc->sc", s.bary, X[s.index])
        assert len(np.unique(P.round(9), axis=0)) == len(P)  # every point once
        np.testing.assert_allclose(s.weights, gaussian_weights(P, C, Q))
    # the Gaussian weights are the skinning kernel's (float32)
    f32 = dict(dtype=torch.float32)
    Wk = skinning_weights(torch.tensor(P, **f32), torch.tensor(C, **f32), torch.tensor(Q, **f32)).numpy()
    np.testing.assert_allclose(gaussian_weights(P, C, Q), Wk, atol=1e-5)
    with pytest.raises(ValueError, match="faces"):
        surface_samples(X, F[:, :2], C, Q, 2)


def test_joint_on_surface_samples_finds_a_boundary_between_vertex_rings():
    # two bones along a tube whose weight boundary (z = 0.25) lies half way between two rings of vertices:
    # no vertex has both weights >= t_r, the vertex fallback lands on a ring, the samples find the band
    X, F = _tube([-1.0, -0.5, 0.0, 0.5, 1.0, 1.5])
    C = np.array([[0, 0, -0.5], [0, 0, 1.0]])
    Q = np.stack([np.diag([1.0, 1.0, 40.0])] * 2)
    W = gaussian_weights(X, C, Q)
    assert (np.minimum(W[:, 0], W[:, 1]) < 0.4).all()
    s = surface_samples(X, F, C, Q, 8)
    Jv = joint_positions(X, W, [[0, 1]])[0]
    Js = joint_positions(X, W, [[0, 1]], samples=s)[0]
    assert abs(Jv[2] - 0.25) > 0.2
    assert abs(Js[2] - 0.25) < 0.02 and np.linalg.norm(Js[:2]) < 0.02  # on the boundary and the tube's axis
    S = joint_selection(W, [[0, 1]], samples=s)
    assert S.shape == (1, len(X)) and (S >= 0).all()
    np.testing.assert_allclose(S.sum(1), 1.0)
    Y = X + np.array([0.3, -0.1, 2.0])  # the selection follows the (here translated) mesh
    np.testing.assert_allclose(joint_positions(np.stack([X, Y]), W, [[0, 1]], samples=s)[1, 0], Js + [0.3, -0.1, 2.0])
    E = bone_endpoints(X, W, [[0, 1]], samples=s)
    np.testing.assert_allclose(E[0, 0] @ X, Js, atol=1e-12)  # an end bone's first end is its joint
    with pytest.raises(ValueError, match="samples"):
        joint_selection(W[:, :1], [[0, 0]], samples=s)


# -------------------------------------------------------------------------------------------------
# bone lengths and joint creation (eqs. 6-7)
# -------------------------------------------------------------------------------------------------


def test_bone_lengths_and_create_joints_for_stretching_bone():
    X, W = chain()
    pairs = tree_joints(np.array([-1, 0, 1]))
    assert pairs.tolist() == [[0, 1], [1, 2]]
    E = bone_endpoints(X, W, pairs)
    L0 = bone_lengths(E, X)
    assert abs(L0[1] - 1.0) < 0.1  # joints at x ~ 1 and 2
    assert 0.7 < L0[0] < 1.2 and 0.7 < L0[2] < 1.2  # joint to far end
    rng = np.random.default_rng(9)
    rigid, stretch = [], []
    for f in range(6):
        R = axis_angle_to_matrix(torch.tensor(rng.normal(size=3) * 0.5)).numpy()
        rigid.append(X @ R.T + rng.normal(size=3))
        s = 1 + 0.5 * f / 5  # the middle part stretches by up to 50 %, the rest translates with it
        Y = X.copy()
        mid = (X[:, 0] > 1) & (X[:, 0] < 2)
        Y[mid, 0] = 1 + (X[mid, 0] - 1) * s
        Y[X[:, 0] >= 2, 0] += s - 1
        stretch.append(Y)
    Lr = bone_lengths_per_frame(E, np.stack(rigid))
    Ls = bone_lengths_per_frame(E, np.stack(stretch))
    assert not create_joints(Lr).any()
    assert create_joints(Ls).tolist() == [False, True, False]
    assert not create_joints(Ls[:2]).any()  # 10 % stretch: below t_d
    # creating the joint: bone 1 is split in two at the midpoint of its joints (x ~ 1.5)
    C = shift_bones(X, W, np.zeros((3, 3)))
    Q = np.stack([np.eye(3)] * 3)
    e = split_at_joints(X, W, C, Q, np.array([-1, 0, 1]), E, create_joints(Ls))
    assert e.num_bones == 4 and e.parents.tolist() == [-1, 0, 1, 2]
    assert [s[0][0] for s in e.sources] == [0, 1, 1, 2]
    assert e.joints.tolist() == [[1, 2]] and abs(e.joint_positions[0, 0] - 1.5) < 0.1
    assert e.centers[1, 0] < 1.5 < e.centers[2, 0]


def test_bone_halves_cut_an_end_part_at_its_endpoints_midpoint():
    """The end bone of the chain (x in [2, 3], joint at 2) is cut at about x = 2.5: the near half first."""
    X, W = chain()
    P = np.array([-1, 0, 1])
    E = bone_endpoints(X, W, tree_joints(P))
    C = shift_bones(X, W, np.zeros((3, 3)))
    bones, W2 = bone_halves(X, W, C, P, E, np.array([False, False, True]))
    assert bones.tolist() == [2] and W2.shape == (len(X), 2)
    lab = assign_parts(W)
    near, far = W2[:, 0] > 0, W2[:, 1] > 0
    assert not (near & far).any() and ((near | far) == (lab == 2)).all()
    m = (bone_endpoints(X, W, tree_joints(P))[2] @ X).mean(0)[0]
    assert 2.3 < m < 2.7 and X[near, 0].max() <= m + 1e-9 < X[far, 0].min()
    np.testing.assert_allclose(W2[near, 0], W[near, 2])
    # the same cut as the joint creation: its two new bones own the two halves
    e = split_at_joints(X, W, C, np.stack([np.eye(3)] * 3), P, E, np.array([False, False, True]))
    assert e.num_bones == 4 and e.centers[2, 0] < m < e.centers[3, 0]
    with pytest.raises(ValueError, match="bone_halves"):
        bone_halves(X, W, C, P[:2], E, np.array([False, False, True]))
    # too few vertices for two halves: not cut
    assert len(bone_halves(X, W, C, P, E, np.array([False, False, True]), min_section_vertices=len(X))[0]) == 0
