"""Regularisers (dynamic rigidity, ARAP, Laplacian, symmetry) and mesh_edges against the dense twins."""

from __future__ import annotations

import pytest
import torch
import trimesh
from s3o_warp.kernels.regularisers import (
    arap_loss,
    dynamic_rigidity_loss,
    laplacian_loss,
    mesh_edges,
    symmetry_loss,
)

from s3o_warp.reference.regularisers import (
    arap_loss_reference,
    dynamic_rigidity_loss_reference,
    laplacian_loss_reference,
    symmetry_loss_reference,
)


def _sphere(subdivisions: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    m = trimesh.creation.icosphere(subdivisions)
    return torch.tensor(m.vertices, dtype=torch.float32), torch.tensor(m.faces, dtype=torch.int64)


def _grads(fn, tensors, *rest):
    """(value, grads) of a scalar fn(*tensors, *rest) w.r.t. each tensor."""
    leaves = [x.detach().clone().requires_grad_(True) for x in tensors]
    out = fn(*leaves, *rest)
    out.backward()
    return out.detach(), [x.grad for x in leaves]


def _compare(fn, ref, tensors, rest=(), atol=1e-6, rtol=1e-4):
    out, grads = _grads(fn, tensors, *rest)
    ref_out, ref_grads = _grads(ref, [x.double() for x in tensors], *rest)
    assert out.dtype == torch.float32 and out.dim() == 0
    torch.testing.assert_close(out.double(), ref_out, atol=atol, rtol=rtol)
    for g, r in zip(grads, ref_grads):
        assert torch.isfinite(g).all()
        torch.testing.assert_close(g.double(), r, atol=atol, rtol=rtol)
    return out, grads


# -------------------------------------------------------------------------------------------------
# mesh_edges
# -------------------------------------------------------------------------------------------------


def test_mesh_edges_tetrahedron_and_degenerate(device):
    faces = torch.tensor([[0, 1, 2], [0, 3, 1], [1, 3, 2], [2, 3, 0], [2, 2, 1]], device=device)
    e = mesh_edges(faces)
    expect = torch.tensor([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]], device=device)
    assert torch.equal(e, expect)


def test_mesh_edges_sphere_euler():
    verts, faces = _sphere(2)
    e = mesh_edges(faces)
    assert verts.shape[0] - e.shape[0] + faces.shape[0] == 2  # closed genus-0 surface
    assert (e[:, 0] < e[:, 1]).all()


def test_mesh_edges_errors():
    with pytest.raises(ValueError, match=r"faces must have shape \(\*, 3\)"):
        mesh_edges(torch.zeros(4, 4, dtype=torch.long))
    with pytest.raises(TypeError, match="integer"):
        mesh_edges(torch.zeros(4, 3))


# -------------------------------------------------------------------------------------------------
# dynamic rigidity and ARAP
# -------------------------------------------------------------------------------------------------


def _motion(device, frames=4, bones=5, seed=0):
    gen = torch.Generator().manual_seed(seed)
    verts, faces = _sphere(1)
    seq = verts[None] + 0.1 * torch.randn(frames, *verts.shape, generator=gen)
    weights = torch.softmax(3.0 * torch.randn(verts.shape[0], bones, generator=gen), 1)
    return seq.to(device), mesh_edges(faces).to(device), weights.to(device)


