"""Closest point / signed distance (Warp BVH) against its brute-force twin, and the even resampling."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch
import trimesh
from s3o_warp.kernels.sdf import closest_point

from s3o_warp.errors import ConfigError, InputError
from s3o_warp.reference.sdf import closest_on_faces_naive, closest_point_naive
from s3o_warp.resample import ResampleSettings, even_resample

MIRROR = torch.tensor([1.0, 1.0, -1.0])


def _rotated_sphere(subdivisions: int = 2, seed: int = 0):
    m = trimesh.creation.icosphere(subdivisions)
    rot = trimesh.transformations.random_rotation_matrix(rand=np.random.default_rng(seed).random(3))
    return torch.tensor(m.vertices @ rot[:3, :3].T, dtype=torch.float32), torch.tensor(m.faces, dtype=torch.int64)


def _box():
    m = trimesh.creation.box(extents=(1.0, 0.6, 0.8))
    return torch.tensor(m.vertices, dtype=torch.float32), torch.tensor(m.faces, dtype=torch.int64)


def _uneven_ellipsoid(subdivisions: int = 3, power: float = 2.5, radii=(1.5, 0.8, 0.6), bend: float = 0.0,
                      shift=(0.0, 0.0, 0.0)):
    """A closed ellipsoid whose vertices crowd towards +x (polar angle theta -> pi (theta / pi)^power).

    ``bend`` adds bend * x^2 to y and ``shift`` moves it; neither touches z, so the mesh stays
    mirror-symmetric about z = 0 (the icosphere is).
    """
    m = trimesh.creation.icosphere(subdivisions)
    v = m.vertices
    theta = np.arccos(np.clip(v[:, 0], -1.0, 1.0))
    theta = np.pi * (theta / np.pi) ** power
    r = np.linalg.norm(v[:, 1:], axis=1, keepdims=True)
    around = np.where(r > 1e-12, v[:, 1:] / np.maximum(r, 1e-12), 0.0)
    v = np.concatenate([np.cos(theta)[:, None], np.sin(theta)[:, None] * around], axis=1) * np.array(radii)
    v[:, 1] += bend * v[:, 0] ** 2
    v += np.array(shift)
    return torch.tensor(v, dtype=torch.float32), torch.tensor(m.faces, dtype=torch.int64)


def _sphere_with_leg(radius: float = 0.08, length: float = 1.2, direction=(1.0, 0.35, 0.25)):
    """A unit sphere with a thin capped cylinder sticking out (two overlapping closed parts); also the leg's tip."""
    s = trimesh.creation.icosphere(3)
    d = np.array(direction) / np.linalg.norm(direction)
    start = 0.93  # just inside the sphere: the leg's own vertices all lie near the union's surface
    c = trimesh.creation.cylinder(radius=radius, segment=[d * start, d * (start + length)], sections=12)
    v = np.concatenate([s.vertices, c.vertices])
    f = np.concatenate([s.faces, c.faces + len(s.vertices)])
    return torch.tensor(v, dtype=torch.float32), torch.tensor(f), torch.tensor(d * (start + length), dtype=torch.float32)


def _trimesh(v: torch.Tensor, f: torch.Tensor) -> trimesh.Trimesh:
    return trimesh.Trimesh(v.detach().cpu().double().numpy(), f.cpu().numpy(), process=False)


def _edge_cv(m: trimesh.Trimesh) -> float:
    e = m.edges_unique_length
    return float(e.std() / e.mean())


def _spacing(m: trimesh.Trimesh) -> float:
    """The grid spacing that made a marching-cubes mesh (about 1.5 vertices per h^2 of area)."""
    return math.sqrt(1.5 * m.area / len(m.vertices))


def _unsigned(verts, faces, points) -> torch.Tensor:
    return closest_point(verts, faces, points)[0].abs().cpu()


# --------------------------------------------------------------------------------------------------
# closest_point


