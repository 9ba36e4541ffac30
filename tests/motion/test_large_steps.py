"""The joint phase's shape step (``s3o_warp.motion.large_steps``) against a dense torch twin."""

from __future__ import annotations

import pytest
import torch
import trimesh

from s3o_warp.evaluation.views import mesh_smoothness
from s3o_warp.motion.large_steps import FitAdam, smoothing_solve, umbrella_laplacian


def _sphere():
    m = trimesh.creation.icosphere(subdivisions=2)
    return (torch.tensor(m.vertices, dtype=torch.float32).contiguous(),
            torch.tensor(m.faces, dtype=torch.int64).contiguous())


def _dense_laplacian(faces: torch.Tensor, n: int) -> torch.Tensor:
    A = torch.zeros(n, n, dtype=torch.float64)
    for a, b in ((0, 1), (1, 2), (2, 0)):
        A[faces[:, a], faces[:, b]] = 1.0
        A[faces[:, b], faces[:, a]] = 1.0
    return torch.diag(A.sum(1)) - A


def test_laplacian_and_solve_match_the_dense_twin():
    v, f = _sphere()
    n = v.shape[0]
    L = _dense_laplacian(f, n)
    assert torch.allclose(torch.tensor(umbrella_laplacian(f, n).toarray()), L)
    b = torch.randn(n, 3, generator=torch.Generator().manual_seed(0))
    got = smoothing_solve(f, n, 7.0)(b)
    want = torch.linalg.solve(torch.eye(n, dtype=torch.float64) + 7.0 * L, b.double())
    assert got.dtype == torch.float32 and torch.allclose(got.double(), want, atol=1e-5)


def test_shape_step_matches_the_dense_twin_and_other_groups_step_as_adam():
    v, f = _sphere()
    n, lam, lr, steps = v.shape[0], 4.0, 0.01, 3
    other0 = torch.randn(5, 2, generator=torch.Generator().manual_seed(1))
    x = torch.nn.Parameter(v.clone())
    other = torch.nn.Parameter(other0.clone())
    opt = FitAdam([{"params": [x], "lr": lr, "name": "shape"}, {"params": [other], "lr": 0.1, "name": "motion"}], f, lam)
    ref_other = torch.nn.Parameter(other0.clone())
    ref_opt = torch.optim.Adam([{"params": [ref_other], "lr": 0.1}])
    Minv = torch.linalg.inv(torch.eye(n, dtype=torch.float64) + lam * _dense_laplacian(f, n))
    xr = v.double().clone()
    m1 = torch.zeros(n, 3, dtype=torch.float64)
    m2 = torch.zeros(n, 3, dtype=torch.float64)
    g = torch.Generator().manual_seed(2)
    for t in range(1, steps + 1):
        gx = torch.randn(n, 3, generator=g)
        go = torch.randn(5, 2, generator=g)
        x.grad, other.grad, ref_other.grad = gx.clone(), go.clone(), go.clone()
        opt.step()
        ref_opt.step()
        gu = Minv @ gx.double()
        m1 = 0.9 * m1 + 0.1 * gu
        m2 = 0.999 * m2 + 0.001 * gu * gu
        step_u = -lr * (m1 / (1 - 0.9**t)) / ((m2 / (1 - 0.999**t)).max().sqrt() + 1e-8)
        xr = xr + Minv @ step_u
        assert torch.allclose(x.detach().double(), xr, atol=1e-5), t
        assert torch.equal(other.detach(), ref_other.detach())
        assert torch.equal(x.grad, gx)  # the gradient is left as it was


def test_shape_step_moves_a_small_gradient_little_and_keeps_the_surface_smooth():
    """Per-vertex Adam moves every vertex by about the learning rate; the shape step scales by the largest second
    moment and smooths the step, so a noisy gradient leaves the sphere far smoother."""
    v, f = _sphere()
    g = torch.Generator().manual_seed(3)
    grads = [torch.randn(v.shape[0], 3, generator=g) for _ in range(50)]
    out = {}
    for name in ("adam", "large_steps"):
        x = torch.nn.Parameter(v.clone())
        groups = [{"params": [x], "lr": 0.01, "name": "shape"}]
        opt = torch.optim.Adam(groups) if name == "adam" else FitAdam(groups, f, 10.0)
        for gx in grads:
            x.grad = gx.clone()
            opt.step()
        out[name] = mesh_smoothness(x.detach().numpy(), f.numpy())
    assert out["large_steps"]["normal_consistency"] > out["adam"]["normal_consistency"] + 0.05
    assert out["large_steps"]["roughness"] < out["adam"]["roughness"]


def test_shape_step_refuses_bad_settings():
    v, f = _sphere()
    with pytest.raises(ValueError, match="lam must be > 0"):
        FitAdam([{"params": [torch.nn.Parameter(v)], "lr": 0.01, "name": "shape"}], f, 0.0)