def test_dynamic_rigidity_values_and_grads(device):
    seq, edges, weights = _motion(device)
    out, (gv, gw) = _grads(lambda v, w: dynamic_rigidity_loss(v, edges, w, 0.2), [seq, weights])
    ref, (rv, rw) = _grads(lambda v, w: dynamic_rigidity_loss_reference(v, edges, w, 0.2), [seq.double(), weights.double()])
    torch.testing.assert_close(out.double(), ref, atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(gv.double(), rv, atol=1e-7, rtol=1e-4)
    torch.testing.assert_close(gw.double(), rw, atol=1e-7, rtol=1e-4)


def test_dynamic_rigidity_one_hot_and_zero_weights(device):
    """One-hot rows (entropy 0, many exact zeros) give R = 1 / lam^2 and finite gradients."""
    seq, edges, weights = _motion(device)
    one_hot = torch.nn.functional.one_hot(weights.argmax(1), weights.shape[1]).float()
    out, (gv, gw) = _grads(lambda v, w: dynamic_rigidity_loss(v, edges, w), [seq, one_hot])
    ref, (rv, rw) = _grads(lambda v, w: dynamic_rigidity_loss_reference(v, edges, w), [seq.double(), one_hot.double()])
    torch.testing.assert_close(out.double(), ref, atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(out, arap_loss(seq, edges) / 0.1**2, atol=1e-5, rtol=1e-5)
    assert torch.isfinite(gw).all()
    torch.testing.assert_close(gw.double(), rw, atol=1e-4, rtol=1e-4)


def test_dynamic_rigidity_lower_near_joints(device):
    """Uniform weights (max entropy) make edges softer than one-hot weights: smaller loss."""
    seq, edges, weights = _motion(device)
    uniform = torch.full_like(weights, 1.0 / weights.shape[1])
    one_hot = torch.nn.functional.one_hot(weights.argmax(1), weights.shape[1]).float()
    assert dynamic_rigidity_loss(seq, edges, uniform) < dynamic_rigidity_loss(seq, edges, one_hot)


def test_arap_values_and_grads(device):
    seq, edges, _ = _motion(device, frames=3)
    _compare(arap_loss, arap_loss_reference, [seq], (edges,))


def test_arap_rigid_motion_is_zero(device):
    verts, faces = _sphere(1)
    rot = torch.tensor(trimesh.transformations.rotation_matrix(0.7, [1, 2, 3])[:3, :3], dtype=torch.float32)
    seq = torch.stack([verts, verts @ rot.T + torch.tensor([1.0, -2.0, 0.5])]).to(device)
    assert float(arap_loss(seq, mesh_edges(faces).to(device))) < 1e-6


def test_stretch_zero_length_edges_no_nan(device):
    """Coincident vertices (zero-length edges) and unchanged lengths: finite, twin-equal gradients."""
    seq, edges, weights = _motion(device, frames=3)
    i, j = int(edges[0, 0]), int(edges[0, 1])
    seq[:, j] = seq[:, i]  # edge 0 has zero length in every frame
    seq[2] = seq[1]  # frames 1 and 2 identical: |.| at 0
    _compare(arap_loss, arap_loss_reference, [seq], (edges,))
    _, (gv,) = _grads(lambda v: dynamic_rigidity_loss(v, edges, weights), [seq])
    assert torch.isfinite(gv).all()


def test_rigidity_reference_gradcheck():
    gen = torch.Generator().manual_seed(3)
    seq = torch.randn(3, 4, 3, generator=gen, dtype=torch.float64, requires_grad=True)
    edges = torch.tensor([[0, 1], [1, 2], [2, 3], [0, 3]])
    w = torch.softmax(torch.randn(4, 3, generator=gen, dtype=torch.float64), 1).requires_grad_()
    assert torch.autograd.gradcheck(lambda v, ww: dynamic_rigidity_loss_reference(v, edges, ww), (seq, w))
    assert torch.autograd.gradcheck(lambda v: arap_loss_reference(v, edges), (seq,))


@pytest.mark.parametrize(
    "kwargs, exc, match",
    [
        ({"verts": torch.zeros(1, 4, 3)}, ValueError, r"T >= 2"),
        ({"verts": torch.zeros(2, 4)}, ValueError, r"verts must have shape \(\*, \*, 3\)"),
        ({"edges": torch.tensor([[0, 4]])}, ValueError, r"edges indices must lie in \[0, 4\)"),
        ({"edges": torch.zeros(0, 2, dtype=torch.long)}, ValueError, "edges is empty"),
        ({"edges": torch.zeros(3, 2)}, TypeError, "edges must be an integer tensor"),
        ({"weights": torch.zeros(5, 2)}, ValueError, r"weights must have shape \(4, \*\)"),
        ({"weights": torch.zeros(4, 2, dtype=torch.float64)}, TypeError, "weights must be float32"),
        ({"lam": 0.0}, ValueError, "lam must be > 0"),
    ],
)
def test_dynamic_rigidity_errors(kwargs, exc, match):
    args = {"verts": torch.zeros(2, 4, 3), "edges": torch.tensor([[0, 1]]), "weights": torch.ones(4, 2) / 2, "lam": 0.1}
    args.update(kwargs)
    with pytest.raises(exc, match=match):
        dynamic_rigidity_loss(**args)


# -------------------------------------------------------------------------------------------------
# Laplacian
# -------------------------------------------------------------------------------------------------


def test_laplacian_values_and_grads(device):
    gen = torch.Generator().manual_seed(4)
    verts, faces = _sphere(1)
    verts = verts + 0.05 * torch.randn(verts.shape, generator=gen)
    _compare(laplacian_loss, laplacian_loss_reference, [verts.to(device)], (faces.to(device),))


def test_laplacian_isolated_vertex_and_plane(device):
    """A vertex in no face contributes 0; a flat regular grid's interior has zero Laplacian."""
    gen = torch.Generator().manual_seed(5)
    verts, faces = _sphere(1)
    verts = torch.cat([verts + 0.05 * torch.randn(verts.shape, generator=gen), torch.tensor([[5.0, 5.0, 5.0]])])
    out, _ = _compare(laplacian_loss, laplacian_loss_reference, [verts.to(device)], (faces.to(device),))
    assert torch.isfinite(out)
    grid = torch.stack(torch.meshgrid(torch.arange(3.0), torch.arange(3.0), indexing="ij"), -1).reshape(-1, 2)
    gverts = torch.cat([grid, torch.zeros(9, 1)], 1)
    quads = [(r * 3 + c, r * 3 + c + 1, (r + 1) * 3 + c + 1, (r + 1) * 3 + c) for r in range(2) for c in range(2)]
    gfaces = torch.tensor([f for a, b, c, d in quads for f in ((a, b, c), (a, c, d))])
    lap = laplacian_loss(gverts.to(device), gfaces.to(device))
    torch.testing.assert_close(lap.double().cpu(), laplacian_loss_reference(gverts.double(), gfaces), atol=1e-6, rtol=1e-5)


def test_laplacian_reference_gradcheck():
    verts = torch.randn(4, 3, dtype=torch.float64, requires_grad=True)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    assert torch.autograd.gradcheck(lambda v: laplacian_loss_reference(v, faces), (verts,))


def test_laplacian_errors():
    with pytest.raises(ValueError, match=r"faces indices must lie in \[0, 3\)"):
        laplacian_loss(torch.zeros(3, 3), torch.tensor([[0, 1, 3]]))
    with pytest.raises(ValueError, match=r"verts must have shape \(\*, 3\)"):
        laplacian_loss(torch.zeros(2, 3, 3), torch.tensor([[0, 1, 2]]))


# -------------------------------------------------------------------------------------------------
# symmetry
# -------------------------------------------------------------------------------------------------


def test_symmetry_values_and_grads(device):
    gen = torch.Generator().manual_seed(6)
    verts = torch.randn(60, 3, generator=gen).to(device)
    normal = torch.tensor([1.0, 0.3, -0.2], device=device)
    plane_args = (normal, 0.25)
    out, (gv,) = _grads(lambda v: symmetry_loss(v, plane_args), [verts])
    ref, (rv,) = _grads(lambda v: symmetry_loss_reference(v, (normal.double(), 0.25)), [verts.double()])
    torch.testing.assert_close(out.double(), ref, atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(gv.double(), rv, atol=1e-6, rtol=1e-4)
    # gradients also reach a learnable plane
    _, (gn,) = _grads(lambda n: symmetry_loss(verts, (n, 0.25)), [normal])
    _, (rn,) = _grads(lambda n: symmetry_loss_reference(verts.double(), (n, 0.25)), [normal.double()])
    torch.testing.assert_close(gn.double(), rn, atol=1e-5, rtol=1e-4)


def test_symmetry_of_symmetric_shape_and_scale_of_normal(device):
    gen = torch.Generator().manual_seed(7)
    half = torch.randn(30, 3, generator=gen) + torch.tensor([1.5, 0.0, 0.0])
    verts = torch.cat([half, half * torch.tensor([-1.0, 1.0, 1.0])]).to(device)
    assert float(symmetry_loss(verts, (torch.tensor([1.0, 0.0, 0.0]), 0.0))) < 1e-10
    shifted = verts + torch.tensor([0.7, 0.0, 0.0], device=device)
    assert float(symmetry_loss(shifted, ([3.0, 0.0, 0.0], 0.7))) < 1e-10  # normal need not be unit
    assert float(symmetry_loss(shifted, ([1.0, 0.0, 0.0], 0.0))) > 0.1


def test_symmetry_coincident_vertices(device):
    gen = torch.Generator().manual_seed(8)
    verts = torch.randn(10, 3, generator=gen)
    verts = torch.cat([verts, verts[:3]]).to(device)  # exact duplicates: ties in the arg-min
    out, (gv,) = _grads(lambda v: symmetry_loss(v, ([0.0, 0.0, 1.0], 0.1)), [verts])
    ref = symmetry_loss_reference(verts.double(), ([0.0, 0.0, 1.0], 0.1))
    torch.testing.assert_close(out.double(), ref, atol=1e-6, rtol=1e-5)
    assert torch.isfinite(gv).all()


def test_symmetry_reference_gradcheck():
    verts = torch.randn(6, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda v: symmetry_loss_reference(v, ([1.0, 0.0, 0.0], 0.0)), (verts,))


@pytest.mark.parametrize(
    "plane, match",
    [
        (([0.0, 0.0, 0.0], 0.0), "finite and nonzero"),
        (([1.0, 0.0], 0.0), r"normal of shape \(3,\)"),
        ((1.0,), "must be a pair"),
        (([1.0, 0.0, 0.0], [0.0, 1.0]), "scalar offset"),
    ],
)
def test_symmetry_errors(plane, match):
    with pytest.raises(ValueError, match=match):
        symmetry_loss(torch.zeros(4, 3), plane)
