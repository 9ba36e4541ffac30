"""Laplacian-preconditioned vertex steps: the in-place trick equals Adam on u = (I + lambda L) X."""

from __future__ import annotations

import pytest
import torch
import trimesh
from s3o_warp.kernels.regularisers import mesh_edges

from s3o_warp.large_steps import Adam, LargeSteps, graph_laplacian, preconditioned_step


def _sphere():
    m = trimesh.creation.icosphere(2)
    return torch.tensor(m.vertices, dtype=torch.float64), torch.tensor(m.faces, dtype=torch.int64)


def test_graph_laplacian_is_degree_minus_adjacency():
    v, f = _sphere()
    edges = mesh_edges(f)
    L = graph_laplacian(edges, len(v))
    mesh = trimesh.Trimesh(v.numpy(), f.numpy(), process=False)
    deg = torch.tensor([len(n) for n in mesh.vertex_neighbors], dtype=torch.float64)
    assert torch.equal(L.diagonal(), deg)
    assert torch.allclose(L.sum(1), torch.zeros(len(v), dtype=torch.float64))
    assert torch.equal(L, L.T)
    a, b = edges[0]
    assert L[a, b] == -1 and L[a, a + 0] > 0


def test_solve_inverts_i_plus_lambda_l():
    v, f = _sphere()
    pre = LargeSteps(mesh_edges(f), len(v), 5.0)
    M = torch.eye(len(v), dtype=torch.float64) + 5.0 * graph_laplacian(mesh_edges(f), len(v))
    g = torch.randn(len(v), 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    assert torch.allclose(M @ pre.solve(g), g, atol=1e-10)


def _energy(X: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    # non-quadratic so Adam's normalisation matters
    return ((X - target) ** 2).sum() + 0.1 * ((X - target) ** 4).sum()


@pytest.mark.parametrize("uniform", [False, True])
@pytest.mark.parametrize("lam", [0.5, 10.0])
def test_preconditioned_adam_equals_adam_on_u(lam, uniform):
    v, f = _sphere()
    edges = mesh_edges(f)
    target = v * 1.3 + 0.2 * torch.randn(v.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    pre = LargeSteps(edges, len(v), lam)
    M = torch.eye(len(v), dtype=torch.float64) + lam * graph_laplacian(edges, len(v))

    X = torch.nn.Parameter(v.clone())
    opt = Adam([{"params": [X], "uniform": uniform}], lr=0.05)
    u = torch.nn.Parameter(M @ v)
    opt_u = Adam([{"params": [u], "uniform": uniform}], lr=0.05)
    for _ in range(15):
        opt.zero_grad()
        _energy(X, target).backward()
        preconditioned_step(X, pre, opt.step)
        opt_u.zero_grad()
        _energy(torch.linalg.solve(M, u), target).backward()
        opt_u.step()
    assert torch.allclose(X.detach(), torch.linalg.solve(M, u.detach()), atol=1e-9)
    assert not torch.allclose(X.detach(), v)  # it moved


def test_a_point_force_moves_a_smooth_neighbourhood():
    v, f = _sphere()
    pre = LargeSteps(mesh_edges(f), len(v), 0.5)
    X = torch.nn.Parameter(v.clone())
    opt = Adam([{"params": [X], "uniform": True}], lr=0.01)
    X.grad = torch.zeros_like(v)
    X.grad[0] = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)  # pull one vertex
    preconditioned_step(X, pre, opt.step)
    moved = (X.detach() - v).norm(dim=1)
    # plain Adam moves exactly one vertex; the preconditioned step moves its neighbourhood, most at 0
    assert int(moved.argmax()) == 0
    assert (moved > 0.1 * moved[0]).sum() > 10
    assert (moved < 0.01 * moved[0]).sum() > len(v) // 4  # and leaves the far side alone


def test_adam_groups_without_uniform_are_torch_adam_and_uniform_uses_one_scale():
    g = torch.Generator().manual_seed(3)
    a0, b0 = torch.randn(5, 3, generator=g), torch.randn(7, generator=g)
    grads = [(torch.randn(5, 3, generator=g), torch.randn(7, generator=g)) for _ in range(4)]
    a, b = torch.nn.Parameter(a0.clone()), torch.nn.Parameter(b0.clone())
    ref_b = torch.nn.Parameter(b0.clone())
    opt = Adam([{"params": [a], "uniform": True, "lr": 0.1}, {"params": [b], "lr": 0.03}])
    ref = torch.optim.Adam([ref_b], lr=0.03)
    m = torch.zeros(5, 3)
    s = torch.zeros(5, 3)
    x = a0.clone()
    for t, (ga, gb) in enumerate(grads, 1):
        a.grad, b.grad, ref_b.grad = ga.clone(), gb.clone(), gb.clone()
        opt.step()
        ref.step()
        m = 0.9 * m + 0.1 * ga
        s = 0.999 * s + 0.001 * ga * ga
        x = x - 0.1 * (m / (1 - 0.9 ** t)) / ((s.max() / (1 - 0.999 ** t)).sqrt() + 1e-8)
    assert torch.allclose(b, ref_b)
    assert torch.allclose(a, x, atol=1e-6)
    assert set(opt.state[a]) == set(ref.state[ref_b])  # same state layout as torch's


def test_refuses_a_bad_lambda():
    v, f = _sphere()
    with pytest.raises(ValueError, match="lambda"):
        LargeSteps(mesh_edges(f), len(v), 0.0)
