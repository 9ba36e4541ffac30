"""Per-vertex visibility by BVH ray cast against the brute-force float64 twin and analytic cases."""

from __future__ import annotations

import pytest
import torch
import trimesh
from s3o_warp.kernels import visibility as vis_mod
from s3o_warp.kernels.visibility import VisibilityContext, vertex_visibility

from s3o_warp.reference.regularisers import vertex_visibility_reference


def _sphere(subdivisions: int, centre, radius: float = 1.0, seed: int = 0):
    """A randomly rotated icosphere (no ray through the camera hits an edge exactly), float32 verts."""
    m = trimesh.creation.icosphere(subdivisions)
    rot = trimesh.transformations.random_rotation_matrix(rand=torch.rand(3, generator=torch.Generator().manual_seed(seed)).numpy())
    v = torch.tensor(m.vertices @ rot[:3, :3].T, dtype=torch.float32)
    return v * radius + torch.tensor(centre, dtype=torch.float32), torch.tensor(m.faces, dtype=torch.int64)


def _facing(verts: torch.Tensor, centre) -> torch.Tensor:
    """Cosine between the outward sphere normal and the direction to the camera."""
    normal = torch.nn.functional.normalize(verts - torch.tensor(centre, dtype=verts.dtype, device=verts.device), dim=-1)
    return (normal * torch.nn.functional.normalize(-verts, dim=-1)).sum(-1)


def test_sphere_front_visible_back_hidden(device):
    verts, faces = _sphere(3, (0.2, -0.1, 4.0))
    vis = vertex_visibility(verts[None].to(device), faces.to(device))[0].cpu()
    facing = _facing(verts, (0.2, -0.1, 4.0))
    assert vis.dtype == torch.bool
    assert vis[facing > 0.0].all()  # the polygonal silhouette differs from the sphere by ~ one edge angle
    assert not vis[facing < -0.15].any()
    ref = vertex_visibility_reference(verts[None].double(), faces)[0]
    assert torch.equal(vis, ref)


def test_second_object_occludes(device):
    big, fb = _sphere(3, (0.0, 0.0, 6.0), 1.5, seed=1)
    small, fs = _sphere(2, (0.3, 0.2, 3.0), 0.4, seed=2)
    verts = torch.cat([big, small])[None]
    faces = torch.cat([fb, fs + big.shape[0]])
    vis = vertex_visibility(verts.to(device), faces.to(device))[0].cpu()
    alone = vertex_visibility(big[None].to(device), fb.to(device))[0].cpu()
    # rays to big-sphere vertices that pass well inside the small sphere's silhouette are blocked
    d = torch.nn.functional.normalize(big, dim=-1)
    c = torch.tensor([0.3, 0.2, 3.0])
    miss = torch.linalg.vector_norm(c - (d @ c)[:, None] * d, dim=-1)  # ray-to-centre distance
    shadow = alone & (miss < 0.3)
    assert shadow.sum() > 10
    assert not vis[: big.shape[0]][shadow].any()
    assert vis[: big.shape[0]][alone & (miss > 0.5)].all()
    assert torch.equal(vis, vertex_visibility_reference(verts.double(), faces)[0])


def test_behind_camera_and_frames(device):
    """Frames are independent (grouped BVH): a vertex behind the camera (z <= 0) is never visible."""
    front, faces = _sphere(2, (0.0, 0.0, 3.0), seed=3)
    behind = front - torch.tensor([0.0, 0.0, 6.0])  # whole sphere at z = -3
    straddle = front - torch.tensor([0.0, 0.0, 3.0])  # camera inside the sphere
    verts = torch.stack([front, behind, straddle]).to(device)
    vis = vertex_visibility(verts, faces.to(device)).cpu()
    assert vis.shape == (3, front.shape[0])
    assert not vis[1].any()
    assert not vis[2][straddle[:, 2] <= 0].any()
    assert torch.equal(vis, vertex_visibility_reference(verts.cpu().double(), faces))


