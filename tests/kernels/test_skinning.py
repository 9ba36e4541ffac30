"""Gaussian skinning weights and linear blend skinning: values and gradients against the dense twins."""

from __future__ import annotations

import pytest
import torch
from s3o_warp.kernels import skinning as skin_mod
from s3o_warp.kernels.skinning import blend_skinning, skinning_weights

from s3o_warp.reference.skinning import (
    blend_skinning_reference,
    skinning_weights_reference,
)


def _rotation(n: int, gen: torch.Generator) -> torch.Tensor:
    """(n, 3, 3) random rotations (QR of Gaussian matrices, det fixed to +1)."""
    q, r = torch.linalg.qr(torch.randn(n, 3, 3, generator=gen, dtype=torch.float64))
    q = q * torch.sign(torch.diagonal(r, dim1=-2, dim2=-1))[:, None, :]
    q[torch.linalg.det(q) < 0, :, 0] *= -1
    return q.float()


def _bones(num_bones: int, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Centres (B, 3) and SPD-ish (but not symmetric) precisions (B, 3, 3)."""
    centers = torch.randn(num_bones, 3, generator=gen)
    rot = _rotation(num_bones, gen)
    scales = torch.exp(torch.randn(num_bones, 3, generator=gen) * 0.3)
    q = rot.transpose(1, 2) @ torch.diag_embed(scales) @ rot
    q = q + 0.05 * torch.randn(num_bones, 3, 3, generator=gen)  # the op must not assume symmetry
    return centers, q


def _grads(fn, inputs, upstream):
    """Gradients of sum(fn(*inputs) * upstream) w.r.t. every input."""
    leaves = [x.detach().clone().requires_grad_(True) for x in inputs]
    out = fn(*leaves)
    (out * upstream.to(out.dtype)).sum().backward()
    return out.detach(), [x.grad for x in leaves]


# -------------------------------------------------------------------------------------------------
# skinning_weights
# -------------------------------------------------------------------------------------------------


def test_skinning_weights_values_and_grads(device):
    gen = torch.Generator().manual_seed(1)
    verts = torch.randn(97, 3, generator=gen)
    centers, prec = _bones(6, gen)
    upstream = torch.randn(97, 6, generator=gen)
    inputs = [x.to(device) for x in (verts, centers, prec)]
    out, grads = _grads(skinning_weights, inputs, upstream.to(device))
    ref, ref_grads = _grads(skinning_weights_reference, [x.double() for x in inputs], upstream.to(device))
    assert out.dtype == torch.float32 and out.shape == (97, 6) and out.device.type == torch.device(device).type
    torch.testing.assert_close(out.double(), ref, atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(out.sum(1), torch.ones(97, device=device), atol=1e-5, rtol=0)
    for g, r, name in zip(grads, ref_grads, ("verts", "centers", "precisions")):
        torch.testing.assert_close(g.double(), r, atol=1e-5, rtol=1e-4, msg=lambda m, n=name: f"d{n}: {m}")


def test_skinning_weights_chunked_reduction_matches(monkeypatch):
    """The CUDA path's chunked per-bone partial sums (exercised here on the CPU) give the same gradients."""
    gen = torch.Generator().manual_seed(2)
    verts = torch.randn(50, 3, generator=gen)
    centers, prec = _bones(4, gen)
    upstream = torch.randn(50, 4, generator=gen)
    _, one = _grads(skinning_weights, [verts, centers, prec], upstream)
    monkeypatch.setattr(skin_mod, "_chunking", lambda n, device: (7, (n + 6) // 7))
    _, many = _grads(skinning_weights, [verts, centers, prec], upstream)
    for a, b in zip(one, many):
        torch.testing.assert_close(a, b, atol=1e-6, rtol=1e-5)


def test_skinning_weights_far_bone_no_nan(device):
    gen = torch.Generator().manual_seed(3)
    verts = torch.randn(40, 3, generator=gen)
    centers, prec = _bones(3, gen)
    centers[2] = torch.tensor([1.0e3, -2.0e3, 5.0e2])  # no vertex anywhere near bone 2
    prec[2] = torch.eye(3) * 50.0
    inputs = [x.to(device) for x in (verts, centers, prec)]
    out, grads = _grads(skinning_weights, inputs, torch.randn(40, 3, generator=gen).to(device))
    assert torch.isfinite(out).all() and all(torch.isfinite(g).all() for g in grads)
    assert out[:, 2].max() < 1e-30
    torch.testing.assert_close(out.sum(1), torch.ones(40, device=device), atol=1e-5, rtol=0)
    assert grads[1][2].abs().max() == 0 and grads[2][2].abs().max() == 0


def test_skinning_weights_reference_gradcheck():
    gen = torch.Generator().manual_seed(4)
    verts = torch.randn(5, 3, generator=gen, dtype=torch.float64, requires_grad=True)
    centers = torch.randn(3, 3, generator=gen, dtype=torch.float64, requires_grad=True)
    prec = (torch.eye(3, dtype=torch.float64) + 0.2 * torch.randn(3, 3, 3, generator=gen, dtype=torch.float64))
    assert torch.autograd.gradcheck(skinning_weights_reference, (verts, centers, prec.requires_grad_()))


@pytest.mark.parametrize(
    "shapes, exc, match",
    [
        (((5, 2), (3, 3), (3, 3, 3)), ValueError, r"verts must have shape \(\*, 3\)"),
        (((5, 3), (3, 3), (2, 3, 3)), ValueError, r"precisions must have shape \(3, 3, 3\)"),
        (((5, 3), (0, 3), (0, 3, 3)), ValueError, "at least one bone"),
    ],
)
def test_skinning_weights_errors(shapes, exc, match):
    args = [torch.zeros(s) for s in shapes]
    with pytest.raises(exc, match=match):
        skinning_weights(*args)


def test_skinning_weights_dtype_error():
    with pytest.raises(TypeError, match="centers must be float32"):
        skinning_weights(torch.zeros(4, 3), torch.zeros(2, 3, dtype=torch.float64), torch.zeros(2, 3, 3))


# -------------------------------------------------------------------------------------------------
# blend_skinning
# -------------------------------------------------------------------------------------------------


def _rt(frames: int, bones: int | None, gen: torch.Generator) -> torch.Tensor:
    """Random rigid [R | t] of shape (T, B, 3, 4) or (T, 3, 4)."""
    count = frames * (bones or 1)
    rt = torch.cat([_rotation(count, gen), torch.randn(count, 3, 1, generator=gen)], dim=2)
    return rt.reshape(frames, bones, 3, 4) if bones else rt


def test_blend_skinning_values_and_grads(device):
    gen = torch.Generator().manual_seed(5)
    n, b, t = 83, 7, 3
    verts = torch.randn(n, 3, generator=gen)
    weights = torch.softmax(2 * torch.randn(n, b, generator=gen), 1)
    inputs = [x.to(device) for x in (verts, weights, _rt(t, b, gen), _rt(t, None, gen))]
    upstream = torch.randn(t, n, 3, generator=gen).to(device)
    out, grads = _grads(blend_skinning, inputs, upstream)
    ref, ref_grads = _grads(blend_skinning_reference, [x.double() for x in inputs], upstream)
    assert out.shape == (t, n, 3) and out.dtype == torch.float32
    torch.testing.assert_close(out.double(), ref, atol=2e-5, rtol=1e-5)
    for g, r, name in zip(grads, ref_grads, ("verts", "weights", "bone_rt", "root_rt")):
        torch.testing.assert_close(g.double(), r, atol=5e-5, rtol=1e-4, msg=lambda m, n=name: f"d{n}: {m}")


def test_blend_skinning_chunked_reduction_matches(monkeypatch):
    gen = torch.Generator().manual_seed(6)
    n, b, t = 45, 4, 2
    inputs = [torch.randn(n, 3, generator=gen), torch.rand(n, b, generator=gen), _rt(t, b, gen), _rt(t, None, gen)]
    upstream = torch.randn(t, n, 3, generator=gen)
    _, one = _grads(blend_skinning, inputs, upstream)
    monkeypatch.setattr(skin_mod, "_chunking", lambda n, device: (8, (n + 7) // 8))
    _, many = _grads(blend_skinning, inputs, upstream)
    for a, c in zip(one, many):
        torch.testing.assert_close(a, c, atol=1e-5, rtol=1e-5)


def test_blend_skinning_identity_and_rigid(device):
    """Identity bones leave the mesh to the root; one bone with all weight moves the mesh rigidly."""
    gen = torch.Generator().manual_seed(7)
    verts = torch.randn(20, 3, generator=gen).to(device)
    weights = torch.softmax(torch.randn(20, 3, generator=gen), 1).to(device)
    eye = torch.eye(3, 4).expand(2, 3, 3, 4).contiguous().to(device)
    root = _rt(2, None, gen).to(device)
    out = blend_skinning(verts, weights, eye, root)
    expect = torch.einsum("tij,nj->tni", root[:, :, :3], verts) + root[:, None, :, 3]
    torch.testing.assert_close(out, expect, atol=1e-5, rtol=1e-5)
    one_hot = torch.zeros(20, 3, device=device)
    one_hot[:, 1] = 1.0
    bones = _rt(2, 3, gen).to(device)
    out = blend_skinning(verts, one_hot, bones, torch.eye(3, 4).expand(2, 3, 4).contiguous().to(device))
    expect = torch.einsum("tij,nj->tni", bones[:, 1, :, :3], verts) + bones[:, 1, None, :, 3]
    torch.testing.assert_close(out, expect, atol=1e-5, rtol=1e-5)


def test_blend_skinning_bone_without_vertices_no_nan(device):
    gen = torch.Generator().manual_seed(8)
    weights = torch.softmax(torch.randn(10, 3, generator=gen), 1)
    weights[:, 2] = 0.0
    inputs = [x.to(device) for x in (torch.randn(10, 3, generator=gen), weights, _rt(2, 3, gen), _rt(2, None, gen))]
    _, grads = _grads(blend_skinning, inputs, torch.randn(2, 10, 3, generator=gen).to(device))
    assert all(torch.isfinite(g).all() for g in grads)
    assert grads[2][:, 2].abs().max() == 0  # an unused bone gets no gradient


def test_blend_skinning_reference_gradcheck():
    gen = torch.Generator().manual_seed(9)
    args = (
        torch.randn(4, 3, generator=gen, dtype=torch.float64),
        torch.rand(4, 2, generator=gen, dtype=torch.float64),
        torch.randn(2, 2, 3, 4, generator=gen, dtype=torch.float64),
        torch.randn(2, 3, 4, generator=gen, dtype=torch.float64),
    )
    assert torch.autograd.gradcheck(blend_skinning_reference, tuple(a.requires_grad_() for a in args))


@pytest.mark.parametrize(
    "shapes, match",
    [
        (((5, 3), (4, 2), (1, 2, 3, 4), (1, 3, 4)), r"weights must have shape \(5, \*\)"),
        (((5, 3), (5, 2), (1, 3, 3, 4), (1, 3, 4)), r"bone_rt must have shape \(\*, 2, 3, 4\)"),
        (((5, 3), (5, 2), (2, 2, 3, 4), (1, 3, 4)), r"root_rt must have shape \(2, 3, 4\)"),
        (((5, 3), (5, 2), (2, 2, 4, 4), (2, 3, 4)), r"bone_rt must have shape"),
    ],
)
def test_blend_skinning_shape_errors(shapes, match):
    with pytest.raises(ValueError, match=match):
        blend_skinning(*[torch.zeros(s) for s in shapes])


def test_blend_skinning_dtype_error():
    with pytest.raises(TypeError, match="verts must be float32"):
        blend_skinning(torch.zeros(5, 3, dtype=torch.float64), torch.zeros(5, 2), torch.zeros(1, 2, 3, 4), torch.zeros(1, 3, 4))


def test_inputs_modified_in_place_before_backward_raise():
    """The ops save their inputs for backward, so torch's version check catches in-place edits."""
    gen = torch.Generator().manual_seed(10)
    leaf = torch.randn(6, 3, generator=gen, requires_grad=True)
    verts = leaf * 1.0
    out = blend_skinning(verts, torch.rand(6, 2, generator=gen), _rt(1, 2, gen), _rt(1, None, gen))
    verts.add_(1.0)
    with pytest.raises(RuntimeError, match="modified by an inplace operation"):
        out.sum().backward()
    centers = torch.randn(2, 3, generator=gen, requires_grad=True) * 1.0
    w = skinning_weights(leaf.detach(), centers, torch.eye(3).expand(2, 3, 3).contiguous())
    centers.mul_(2.0)
    with pytest.raises(RuntimeError, match="modified by an inplace operation"):
        w.sum().backward()
