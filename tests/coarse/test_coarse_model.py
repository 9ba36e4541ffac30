"""The coarse model (paper 3.2) and the coarse fit's start: the lift, the bones' refit, the canonical frame, the shared
principal point."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import smoke_config

from s3o_warp.coarse.model import coarse_model
from s3o_warp.data.store import prepare_data
from s3o_warp.errors import ConfigError
from s3o_warp.fit import Fitter, fit

_cfg = smoke_config  # tiny_sequence: conftest.py


def test_coarse_phase_builds_a_quadruped_skeleton(tiny_sequence, tmp_path):
    cfg = _cfg()
    data = prepare_data(tiny_sequence, cfg, tmp_path, torch.device("cpu"))
    res = coarse_model(data, cfg)
    # a side view of the built-in quadruped: a tree of bones with a torso root and limbs hanging off it
    parents = res.parents
    assert (parents == -1).sum() == 1
    assert len(parents) >= 5
    v = res.init.verts.numpy()
    assert np.isfinite(v).all() and len(v) > 100
    # the coarse mesh, posed by the canonical root, projects onto the canonical crop's mask
    from s3o_warp.model import S3OModel

    m = S3OModel(res.init)
    c = torch.tensor([res.canonical])
    with torch.no_grad():
        from s3o_warp.kernels.raster import rasterize

        fi, _, _ = rasterize(m(c), m.faces, m.intrinsics_crop(c), (64, 64))
    pred = (fi[0] >= 0).numpy()
    gt = data.masks[res.canonical].numpy() > 0.5
    iou = (pred & gt).sum() / (pred | gt).sum()
    assert iou > 0.5, iou


@pytest.mark.parametrize("method", ["s3o", "virtual"])
def test_bones_refit_to_their_coarse_parts_only_for_the_lift(tiny_sequence, tmp_path, method):
    """After the coarse fit the lift's bones move onto their labelled parts; the virtual baseline's k-means
    bones have no parts and stay where k-means put them, and its short fit runs through."""
    from s3o_warp.coarse.model import REFIT_MIN_FACES, refit_bones_to_parts
    from s3o_warp.skeleton.edit import fit_bones_to_parts

    cfg = _cfg(**{"coarse.steps": 4, "motion.warmup_steps": 4, "motion.steps": 4, "skeleton.method": method,
                  "skeleton.virtual_bones": 6})
    data = prepare_data(tiny_sequence, cfg, tmp_path, torch.device("cpu"))
    res = coarse_model(data, cfg)
    (tmp_path / "run").mkdir()
    fitter = Fitter(data, res, cfg, tmp_path / "run", torch.device("cpu"))
    m = fitter.model
    C0, Q0 = m.bone_centers.detach().clone(), m.precisions().detach().clone()
    if method == "s3o":  # the loop refits only the lift's bones
        refit_bones_to_parts(m, res)
    if method == "virtual":
        assert C0.shape[0] == 6
        torch.testing.assert_close(m.bone_centers, C0, rtol=0, atol=0)
        torch.testing.assert_close(m.precisions(), Q0, rtol=0, atol=0)
        fitter.run()
        assert (fitter.skel.parents == np.r_[-1, np.zeros(5, int)]).all()
        return
    C, Q, moved = fit_bones_to_parts(m.verts.detach(), m.faces, res.face_parts, C0, Q0, REFIT_MIN_FACES)
    assert moved.sum() >= len(moved) // 2 and np.abs(C - C0.numpy()).max() > 1e-3
    np.testing.assert_allclose(m.bone_centers.detach().numpy(), C, atol=1e-6)
    np.testing.assert_allclose(m.precisions().detach().numpy(), Q, rtol=1e-4, atol=1e-3 * np.abs(Q).max())


def test_a_shared_principal_point_starts_where_the_per_frame_ones_do_and_stays_one(tiny_sequence, tmp_path):
    from s3o_warp.model import S3OModel

    short = {"coarse.steps": 2, "motion.warmup_steps": 4, "motion.steps": 4}
    cfg, shared_cfg = _cfg(**short), _cfg(**short, **{"motion.principal_point": "shared"})
    data = prepare_data(tiny_sequence, cfg, tmp_path, torch.device("cpu"))
    per, shared = (S3OModel(coarse_model(data, c).init) for c in (cfg, shared_cfg))
    frames = torch.arange(data.num_frames)
    with torch.no_grad():
        Kp, Ks = per.intrinsics_frame(frames), shared.intrinsics_frame(frames)
        H, W = data.frame_size
        # the crops follow the object, so the per-frame points wander over the frame; the shared one is its centre
        assert (Kp[:, :2, 2] - Kp[:1, :2, 2]).abs().max() > 2.0
        assert torch.allclose(Ks[:, :2, 2], torch.tensor([(W - 1) / 2, (H - 1) / 2]).expand(len(frames), 2), atol=1e-3)
        assert torch.allclose(Ks[:, 0, 0], Kp[:, 0, 0])
        # the root starts where each crop's centre put the object: the same full-frame pixels, to perspective's
        # difference over the object's depth (a fraction of a pixel)
        def pixels(m, K):
            v = m(frames)
            return (v @ K.transpose(1, 2))[..., :2] / v[..., 2:]

        px_per, px_shared = pixels(per, Kp), pixels(shared, Ks)
        assert (px_per - px_shared).norm(dim=-1).max() < 0.5, (px_per - px_shared).norm(dim=-1).max()
        assert (per.root_t[:, :2] - shared.root_t[:, :2]).abs().max() > 1e-3  # the root took the crops' shift
        assert (per.root_R0 - shared.root_R0).abs().max() > 1e-4  # and turned with the ray to each crop's centre
    # a fit keeps one principal point (the exported intrinsics)
    run = tmp_path / "run"
    fit(tiny_sequence, run, shared_cfg, torch.device("cpu"))
    K = np.load(run / "motion.npz")["K"]
    assert np.abs(K[:, :2, 2] - K[:1, :2, 2]).max() < 1e-3 and np.abs(K[0, :2, 2] - [(W - 1) / 2, (H - 1) / 2]).max() > 0


def test_the_shared_principal_points_start_shows_each_crops_view():
    """Hand-made: crops far off the frame's centre (a ray 0.2 rad off the axis). The root on the crop's axis lands on
    the crop's centre, and the side of the object facing the camera (the camera's direction in the object frame) is
    the crop model's; moving the root sideways alone lands there too but shows another side."""
    from s3o_warp.geometry import axis_angle_to_matrix
    from s3o_warp.model import root_for_shared_principal_point

    f, pp, S = 500.0, (319.5, 239.5), 64
    centres = torch.tensor([[420.0, 239.5], [319.5, 140.0], [250.0, 330.0]], dtype=torch.float64)
    scale = 0.5  # crop pixels per frame pixel
    A = torch.zeros(3, 3, 3, dtype=torch.float64)  # crop -> frame: frame = crop / scale + offset
    A[:, 0, 0] = A[:, 1, 1] = 1 / scale
    A[:, 2, 2] = 1
    A[:, :2, 2] = centres - (S - 1) / 2 / scale
    R0 = axis_angle_to_matrix(torch.tensor([[0.3, -0.5, 0.2]], dtype=torch.float64)).expand(3, 3, 3)
    t0 = torch.tensor([[0.0, 0.0, 4.0]], dtype=torch.float64).expand(3, 3)
    R, t = root_for_shared_principal_point(R0, t0, A, S, f, pp)
    assert torch.allclose(R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(3, 3, 3), atol=1e-12)
    px = f * t[:, :2] / t[:, 2:] + torch.tensor(pp, dtype=torch.float64)
    assert torch.allclose(px, centres, atol=1e-9), px
    assert torch.allclose(t.norm(dim=1), t0.norm(dim=1))  # as far from the camera
    side = lambda R, t: torch.einsum("tji,tj->ti", R, -t) / t.norm(dim=1, keepdim=True)  # noqa: E731
    assert torch.allclose(side(R, t), side(R0, t0), atol=1e-12)
    shifted = t0.clone()
    shifted[:, :2] += (centres - torch.tensor(pp, dtype=torch.float64)) * t0[:, 2:] / f
    turned_by = torch.arccos((side(R0, shifted) * side(R0, t0)).sum(1).clamp(-1, 1))
    assert (turned_by > 0.15).all(), turned_by  # the old start showed the object 0.15-0.2 rad from the crop's side