def test_eps_is_relative(device):
    """A single triangle just in front of a point hides it unless eps skips past it."""
    tri = torch.tensor([[-1.0, -1.0, 0.99], [1.0, -1.0, 0.99], [0.0, 1.0, 0.99]])
    verts = torch.cat([tri, torch.tensor([[0.0, 0.0, 1.0]])])[None].to(device)
    faces = torch.tensor([[0, 1, 2]], device=device)
    assert not vertex_visibility(verts, faces, eps=1e-3)[0, 3]
    assert vertex_visibility(verts, faces, eps=0.02)[0, 3]
    assert vertex_visibility(verts, faces)[0, :3].all()  # a triangle's own vertices see the camera
    for eps in (1e-3, 0.02):
        ref = vertex_visibility_reference(verts.cpu().double(), faces.cpu(), eps=eps)
        assert torch.equal(vertex_visibility(verts, faces, eps=eps).cpu(), ref)


def test_refit_not_rebuild(device):
    verts, faces = _sphere(2, (0.0, 0.0, 4.0), seed=4)
    faces = faces.to(device)
    seq = torch.stack([verts, verts + torch.tensor([0.5, 0.0, 0.0])]).to(device)
    ctx = VisibilityContext(faces)
    first = ctx(seq)
    mesh_id = ctx.mesh.id
    moved = seq.flip(1) * torch.tensor([1.0, 1.0, 1.2], device=device)  # same topology, new positions
    second = ctx(moved)
    assert ctx.mesh.id == mesh_id and ctx.num_builds == 1 and ctx.num_refits == 1
    assert torch.equal(first.cpu(), vertex_visibility_reference(seq.cpu().double(), faces.cpu()))
    assert torch.equal(second.cpu(), vertex_visibility_reference(moved.cpu().double(), faces.cpu()))
    ctx(seq[:1])  # a new frame count needs a new BVH
    assert ctx.num_builds == 2


def test_functional_cache_reuses_context(device):
    verts, faces = _sphere(1, (0.0, 0.0, 4.0), seed=5)
    faces = faces.to(device)
    seq = verts[None].to(device)
    vertex_visibility(seq, faces)
    ctx = next(c for k, c in vis_mod._cache.items() if k[1] == faces.data_ptr())
    vertex_visibility(seq + 0.1, faces)
    assert ctx.num_builds == 1 and ctx.num_refits == 1
    faces[0] = faces[0].flip(0)  # same storage, new content: must not reuse the stale topology
    vertex_visibility(seq, faces)
    ctx2 = next(c for k, c in vis_mod._cache.items() if k[1] == faces.data_ptr())
    assert ctx2 is not ctx and torch.equal(ctx2.faces, faces.to(torch.int32))


def test_reference_brute_force_single_triangle():
    """The twin itself: a point straight behind a triangle is hidden, one beside it is visible."""
    verts = torch.tensor([[[-1.0, -1.0, 2.0], [1.0, -1.0, 2.0], [0.0, 1.0, 2.0], [0.0, 0.0, 4.0], [4.0, 0.0, 4.0]]])
    vis = vertex_visibility_reference(verts.double(), torch.tensor([[0, 1, 2]]))
    assert vis.tolist() == [[True, True, True, False, True]]


def test_visibility_errors():
    faces = torch.tensor([[0, 1, 2]])
    with pytest.raises(ValueError, match=r"verts must have shape \(\*, \*, 3\)"):
        vertex_visibility(torch.zeros(3, 3), faces)
    with pytest.raises(TypeError, match="verts must be float32"):
        vertex_visibility(torch.zeros(1, 3, 3, dtype=torch.float64), faces)
    with pytest.raises(ValueError, match="faces index vertex 2 but verts has only 2"):
        vertex_visibility(torch.zeros(1, 2, 3), faces)
    with pytest.raises(ValueError, match=r"eps must lie in \[0, 1\)"):
        vertex_visibility(torch.zeros(1, 3, 3), faces, eps=1.5)
    with pytest.raises(ValueError, match=r"faces must have shape \(\*, 3\)"):
        VisibilityContext(torch.zeros(2, 2, dtype=torch.long))
    with pytest.raises(TypeError, match="integer"):
        VisibilityContext(torch.zeros(2, 3))
