"""Rasteriser ops (soft silhouette, z-buffer, interpolation) against their dense float64 twins."""

from __future__ import annotations

import math

import pytest
import torch
import trimesh
from s3o_warp.kernels.raster import (
    interpolate,
    rasterize,
    soft_silhouette,
    soft_silhouette_naive,
)

from s3o_warp.reference.raster import (
    interpolate_reference,
    rasterize_reference,
    soft_silhouette_reference,
)


def _K(f=20.0, cx=11.0, cy=9.0, dtype=torch.float32):
    return torch.tensor([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]], dtype=dtype)


def _soup(T=2, F=8, seed=0):
    """Random triangle soup in front of the camera, per-frame intrinsics, odd image size."""
    g = torch.Generator().manual_seed(seed)
    centres = torch.rand(T, F, 1, 3, generator=g) * torch.tensor([1.4, 1.2, 1.5]) - torch.tensor([0.7, 0.6, -2.5])
    verts = (centres + 0.35 * torch.randn(T, F, 3, 3, generator=g)).reshape(T, 3 * F, 3)
    faces = torch.arange(3 * F).reshape(F, 3)
    K = torch.stack([_K(18.0 + 2 * t, 11.0 + 0.5 * t, 9.0 - 0.25 * t) for t in range(T)])
    return verts, faces, K, (19, 23)


def _sphere(subdivisions=1, radius=0.8, z=3.0):
    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    v = torch.tensor(m.vertices, dtype=torch.float32) * radius + torch.tensor([0.05, -0.03, z])
    return v[None], torch.tensor(m.faces, dtype=torch.int64)


def _grads(fn, inputs, upstream):
    """Gradients of sum(fn(*inputs) * upstream) w.r.t. the inputs (fresh leaves)."""
    leaves = [x.detach().clone().requires_grad_() for x in inputs]
    out = fn(*leaves)
    (out * upstream.to(out.dtype)).sum().backward()
    return out.detach(), [leaf.grad for leaf in leaves]


def _assert_rel(actual, expected, rtol):
    """Max abs error relative to the largest magnitude of the expected tensor."""
    scale = expected.abs().max().item()
    err = (actual.double().cpu() - expected.double().cpu()).abs().max().item()
    assert err <= rtol * max(scale, 1e-12), f"max error {err:.3g} vs scale {scale:.3g} (rtol {rtol})"


# ---------------------------------------------------------------------------------------------
# soft silhouette


def test_soft_silhouette_matches_reference(device):
    verts, faces, K, size = _soup()
    up = torch.randn(verts.shape[0], *size)
    A, (gv, gK) = _grads(lambda v, k: soft_silhouette(v, faces.to(device), k, size, sigma=2.0, tile_size=8),
                         [verts.to(device), K.to(device)], up.to(device))
    Ar, (gvr, gKr) = _grads(lambda v, k: soft_silhouette_reference(v, faces, k, size, sigma=2.0),
                            [verts.double(), K.double()], up)
    assert A.shape == (2, 19, 23) and A.dtype == torch.float32 and A.device.type == torch.device(device).type
    torch.testing.assert_close(A.cpu().double(), Ar, atol=2e-6, rtol=0)
    assert 0.05 < Ar.mean() < 0.95  # the scene is neither empty nor full
    _assert_rel(gv, gvr, 1e-5)
    _assert_rel(gK, gKr, 1e-5)


@pytest.mark.parametrize("tile_size", [1, 5, 8, 16, 64])
def test_soft_silhouette_tile_size_is_output_neutral(device, tile_size):
    verts, faces, K, size = _soup(F=12, seed=1)
    verts, faces, K = verts.to(device), faces.to(device), K.to(device)
    up = torch.randn(verts.shape[0], *size, device=device)
    An, (gn,) = _grads(lambda v: soft_silhouette_naive(v, faces, K, size, sigma=1.5), [verts], up)
    At, (gt,) = _grads(lambda v: soft_silhouette(v, faces, K, size, sigma=1.5, tile_size=tile_size), [verts], up)
    torch.testing.assert_close(At, An, atol=1e-7, rtol=0)
    _assert_rel(gt, gn, 1e-6)