def test_coarse_fit_keeps_the_lifted_depth(tiny_sequence, tmp_path):
    """One view says nothing about depth: the coarse fit moves vertices in its image plane only."""
    cfg = _cfg(**{"coarse.steps": 15, "motion.warmup_steps": 0, "motion.steps": 0})
    data = prepare_data(tiny_sequence, cfg, tmp_path, torch.device("cpu"))
    f = Fitter(data, coarse_model(data, cfg), cfg, tmp_path, torch.device("cpu"))
    v0 = f.model.verts.detach().clone()
    f.run()
    v1 = f.model.verts.detach()
    assert (v1[:, :2] - v0[:, :2]).abs().max() > 1e-3  # the silhouette moved them
    dz = float((v1[:, 2] - v0[:, 2]).abs().max())
    assert dz == 0.0, dz
    # the relative Laplacian is zero at its reference shape and grows with a bumpy change
    from s3o_warp.kernels.regularisers import laplacian_loss

    assert float(laplacian_loss(v1 - v1, f.model.faces)) == 0.0
    assert float(laplacian_loss(torch.randn_like(v1) * 0.01, f.model.faces)) > 0


def test_canonical_frame_setting_picks_the_lifted_frame(tiny_sequence, tmp_path):
    """coarse.canonical_frame overrides the automatic choice (the lift and the anchor of the fit follow it);
    a frame outside the sequence is one ConfigError naming the setting."""
    from s3o_warp.coarse.model import coarse_model
    from s3o_warp.data.store import prepare_data

    cfg = smoke_config()
    data = prepare_data(tiny_sequence, cfg, tmp_path, torch.device("cpu"))
    auto = coarse_model(data, cfg).canonical
    forced = (auto + 3) % data.num_frames
    res = coarse_model(data, smoke_config(**{"coarse.canonical_frame": forced}))
    assert res.canonical == forced != auto
    with pytest.raises(ConfigError, match="coarse.canonical_frame=8"):  # refused before the flow is computed
        prepare_data(tiny_sequence, smoke_config(**{"coarse.canonical_frame": data.num_frames}), tmp_path / "x",
                     torch.device("cpu"))
    assert not (tmp_path / "x").exists()
