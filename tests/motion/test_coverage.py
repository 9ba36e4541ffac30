"""Nearest-point search (Warp) against its dense twin, and the mask-coverage loss built on it."""

from __future__ import annotations

import pytest
import torch
from s3o_warp.kernels.nearest import nearest_point

from s3o_warp.motion.losses import coverage_loss
from s3o_warp.reference.nearest import nearest_point_reference


def test_nearest_point_matches_reference(device):
    g = torch.Generator().manual_seed(1)
    points = (torch.rand(3, 200, 2, generator=g) * 64).to(device)
    queries = (torch.rand(500, 2, generator=g) * 64).to(device)
    frame = torch.randint(0, 3, (500,), generator=g).to(device)
    got = nearest_point(queries, frame, points)
    assert got.dtype == torch.int64 and got.device == queries.device
    assert torch.equal(got.cpu(), nearest_point_reference(queries.cpu().double(), frame.cpu(), points.cpu().double()))


def test_nearest_point_uses_the_query_frame_and_first_tie(device):
    points = torch.tensor([[[0.0, 0.0], [10.0, 0.0], [10.0, 0.0]], [[10.0, 0.0], [0.0, 0.0], [5.0, 5.0]]], device=device)
    queries = torch.tensor([[9.0, 0.0], [9.0, 0.0], [1.0, 0.0]], device=device)
    frame = torch.tensor([0, 1, 1], device=device)
    assert nearest_point(queries, frame, points).tolist() == [1, 0, 1]  # [1] over its twin [2]; frame 1's order


def test_nearest_point_rejects_bad_input():
    points = torch.zeros(2, 4, 2)
    q = torch.zeros(3, 2)
    with pytest.raises(ValueError, match="query_frame must lie in"):
        nearest_point(q, torch.tensor([0, 1, 2]), points)
    with pytest.raises(TypeError, match="query_frame must be an integer"):
        nearest_point(q, torch.zeros(3), points)
    with pytest.raises(TypeError, match="float32"):
        nearest_point(q.double(), torch.zeros(3, dtype=torch.long), points)
    with pytest.raises(ValueError, match="no candidates"):
        nearest_point(q, torch.zeros(3, dtype=torch.long), torch.zeros(2, 0, 2))
    assert nearest_point(torch.zeros(0, 2), torch.zeros(0, dtype=torch.long), points).shape == (0,)


def _coverage_reference(proj: torch.Tensor, uncovered: torch.Tensor) -> torch.Tensor:
    """Dense twin: every uncovered pixel's distance to the nearest projected point, summed, over t S^2."""
    t, S = uncovered.shape[0], uncovered.shape[-1]
    r, c = torch.meshgrid(torch.arange(S, dtype=proj.dtype), torch.arange(S, dtype=proj.dtype), indexing="ij")
    pix = torch.stack([c, r], -1).reshape(-1, 2)  # (S*S, 2) as (column, row)
    total = proj.sum() * 0
    for f in range(t):
        d = torch.cdist(pix, proj[f]).min(1).values  # (S*S,)
        total = total + (d * uncovered[f].reshape(-1)).sum()
    return total / (t * S * S)


def test_coverage_loss_value_and_gradient_match_dense_twin():
    g = torch.Generator().manual_seed(3)
    S = 12
    proj = (torch.rand(2, 15, 2, generator=g, dtype=torch.float64) * S).requires_grad_(True)
    uncovered = torch.rand(2, S, S, generator=g) > 0.6
    got = coverage_loss(proj, uncovered)
    ref = _coverage_reference(proj, uncovered)
    assert torch.allclose(got, ref, rtol=1e-10, atol=1e-12)
    (g1,) = torch.autograd.grad(got, proj)
    (g2,) = torch.autograd.grad(_coverage_reference(proj, uncovered), proj)
    assert torch.allclose(g1, g2, atol=1e-12)
    assert torch.autograd.gradcheck(lambda p: coverage_loss(p, uncovered), (proj.detach().requires_grad_(True),))


def test_coverage_loss_pulls_the_nearest_point_towards_an_uncovered_patch():
    S = 16
    uncovered = torch.zeros(1, S, S, dtype=torch.bool)
    uncovered[0, 10:13, 12:15] = True  # a patch at columns 12-14, rows 10-12
    proj = torch.tensor([[[2.0, 2.0], [6.0, 8.0]]], requires_grad=True)  # point 1 is the nearer
    loss = coverage_loss(proj, uncovered)
    assert loss > 0
    (grad,) = torch.autograd.grad(loss, proj)
    assert torch.equal(grad[0, 0], torch.zeros(2))  # the far point is not pulled
    assert grad[0, 1, 0] < 0 and grad[0, 1, 1] < 0  # descent moves point 1 right and down, to the patch
    assert coverage_loss(proj, torch.zeros_like(uncovered)) == 0


def test_coverage_loss_sampling_is_exact_when_it_keeps_every_pixel_and_unbiased_otherwise():
    g = torch.Generator().manual_seed(5)
    S = 20
    proj = torch.rand(2, 30, 2, generator=g) * S
    uncovered = torch.rand(2, S, S, generator=g) > 0.5
    full = coverage_loss(proj, uncovered)
    assert torch.allclose(coverage_loss(proj, uncovered, max_pixels=S * S), full)
    samples = torch.stack([coverage_loss(proj, uncovered, max_pixels=20, generator=g) for _ in range(400)])
    assert samples.std() > 0  # it does sample
    assert abs(float(samples.mean() / full) - 1) < 0.03