def test_soft_silhouette_reference_gradcheck():
    verts, faces, K, _ = _soup(T=1, F=2, seed=2)
    # large sigma: every face is inside the blur cutoff for every pixel, so A is smooth
    fn = lambda v, k: soft_silhouette_reference(v, faces, k, (5, 6), sigma=40.0)  # noqa: E731
    K = _K(4.0, 2.5, 2.0, torch.float64)
    assert torch.autograd.gradcheck(fn, (verts.double().requires_grad_(), K.requires_grad_()), eps=1e-6, atol=1e-6)


def test_soft_silhouette_closed_mesh_shared_edges(device):
    """Gradients of a closed mesh cancel on shared edges: float64 accumulation keeps them right."""
    verts, faces = _sphere(subdivisions=2)
    K, size = _K(14.0, 15.5, 14.5), (31, 33)
    up = torch.randn(1, *size)
    A, (gv,) = _grads(lambda v: soft_silhouette(v, faces.to(device), K.to(device), size, sigma=1.0), [verts.to(device)], up.to(device))
    Ar, (gvr,) = _grads(lambda v: soft_silhouette_reference(v, faces, K.double(), size, sigma=1.0), [verts.double()], up)
    torch.testing.assert_close(A.cpu().double(), Ar, atol=2e-6, rtol=0)
    _assert_rel(gv, gvr, 1e-4)


def test_soft_silhouette_fills_image_and_vanishes_far_away(device):
    # a closed mesh larger than the view: coverage ~1 everywhere (back faces cover the front's edges)
    verts, faces = _sphere(subdivisions=2, radius=2.0, z=3.0)
    A = soft_silhouette(verts.to(device), faces.to(device), _K(40.0).to(device), (19, 23), sigma=1.0)
    assert A.mean().item() > 0.98 and A.min().item() > 0.9  # dips only near edges of both layers
    # one open quad larger than the view: ~1, except near its diagonal, where one triangle has
    # D = sigmoid(x) and the other sigmoid(-x): A = 1 - sigmoid(x) sigmoid(-x) (SoftRas' inner-edge dip)
    big = torch.tensor([[[-5.0, -5.0, 2.0], [5.0, -5.0, 2.0], [5.0, 5.0, 2.0], [-5.0, 5.0, 2.0]]])
    quad = torch.tensor([[0, 1, 2], [0, 2, 3]])
    A = soft_silhouette(big.to(device), quad.to(device), _K(10.0, 9.0, 9.0).to(device), (19, 19), sigma=1.0).cpu()
    r, c = torch.meshgrid(torch.arange(19.0), torch.arange(19.0), indexing="ij")
    x = (r - c) ** 2 / 2.0  # squared distance to the diagonal; the outer edges are beyond the blur
    torch.testing.assert_close(A[0], 1.0 - torch.sigmoid(x) * torch.sigmoid(-x), atol=1e-6, rtol=0)
    assert A[0, 9, 9].item() == pytest.approx(0.75) and A[0, 0, 18].item() > 0.9999
    # a small triangle in one corner: exactly 0 beyond the blur radius, ~1 deep inside
    K = _K(10.0, 0.0, 0.0)
    tri = torch.tensor([[[0.0, 0.0, 1.0], [1.2, 0.0, 1.0], [0.0, 1.2, 1.0]]])  # pixels (0,0),(12,0),(0,12)
    A = soft_silhouette(tri.to(device), quad[:1].to(device), K.to(device), (40, 48), sigma=1.0, tile_size=8).cpu()
    radius = math.sqrt(math.log(1e4 - 1))
    assert A[0, 20:, :].abs().max().item() == 0.0 and A[0, :, 20:].abs().max().item() == 0.0  # empty tiles
    assert A[0, 3, 3].item() > 0.99
    assert A[0, 0, 14].item() > 0.0 and A[0, 0, 12 + math.ceil(radius) + 1].item() == 0.0