@pytest.mark.parametrize("shape", ["sphere", "box"])
def test_closest_point_matches_naive(device, shape):
    verts, faces = _rotated_sphere(2) if shape == "sphere" else _box()
    gen = torch.Generator().manual_seed(1)
    half = verts.abs().max(0).values
    points = (torch.rand(400, 3, generator=gen) * 2.0 - 1.0) * 1.4 * half  # inside and outside
    ref_d, ref_f, ref_b = closest_point_naive(verts.double(), faces, points.double())
    points = points[ref_d.abs() > 1e-3]  # the sign of a point on the surface is a coin toss
    ref_d, ref_f, ref_b = ref_d[ref_d.abs() > 1e-3], ref_f[ref_d.abs() > 1e-3], ref_b[ref_d.abs() > 1e-3]
    assert (ref_d < 0).sum() > 50 and (ref_d > 0).sum() > 50

    d, f, b = closest_point(verts.to(device), faces.to(device), points.to(device))
    assert d.device == points.to(device).device and d.dtype == torch.float32
    assert f.dtype == torch.int64 and b.dtype == torch.float32 and b.shape == (len(points), 3)
    d, f, b = d.cpu(), f.cpu(), b.cpu()
    torch.testing.assert_close(d.double(), ref_d, atol=2e-5, rtol=0)
    assert torch.equal(d < 0, ref_d < 0)
    # barycentrics: a convex combination whose point is the naive closest point, |d| away
    assert (b >= -1e-6).all() and torch.allclose(b.sum(1), torch.ones(len(b)), atol=1e-5)
    closest = (b[:, :, None] * verts[faces[f]]).sum(1)
    torch.testing.assert_close(torch.linalg.vector_norm(closest - points, dim=1), d.abs(), atol=1e-5, rtol=0)
    # the face: any face at the minimum distance is right; where the runner-up is clearly farther, exactly it
    d2, _ = closest_on_faces_naive(verts.double()[faces], points.double())
    best2 = d2.gather(1, ref_f[:, None])[:, 0]
    assert ((d2.gather(1, f[:, None])[:, 0].sqrt() - best2.sqrt()).abs() < 1e-5).all()
    runner_up = d2.scatter(1, ref_f[:, None], math.inf).min(1).values
    unambiguous = runner_up.sqrt() - best2.sqrt() > 1e-3
    assert unambiguous.sum() > 100
    assert torch.equal(f[unambiguous], ref_f[unambiguous])
    # the closest point itself, wherever it is unique (one face's closest point is)
    unique = unambiguous | (f == ref_f)
    ref_closest = (ref_b[:, :, None] * verts.double()[faces[ref_f]]).sum(1)
    assert (closest.double() - ref_closest)[unique].norm(dim=1).max() < 1e-4


def test_closest_point_far_points_and_float64_mesh(device):
    """Points far from a float64 mesh: right distance and sign; outputs float32 on the points' device."""
    verts, faces = _rotated_sphere(1, seed=2)
    points = torch.tensor([[0.0, 0.0, 0.0], [30.0, -40.0, 0.0], [0.1, 0.2, -0.3]], dtype=torch.float64)
    d, _, _ = closest_point(verts.double().to(device), faces.to(device), points.to(device))
    ref_d, _, _ = closest_point_naive(verts.double(), faces, points)
    assert d.dtype == torch.float32 and d.device == points.to(device).device
    torch.testing.assert_close(d.cpu().double(), ref_d, atol=1e-4, rtol=1e-6)
    assert d[0] < 0 and d[1] > 49 and d[2] < 0


