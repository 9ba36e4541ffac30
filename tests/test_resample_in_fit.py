"""Even resampling (paper B) on a fit's state: the render, the loss and the optimiser's state carry over."""

from __future__ import annotations

import pytest
import torch
from conftest import joint_fitter, smoke_config

_cfg = smoke_config  # tiny_sequence: conftest.py


@pytest.mark.parametrize("method", ["marching", "isotropic"])
def test_even_resampling_in_the_fit_keeps_the_render_and_the_loss(tiny_sequence, tmp_path, method, monkeypatch):
    from s3o_warp.kernels.raster import rasterize

    import s3o_warp.resample as rs

    cfg, data, f, frames = joint_fitter(tiny_sequence, tmp_path)
    monkeypatch.setattr(rs, "METHODS", (method,))  # this method alone
    m, S = f.model, data.crop_size

    def state():
        with torch.no_grad():
            fi, _, _ = rasterize(m(frames), m.faces, m.intrinsics_crop(frames), (S, S))
            return (fi >= 0), float(sum(w * v for w, v in f.motion_losses(frames)[0].values()))

    sil0, loss0 = state()
    n0, bones_state = m.verts.shape[0], f.opt.state[m.bone_aa]["exp_avg"].clone()
    f.resample_mesh()
    sil1, loss1 = state()
    iou = float((sil0 & sil1).sum() / (sil0 | sil1).sum())
    assert iou > 0.9, iou  # the same surface, posed by the same skeleton
    assert abs(loss1 - loss0) < 0.15 * loss0, (loss0, loss1)
    assert abs(m.verts.shape[0] - len(f.coarse.init.verts)) <= 0.15 * len(f.coarse.init.verts) or m.verts.shape[0] != n0
    if method == "isotropic":  # no grid: the count lands near the target
        assert abs(m.verts.shape[0] - len(f.coarse.init.verts)) <= 0.15 * len(f.coarse.init.verts)
    assert f.ctx.edges.max() < m.verts.shape[0]
    # the optimiser keeps the motion's Adam state and steps the new vertices
    torch.testing.assert_close(f.opt.state[m.bone_aa]["exp_avg"], bones_state)
    v0 = m.verts.detach().clone()
    f.opt.zero_grad()
    terms, _, _ = f.motion_losses(frames)
    sum(w * v for w, v in terms.values()).backward()
    f.step_window(frames)
    assert not torch.equal(v0, m.verts.detach())


def test_a_refused_resampling_keeps_the_mesh_and_its_optimiser_state(tiny_sequence, tmp_path, monkeypatch):
    """When even_resample gives the mesh back (it would lose more than ResampleSettings.max_lost), the fit keeps its
    vertex parameter, the vertices' Adam state and the Laplacian reference, and logs the resampling as kept."""
    import s3o_warp.resample as rs

    cfg, data, f, frames = joint_fitter(tiny_sequence, tmp_path)
    m = f.model
    f.opt.zero_grad()
    terms, _, _ = f.motion_losses(frames)
    sum(w * v for w, v in terms.values()).backward()
    f.step_window(frames)  # the vertices have Adam state now
    seen = []

    def refuse(verts, faces, settings=None, attributes=None):
        seen.append((settings.method, settings.target_vertices))
        return verts.detach().clone(), faces.detach().clone(), attributes.detach().clone()

    monkeypatch.setattr(rs, "even_resample", refuse)
    verts, lap_ref, state = m.verts, f.ctx.lap_ref, {k: v.clone() for k, v in f.opt.state[m.verts].items()}
    f.resample_mesh()
    # the target reaches the resampling; refused by marching, isotropic is tried on the same mesh
    n = len(f.coarse.init.verts)
    assert seen == [("marching", n), ("isotropic", n)]
    assert m.verts is verts and f.ctx.lap_ref is lap_ref
    for k, v in state.items():
        torch.testing.assert_close(f.opt.state[m.verts][k], v)
    assert f.history[-1]["what"] == "resample" and f.history[-1]["kept"] is True and f.history[-1]["method"] is None


def test_a_resampling_refused_by_marching_is_done_by_the_fallback(tiny_sequence, tmp_path, monkeypatch):
    """When marching would lose too much, isotropic remeshing's result is used (and logged)."""
    import s3o_warp.resample as rs

    cfg, data, f, frames = joint_fitter(tiny_sequence, tmp_path)
    m = f.model
    real = rs.even_resample
    seen = []

    def marching_refuses(verts, faces, settings=None, attributes=None):
        seen.append(settings.method)
        if settings.method == "marching":
            return verts.detach().clone(), faces.detach().clone(), attributes.detach().clone()
        return real(verts, faces, settings, attributes)

    monkeypatch.setattr(rs, "even_resample", marching_refuses)
    verts = m.verts
    f.resample_mesh()
    assert seen == ["marching", "isotropic"]
    assert m.verts is not verts and f.ctx.edges.max() < m.verts.shape[0]
    assert f.history[-1]["kept"] is False and f.history[-1]["method"] == "isotropic"