def test_soft_silhouette_degenerate_and_behind_camera(device):
    verts, faces, K, size = _soup(T=1, F=4, seed=3)
    extra = torch.tensor([[[0.0, 0.0, 3.0], [0.3, 0.2, 3.0], [0.6, 0.4, 3.0],   # collinear (zero area)
                           [0.1, -0.2, 3.0], [0.1, -0.2, 3.0], [0.1, -0.2, 3.0],  # a point
                           [0.2, 0.1, 2.0], [0.2, 0.1, 4.0], [0.2, 0.5, 3.0],   # edge-on
                           [0.3, 0.3, 3.0], [-0.4, 0.2, -1.0], [0.1, 0.6, 0.0]]])  # behind / at the camera
    verts = torch.cat([verts, extra], 1)
    faces = torch.cat([faces, torch.arange(12, 24).reshape(4, 3)])
    up = torch.randn(1, *size)
    A, (gv,) = _grads(lambda v: soft_silhouette(v, faces.to(device), K.to(device), size, sigma=1.0, tile_size=4),
                      [verts.to(device)], up.to(device))
    Ar, (gvr,) = _grads(lambda v: soft_silhouette_reference(v, faces, K.double(), size, sigma=1.0), [verts.double()], up)
    assert torch.isfinite(A).all() and torch.isfinite(gv).all()
    torch.testing.assert_close(A.cpu().double(), Ar, atol=2e-6, rtol=0)
    # a collinear triangle's edges overlap, so how its gradient splits between its vertices is not
    # unique (float32 and float64 may pick different nearest edges); its translation gradient is
    keep = torch.ones(verts.shape[1], dtype=torch.bool)
    keep[12:15] = False
    _assert_rel(gv[:, keep], gvr[:, keep], 1e-5)
    _assert_rel(gv[0, 12:15].sum(0), gvr[0, 12:15].sum(0), 1e-5)
    assert gv[0, 21:].abs().max().item() == 0.0  # the face with vertices behind the camera is ignored
    # without that face the image is unchanged
    A2 = soft_silhouette(verts.to(device), faces[:-1].to(device), K.to(device), size, sigma=1.0)
    torch.testing.assert_close(A, A2, atol=0, rtol=0)


def test_soft_silhouette_pixels_exactly_on_edges(device):
    # vertices on pixel centres: pixels on the edges have d = 0 and coverage 1/2
    K = _K(10.0, 0.0, 0.0)
    tri = torch.tensor([[[0.2, 0.2, 1.0], [1.0, 0.2, 1.0], [0.2, 1.0, 1.0]]])  # pixels (2,2),(10,2),(2,10)
    faces = torch.tensor([[0, 1, 2]], dtype=torch.int32)
    up = torch.randn(1, 13, 12)
    A, (gv,) = _grads(lambda v: soft_silhouette(v, faces.to(device), K.to(device), (13, 12), sigma=0.5), [tri.to(device)], up.to(device))
    Ar, (gvr,) = _grads(lambda v: soft_silhouette_reference(v, faces, K.double(), (13, 12), sigma=0.5), [tri.double()], up)
    assert abs(A[0, 2, 6].item() - 0.5) < 1e-6 and abs(A[0, 6, 2].item() - 0.5) < 1e-6
    torch.testing.assert_close(A.cpu().double(), Ar, atol=2e-6, rtol=0)
    _assert_rel(gv, gvr, 1e-5)


# ---------------------------------------------------------------------------------------------
# rasterize and interpolate


def test_rasterize_matches_reference(device):
    verts, faces, K, size = _soup(F=10, seed=4)
    fi, bary, depth = rasterize(verts.to(device), faces.to(device), K.to(device), size, tile_size=8)
    fr, br, dr = rasterize_reference(verts.double(), faces, K.double(), size)
    assert fi.dtype == torch.int32 and bary.shape == (2, 19, 23, 3) and depth.shape == (2, 19, 23)
    assert (fi.cpu() == fr).all() and (fr >= 0).sum() > 50 and (fr == -1).sum() > 50
    torch.testing.assert_close(bary.cpu().double(), br, atol=1e-5, rtol=0)
    torch.testing.assert_close(depth.cpu().double(), dr, atol=1e-5, rtol=1e-6)
    # gradients of bary and depth w.r.t. verts and K (visibility fixed)
    ub, ud = torch.randn(2, 19, 23, 3), torch.randn(2, 19, 23)
    _, (gv, gK) = _grads(lambda v, k: _bd(rasterize(v, faces.to(device), k, size), ub.to(device), ud.to(device)),
                         [verts.to(device), K.to(device)], torch.ones(()).to(device))
    _, (gvr, gKr) = _grads(lambda v, k: _bd(rasterize_reference(v, faces, k, size), ub.double(), ud.double()),
                           [verts.double(), K.double()], torch.ones(()))
    _assert_rel(gv, gvr, 1e-4)
    _assert_rel(gK, gKr, 1e-4)