def test_closest_point_errors():
    verts, faces = _box()
    with pytest.raises(ValueError, match=r"points must have shape \(\*, 3\)"):
        closest_point(verts, faces, torch.zeros(4, 2))
    with pytest.raises(TypeError, match="faces must be an integer"):
        closest_point(verts, faces.float(), verts)
    with pytest.raises(ValueError, match="faces index vertices"):
        closest_point(verts[:4], faces, verts)
    with pytest.raises(ValueError, match="mesh is empty"):
        closest_point(verts, faces[:0], verts)
    d, f, b = closest_point(verts, faces, torch.zeros(0, 3))
    assert d.shape == (0,) and f.shape == (0,) and b.shape == (0, 3)


# --------------------------------------------------------------------------------------------------
# even_resample


def test_even_resample_uneven_ellipsoid(device):
    verts, faces = _uneven_ellipsoid()
    before = _trimesh(verts, faces)
    assert before.is_watertight and _edge_cv(before) > 0.7
    s = ResampleSettings(target_vertices=1000)
    nv, nf, attr = even_resample(verts.to(device), faces.to(device), s)
    assert attr is None and nv.dtype == torch.float32 and nf.dtype == torch.int64
    assert nv.device == verts.to(device).device and nf.device == nv.device
    after = _trimesh(nv, nf)
    assert after.is_watertight and after.is_winding_consistent and after.volume > 0 and after.body_count == 1
    assert abs(len(nv) - 1000) <= s.vertex_tolerance * 1000
    assert _edge_cv(after) < 0.5 * _edge_cv(before)
    assert abs(after.volume / before.volume - 1.0) < 0.03
    h = _spacing(after)
    nv, nf = nv.cpu(), nf.cpu()
    assert _unsigned(nv, nf, verts).max() < 1.5 * h  # old surface -> new one
    # new vertices lie on the old surface (projected), give or take the volume-keeping offset
    assert _unsigned(verts, faces, nv).max() < 0.05 * h
    # and the new surface stays near the old one between vertices too (face centres)
    assert _unsigned(verts, faces, nv[nf].mean(1)).max() < 0.5 * h


def test_even_resample_keeps_count_by_default_and_float64():
    verts, faces = _uneven_ellipsoid(power=2.0)
    nv, nf, _ = even_resample(verts.double(), faces.int())
    assert nv.dtype == torch.float64 and nf.dtype == torch.int64
    assert abs(len(nv) - len(verts)) <= 0.15 * len(verts)
    after = _trimesh(nv, nf)
    assert after.is_watertight and after.is_winding_consistent and after.volume > 0


def test_even_resample_carries_linear_attributes(device):
    verts, faces = _uneven_ellipsoid(bend=0.3)
    a = torch.tensor([[0.5, -1.0], [2.0, 0.3], [-0.7, 1.1]])
    b = torch.tensor([0.2, -3.0])
    attrs = verts @ a + b
    slope = float(torch.linalg.matrix_norm(a, ord=2))
    for project, keep_volume in ((True, False), (False, False), (True, True)):
        s = ResampleSettings(target_vertices=700, project=project, keep_volume=keep_volume)
        nv, _, new = even_resample(verts.to(device), faces.to(device), s, attributes=attrs.to(device))
        nv, new = nv.cpu(), new.cpu()
        assert new.shape == (len(nv), 2) and new.dtype == torch.float32
        # off by the vertex's distance to the old surface times the slope: exact for vertices on it
        err = (new - (nv @ a + b)).abs().max(1).values
        off = _unsigned(verts, faces, nv)
        assert (err <= slope * off + 1e-4).all()
        if project and not keep_volume:  # all but a few (mirror-averaged on the plane, or kept) are on it
            assert (err < 1e-4).float().mean() > 0.95
            projected = (nv, new)
        else:
            assert err.max() > 1e-3
    s = ResampleSettings(target_vertices=700, keep_volume=False)
    nv, _, new = even_resample(verts.to(device), faces.to(device), s, attributes=attrs.double().to(device))
    nv, new = nv.cpu(), new.cpu()  # the same device as the float32 run: bit-equal vertices
    assert new.dtype == torch.float64 and nv.dtype == torch.float32
    assert torch.equal(nv, projected[0]) and (new - projected[1].double()).abs().max() < 1e-5


def test_even_resample_stays_mirror_symmetric(device):
    verts, faces = _uneven_ellipsoid(bend=0.3, shift=(0.37, -0.21, 0.0))
    assert _unsigned(verts, faces, verts * MIRROR).max() < 1e-6  # the input is symmetric about z = 0
    nv, nf, _ = even_resample(verts.to(device), faces.to(device), ResampleSettings(target_vertices=800))
    nv, nf = nv.cpu(), nf.cpu()
    h = _spacing(_trimesh(nv, nf))
    # every reflected vertex lies on the new surface, and near a new vertex (what the symmetry loss pairs)
    assert _unsigned(nv, nf, nv * MIRROR).max() < 0.02 * h
    assert torch.cdist(nv * MIRROR, nv).min(1).values.max() < 0.05 * h


@pytest.mark.parametrize("repair", ["dilate", "refine"])
def test_even_resample_keeps_thin_leg(device, repair):
    verts, faces, tip = _sphere_with_leg()
    s = ResampleSettings(target_vertices=800)
    if repair == "refine":
        s = replace(s, dilate_steps=())
    # at the target's spacing the leg falls apart into specks that are dropped ...
    nv, nf, _ = even_resample(verts.to(device), faces.to(device), replace(s, coverage_fraction=0.5))
    assert _unsigned(nv.cpu(), nf.cpu(), tip[None]) > 0.5
    # ... so it is marched again, from a dilated surface (then projected back) or on a finer grid
    nv, nf, _ = even_resample(verts.to(device), faces.to(device), s)
    nv, nf = nv.cpu(), nf.cpu()
    after = _trimesh(nv, nf)
    assert after.is_watertight and after.is_winding_consistent and after.body_count == 1
    assert len(nv) <= s.max_vertices_factor * 800 * (1 + s.vertex_tolerance)
    if repair == "dilate":  # the count stays near the target
        assert len(nv) <= 800 * (1 + 2 * s.vertex_tolerance)
    h = _spacing(after)
    assert _unsigned(nv, nf, tip[None]) < 1.5 * h
    assert (_unsigned(nv, nf, verts) > 1.5 * h).float().mean() <= s.coverage_fraction


def _sphere_with_legs(n: int = 12, radius: float = 0.03, length: float = 1.0, seed: int = 0):
    """A unit sphere with n thin capped cylinders sticking out in random directions, and the legs' tips."""
    s = trimesh.creation.icosphere(3)
    vs, fs, tips, off = [s.vertices], [s.faces], [], len(s.vertices)
    rng = np.random.default_rng(seed)
    for _ in range(n):
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        c = trimesh.creation.cylinder(radius=radius, segment=[d * 0.93, d * (0.93 + length)], sections=12)
        vs.append(c.vertices)
        fs.append(c.faces + off)
        off += len(c.vertices)
        tips.append(d * (0.93 + length))
    return (torch.tensor(np.concatenate(vs), dtype=torch.float32), torch.tensor(np.concatenate(fs)),
            torch.tensor(np.array(tips), dtype=torch.float32))


def test_even_resample_never_passes_its_vertex_cap(caplog):
    """Twelve legs thinner than the grid: dilating them adds so much surface that the refinement's next grid
    would make 1324 vertices against a cap of 1.5 x 600 x 1.15 (which the repair used to return). It stops below the
    cap instead, keeps the attempt that lost the fewest old vertices, and says so."""
    verts, faces, _ = _sphere_with_legs()
    s = ResampleSettings(target_vertices=600, max_vertices_factor=1.5)
    with caplog.at_level("WARNING", logger="s3o_warp.resample"):
        nv, nf, _ = even_resample(verts, faces, s)
    assert len(nv) <= 1.5 * 600 * (1 + s.vertex_tolerance)
    after = _trimesh(nv, nf)
    assert after.is_watertight and after.is_winding_consistent
    assert "stay farther than" in caplog.text and "a higher target" in caplog.text