@pytest.mark.parametrize("which", ["bary", "depth"])
def test_rasterize_gradient_of_one_output(device, which):
    """Only bary or only depth reaches the loss: the other's missing upstream gradient counts as zero."""
    verts, faces, K, size = _soup(F=10, seed=7)
    i = 1 if which == "bary" else 2
    up = torch.randn(2, 19, 23, 3) if which == "bary" else torch.randn(2, 19, 23)
    _, (gv,) = _grads(lambda v: rasterize(v, faces.to(device), K.to(device), size)[i], [verts.to(device)], up.to(device))
    _, (gvr,) = _grads(lambda v: rasterize_reference(v, faces, K.double(), size)[i], [verts.double()], up.double())
    assert gvr.abs().max() > 0
    _assert_rel(gv, gvr, 1e-4)


def test_interpolate_without_attribute_gradient(device):
    """Attributes that need no gradient (constants) still pass the barycentrics' gradient back to the vertices."""
    verts, faces, K, size = _soup(F=10, seed=8)
    attr = torch.randn(verts.shape[1], 2)
    up = torch.randn(2, *size, 2)

    def fn(v, fcs, k, a, ras, interp):
        fi, bary, _ = ras(v, fcs, k, size)
        return interp(a, fcs, fi, bary)

    _, (gv,) = _grads(lambda v: fn(v, faces.to(device), K.to(device), attr.to(device), rasterize, interpolate),
                      [verts.to(device)], up.to(device))
    _, (gvr,) = _grads(lambda v: fn(v, faces, K.double(), attr.double(), rasterize_reference, interpolate_reference),
                       [verts.double()], up.double())
    assert gvr.abs().max() > 0
    _assert_rel(gv, gvr, 1e-4)


def _bd(out, ub, ud):
    _, bary, depth = out
    return (bary * ub).sum() + (depth * ud).sum()


def test_rasterize_reference_gradcheck():
    verts, faces, K, _ = _soup(T=1, F=3, seed=5)
    fi = rasterize_reference(verts.double(), faces, K.double(), (19, 23))[0]
    assert (fi >= 0).sum() > 10

    def fn(v, k):
        _, bary, depth = rasterize_reference(v, faces, k, (19, 23))
        return bary, depth

    assert torch.autograd.gradcheck(fn, (verts.double().requires_grad_(), K.double().requires_grad_()), eps=1e-7, atol=1e-5)


@pytest.mark.parametrize("tile_size", [3, 16, 64])
def test_rasterize_tile_size_is_output_neutral(device, tile_size):
    verts, faces = _sphere(subdivisions=2)
    K = _K(14.0, 15.5, 14.5).to(device)
    ref = rasterize(verts.to(device), faces.to(device), K, (31, 33), tile_size=1)
    out = rasterize(verts.to(device), faces.to(device), K, (31, 33), tile_size=tile_size)
    for a, b in zip(out, ref):
        torch.testing.assert_close(a, b, atol=0, rtol=0)


def test_rasterize_tie_breaking_and_hidden_faces(device):
    v = torch.tensor([[[-1.0, -1.0, 2.0], [1.0, -1.0, 2.0], [0.0, 1.0, 2.0], [0.0, 0.0, 4.0], [0.0, 0.0, -1.0]]])
    faces = torch.tensor([[0, 1, 3], [0, 1, 2], [2, 1, 0], [0, 1, 4]])  # 1 and 2: same triangle, both windings
    fi, _, _ = rasterize(v.to(device), faces.to(device), _K(8.0, 11.0, 9.0).to(device), (19, 23))
    fr = rasterize_reference(v.double(), faces, _K(8.0, 11.0, 9.0, torch.float64), (19, 23))[0]
    assert (fi.cpu() == fr).all()
    vals = set(fi.unique().tolist())
    assert 1 in vals and 2 not in vals and 3 not in vals  # lower id wins, behind-camera face never drawn


def test_rasterize_interpolate_tilted_plane(device):
    """Two triangles on the plane z = 3 + 0.4 x - 0.3 y: depth and interpolated camera-space points
    match the analytic ray-plane intersection at every pixel centre."""
    K = torch.tensor([[25.0, 0.0, 15.3], [0.0, 22.0, 12.7], [0.0, 0.0, 1.0]])
    xy = torch.tensor([[-1.5, -1.5], [1.5, -1.5], [1.5, 1.5], [-1.5, 1.5]])
    z = 3.0 + 0.4 * xy[:, 0] - 0.3 * xy[:, 1]
    v = torch.cat([xy, z[:, None]], 1)[None]
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    fi, bary, depth = rasterize(v.to(device), faces.to(device), K.to(device), (26, 31))
    pts = interpolate(v[0].to(device), faces.to(device), fi, bary).cpu()
    fi, bary, depth = fi.cpu(), bary.cpu(), depth.cpu()
    r, c = torch.meshgrid(torch.arange(26.0), torch.arange(31.0), indexing="ij")
    u, w = (c - 15.3) / 25.0, (r - 12.7) / 22.0
    z_true = 3.0 / (1.0 - 0.4 * u + 0.3 * w)
    fg = fi[0] >= 0
    assert fg.float().mean() > 0.5 and (fi[0] == 1).any() and (fi[0] == 0).any()
    torch.testing.assert_close(depth[0][fg], z_true[fg], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(pts[0][fg], torch.stack([u * z_true, w * z_true, z_true], -1)[fg], atol=2e-5, rtol=1e-5)
    torch.testing.assert_close(bary[0][fg].sum(-1), torch.ones(int(fg.sum())), atol=1e-6, rtol=0)
    assert (depth[0][~fg] == 0).all() and (pts[0][~fg] == 0).all() and (bary[0][~fg] == 0).all()


@pytest.mark.parametrize("per_frame", [False, True])
def test_interpolate_matches_reference(device, per_frame):
    verts, faces, K, size = _soup(F=10, seed=6)
    fi, bary, _ = rasterize(verts.to(device), faces.to(device), K.to(device), size)
    attr = torch.randn(2, verts.shape[1], 4) if per_frame else torch.randn(verts.shape[1], 4)
    up = torch.randn(2, *size, 4)
    out, (ga, gb) = _grads(lambda a, b: interpolate(a, faces.to(device), fi, b), [attr.to(device), bary], up.to(device))
    outr, (gar, gbr) = _grads(lambda a, b: interpolate_reference(a, faces, fi.cpu(), b), [attr.double(), bary.cpu().double()], up)
    torch.testing.assert_close(out.cpu().double(), outr, atol=1e-6, rtol=1e-6)
    torch.testing.assert_close(ga.cpu().double(), gar, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(gb.cpu().double(), gbr, atol=1e-5, rtol=1e-5)


def test_interpolate_reference_gradcheck():
    fi = torch.tensor([[[0, -1, 1], [1, 1, -1]]])
    faces = torch.tensor([[0, 1, 2], [1, 2, 3]])
    attr = torch.randn(4, 2, dtype=torch.float64, requires_grad=True)
    bary = torch.rand(1, 2, 3, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b: interpolate_reference(a, faces, fi, b), (attr, bary))


# ---------------------------------------------------------------------------------------------
# error paths


@pytest.mark.parametrize(
    "kwargs, exc, match",
    [
        ({"verts": torch.zeros(5, 3)}, ValueError, r"soft_silhouette\(\): verts must have shape \(\*, \*, 3\), got \(5, 3\)"),
        ({"verts": torch.zeros(1, 3, 3, dtype=torch.float64)}, TypeError, "verts must be float32"),
        ({"faces": torch.zeros(1, 3)}, TypeError, "faces must be int32 or int64"),
        ({"faces": torch.tensor([[0, 1, 3]])}, ValueError, r"faces must index vertices in \[0, 2\]"),
        ({"faces": torch.zeros(0, 3, dtype=torch.int64)}, ValueError, "F >= 1"),
        ({"K": torch.eye(3)[None].repeat(2, 1, 1)}, ValueError, r"K must have shape \(1, 3, 3\)"),
        ({"K": [[1, 0, 0]]}, TypeError, "K must be a torch.Tensor"),
        ({"image_size": (0, 4)}, ValueError, "image_size must be two positive integers"),
        ({"image_size": 7}, ValueError, "image_size must be two positive integers"),
        ({"sigma": 0.0}, ValueError, "sigma must be a positive number"),
        ({"tile_size": 2.5}, ValueError, "tile_size must be a positive integer"),
    ],
)
def test_soft_silhouette_errors(kwargs, exc, match):
    args = {"verts": torch.rand(1, 3, 3) + 1.0, "faces": torch.tensor([[0, 1, 2]]), "K": torch.eye(3),
            "image_size": (4, 5), "sigma": 1.0, "tile_size": 8}
    args.update(kwargs)
    with pytest.raises(exc, match=match):
        soft_silhouette(**args)


def test_rasterize_and_interpolate_errors():
    v, f = torch.rand(1, 3, 3) + 1.0, torch.tensor([[0, 1, 2]])
    with pytest.raises(ValueError, match=r"rasterize\(\): K must have shape"):
        rasterize(v, f, torch.eye(4), (4, 5))
    with pytest.raises(ValueError, match=r"rasterize\(\): near must be a positive number"):
        rasterize(v, f, torch.eye(3), (4, 5), near=-1.0)
    fi, bary = torch.full((1, 4, 5), -1, dtype=torch.int32), torch.zeros(1, 4, 5, 3)
    with pytest.raises(ValueError, match=r"interpolate\(\): bary must have shape \(1, 4, 5, 3\)"):
        interpolate(torch.zeros(3, 2), f, fi, bary[..., :2])
    with pytest.raises(ValueError, match=r"interpolate\(\): attr must have shape \(V, C\) or \(1, V, C\)"):
        interpolate(torch.zeros(2, 3, 2), f, fi, bary)
    with pytest.raises(ValueError, match=r"face_index must be -1 or a face id in \[0, 0\]"):
        interpolate(torch.zeros(3, 2), f, fi + 2, bary)
    with pytest.raises(TypeError, match="face_index must be int32 or int64"):
        interpolate(torch.zeros(3, 2), f, fi.float(), bary)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device to mix devices")
def test_mixed_devices_error():
    with pytest.raises(ValueError, match="all inputs must be on one device"):
        soft_silhouette(torch.rand(1, 3, 3).cuda() + 1, torch.tensor([[0, 1, 2]]), torch.eye(3), (4, 5))


def test_frame_ranges_side_by_side_change_no_bit():
    """On the CPU the raster ops launch their frames in ranges, one per torch thread: the result and the gradients
    are the same to the last bit as one launch over every frame."""
    verts, faces, K, size = _soup(T=5, F=12, seed=9)
    up = torch.randn(5, *size)
    upc = torch.randn(5, *size, 2)
    attr = torch.randn(verts.shape[1], 2)

    def run():
        v = verts.clone().requires_grad_()
        a = attr.clone().requires_grad_()
        sil = soft_silhouette(v, faces, K, size, sigma=1.5)
        fi, bary, depth = rasterize(v, faces, K, size)
        col = interpolate(a, faces, fi, bary)
        ((sil * up).sum() + (depth * up).sum() + (col * upc).sum()).backward()
        return [sil, fi, bary, depth, col, v.grad, a.grad]

    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = run()
        torch.set_num_threads(3)
        ranges = run()
    finally:
        torch.set_num_threads(threads)
    for x, y in zip(one, ranges):
        assert torch.equal(x, y)