def _ball_with_fin(thickness: float = 0.004):
    """A ball with a flat fin thinner than any grid of a few hundred vertices (two overlapping closed surfaces)."""
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    fin = trimesh.creation.box(extents=(1.6, 1.2, thickness))
    fin.apply_translation((0.9, 0.0, 0.0))
    fin = trimesh.Trimesh(*trimesh.remesh.subdivide_to_size(fin.vertices, fin.faces, max_edge=0.06))
    m = trimesh.util.concatenate([ball, fin])
    return torch.tensor(m.vertices, dtype=torch.float32), torch.tensor(m.faces)


def test_even_resample_that_would_lose_too_much_gives_the_mesh_back(caplog):
    """A fin 0.004 thick is lost at a 600-vertex grid whatever the repair (about 6.5 % of the old vertices): over
    max_lost the input comes back as it is, attributes too, with a warning; max_lost=1 returns that lossy attempt."""
    verts, faces = _ball_with_fin()
    attr = torch.randn(len(verts), 3)
    s = ResampleSettings(target_vertices=600, max_lost=0.02)
    with caplog.at_level("WARNING", logger="s3o_warp.resample"):
        nv, nf, na = even_resample(verts, faces, s, attributes=attr)
    assert "not used" in caplog.text and "over max_lost=0.02" in caplog.text
    assert torch.equal(nv, verts) and torch.equal(nf, faces.to(torch.int64)) and torch.equal(na, attr)
    assert nv.data_ptr() != verts.data_ptr()  # a copy: the caller may change it
    lossy, lf, _ = even_resample(verts, faces, replace(s, max_lost=1.0))
    assert len(lossy) <= 2 * 600 * (1 + s.vertex_tolerance) < len(verts)
    far = _unsigned(lossy, lf, verts)  # the fin's far edge is gone
    assert float((far > 0.1).float().mean()) > 0.02


def _needle(radius: float = 0.03, length: float = 1.0):
    """One closed surface of revolution: a unit ball with a leg of this radius up the z axis; and the leg's tip."""
    theta = np.linspace(0.0, np.pi - np.arcsin(radius), 48)  # polar angle from the south pole to the leg
    profile = np.stack([np.sin(theta), -np.cos(theta)], 1)
    profile = np.concatenate([profile, [[radius, 1.0 + 0.5 * length], [radius, 1.0 + length], [0.0, 1.0 + length]]])
    m = trimesh.creation.revolve(profile, sections=24)
    return (torch.tensor(m.vertices, dtype=torch.float32), torch.tensor(m.faces),
            torch.tensor([[0.0, 0.0, 1.0 + length]]))


@pytest.mark.parametrize("shape", ["ellipsoid", "needle"])
def test_isotropic_resample_evens_the_surface_and_keeps_thin_parts(device, shape):
    """method=isotropic remeshes the surface itself: the count near the target, edges more even, the volume
    kept, and legs thinner than marching cubes' grid all there (every old vertex near the new surface)."""
    if shape == "ellipsoid":
        verts, faces = _uneven_ellipsoid()
        tips = None
    else:
        verts, faces, tips = _needle()
    before = _trimesh(verts, faces)
    assert before.body_count == 1
    target = 1000 if shape == "ellipsoid" else 600
    s = ResampleSettings(method="isotropic", target_vertices=target)
    nv, nf, _ = even_resample(verts.to(device), faces.to(device), s)
    assert nv.device == verts.to(device).device and nv.dtype == torch.float32 and nf.dtype == torch.int64
    nv, nf = nv.cpu(), nf.cpu()
    after = _trimesh(nv, nf)
    assert after.is_watertight and after.is_winding_consistent and after.body_count == 1
    assert abs(len(nv) - target) <= s.vertex_tolerance * target
    assert _edge_cv(after) < _edge_cv(before)
    assert abs(after.volume / before.volume - 1.0) < 0.03
    mean_edge = float(after.edges_unique_length.mean())
    assert _unsigned(nv, nf, verts).max() < 0.5 * mean_edge  # nothing of the old surface lost
    assert _unsigned(verts, faces, nv).max() < 0.1 * mean_edge  # new vertices on the old surface
    if tips is not None:
        assert _unsigned(nv, nf, tips).max() < 0.2 * mean_edge
    # the marching-cubes path at this count loses legs (or has to dilate them)
    mv, mf, _ = even_resample(verts, faces, ResampleSettings(target_vertices=target, dilate_steps=(),
                                                             max_vertices_factor=1.0))
    if tips is not None:
        assert _unsigned(mv, mf, tips).max() > 0.5


def test_isotropic_resample_carries_linear_attributes():
    verts, faces = _uneven_ellipsoid(bend=0.3)
    a = torch.tensor([[0.5, -1.0], [2.0, 0.3], [-0.7, 1.1]])
    attrs = verts @ a
    s = ResampleSettings(method="isotropic", target_vertices=700, keep_volume=False)
    nv, _, new = even_resample(verts, faces, s, attributes=attrs)
    assert new.shape == (len(nv), 2)
    assert ((new - nv @ a).abs().max(1).values < 1e-4).float().mean() > 0.95  # vertices on the old surface


def test_repeated_resampling_keeps_volume_and_count():
    """Every-epoch use: ten resamplings at a fixed target neither shrink the mesh nor drift in count."""
    verts, faces = _uneven_ellipsoid(subdivisions=2, radii=(1.5, 0.5, 0.4))
    volume = _trimesh(verts, faces).volume
    s = ResampleSettings(target_vertices=400)
    v, f = verts, faces
    for _ in range(10):
        v, f, _ = even_resample(v, f, s)
    after = _trimesh(v, f)
    assert after.is_watertight and after.is_winding_consistent
    assert abs(after.volume / volume - 1.0) < 0.01
    assert abs(len(v) - 400) <= s.vertex_tolerance * 400
    sv, sf, _ = even_resample(verts, faces, replace(s, keep_volume=False))
    assert _trimesh(sv, sf).volume < 0.99 * volume  # what keep_volume undoes (per resampling)


def test_even_resample_input_errors():
    verts, faces = _box()
    with pytest.raises(InputError, match="mesh is empty"):
        even_resample(torch.zeros(0, 3), torch.zeros(0, 3, dtype=torch.int64))
    with pytest.raises(InputError, match="mesh is empty"):
        even_resample(verts, faces[:0])
    with pytest.raises(InputError, match="no inside found"):  # one open triangle has no inside
        even_resample(verts[:3], torch.tensor([[0, 1, 2]]))
    with pytest.raises(InputError, match="no inside found"):  # inside-out: winding number -1 inside
        even_resample(verts, faces.flip(1))
    with pytest.raises(InputError, match="attributes must be"):
        even_resample(verts, faces, attributes=torch.zeros(3, 2))
    bad = verts.clone()
    bad[0, 0] = float("nan")
    with pytest.raises(InputError, match="NaN"):
        even_resample(bad, faces)


def test_resample_settings_validation():
    with pytest.raises(ConfigError, match="ResampleSettings.vertex_tolerance"):
        ResampleSettings(vertex_tolerance=0.0)
    with pytest.raises(ConfigError, match="ResampleSettings.taubin_iterations"):
        ResampleSettings(taubin_iterations=5)
    with pytest.raises(ConfigError, match="ResampleSettings.target_vertices"):
        ResampleSettings(target_vertices=3)
    with pytest.raises(ConfigError, match="ResampleSettings.dilate_steps"):
        ResampleSettings(dilate_steps=(0.5, 0.25))
    with pytest.raises(ConfigError, match="ResampleSettings.refine_step"):
        replace(ResampleSettings(), refine_step=1.0)
    with pytest.raises(ConfigError, match="ResampleSettings.method"):
        ResampleSettings(method="manifold")
    with pytest.raises(ConfigError, match="ResampleSettings.isotropic_iterations"):
        ResampleSettings(isotropic_iterations=0)
    with pytest.raises(ConfigError, match="ResampleSettings.max_lost"):
        ResampleSettings(max_lost=-0.1)


# --------------------------------------------------------------------------------------------------
# ray_hit


def test_ray_hit_matches_naive(device):
    from s3o_warp.kernels.sdf import ray_hit

    from s3o_warp.reference.sdf import ray_hit_naive

    verts, faces = _rotated_sphere(2, seed=4)
    gen = torch.Generator().manual_seed(5)
    origins = (torch.rand(300, 3, generator=gen) * 2 - 1) * 1.1  # inside and outside
    dirs = torch.randn(300, 3, generator=gen)
    ref_t, ref_f = ray_hit_naive(verts.double(), faces, origins.double(), dirs.double(), max_t=50.0)
    assert (ref_f >= 0).sum() > 100 and (ref_f < 0).sum() > 10  # hits and misses
    t, f = ray_hit(verts.to(device), faces.to(device), origins.to(device), dirs.to(device), max_t=50.0)
    t, f = t.cpu(), f.cpu()
    assert t.dtype == torch.float32 and f.dtype == torch.int64
    assert torch.equal(f < 0, ref_f < 0)
    torch.testing.assert_close(t.double(), ref_t, atol=2e-5, rtol=0)
    hit = ref_f >= 0
    # the face: the naive one, or one at the same distance (a ray through an edge)
    assert (f[hit] == ref_f[hit]).float().mean() > 0.97
    with pytest.raises(ValueError, match="non-zero"):
        ray_hit(verts, faces, origins[:2], torch.zeros(2, 3))
    with pytest.raises(ValueError, match=r"dirs must have shape"):
        ray_hit(verts, faces, origins[:2], dirs[:3])


def test_centre_in_body_puts_joints_on_a_tube_axis():
    from s3o_warp.skeleton.joints import centre_in_body

    tube = trimesh.creation.cylinder(radius=0.1, height=1.0, sections=48)  # axis z
    v, f = trimesh.remesh.subdivide_to_size(tube.vertices, tube.faces, max_edge=0.05)  # rings along the side
    tube = trimesh.Trimesh(v, f)
    pts = np.array([[0.0, 0.099, 0.1],  # inside, at the wall
                    [0.14, 0.0, -0.2],  # outside, 0.04 off the wall
                    [0.03, -0.05, 0.3],  # inside, off axis
                    [0.0, 0.0, 0.0]])  # on the axis already
    out = centre_in_body(pts, tube.vertices, tube.faces, max_depth=0.2)  # 0.2 x 1.04 > the radius
    np.testing.assert_allclose(out[:, :2], 0.0, atol=3e-3)  # on the axis (48-gon: radius within 0.3%)
    np.testing.assert_allclose(out[:, 2], pts[:, 2], atol=1e-6)  # along it, where they were
    # a thick box: a point near a face goes max_depth x the diagonal below it, not to the middle; a deeper
    # point stays where it is
    box = trimesh.creation.box(extents=(2.0, 0.8, 1.0))
    cap = 0.03 * np.sqrt(4.0 + 0.64 + 1.0)
    out = centre_in_body(np.array([[0.5, 0.39, 0.1], [0.5, 0.45, 0.1], [0.2, 0.1, 0.0]]), box.vertices, box.faces)
    np.testing.assert_allclose(out, [[0.5, 0.4 - cap, 0.1], [0.5, 0.4 - cap, 0.1], [0.2, 0.1, 0.0]], atol=1e-5)
