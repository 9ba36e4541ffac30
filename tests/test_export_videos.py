"""glTF export of one object fitted to several videos: one mesh and skin, and per video a camera node and an
animation, each animation re-evaluated with the spec's skinning from the file (pygltflib, numpy) and, when bpy is
importable, imported by Blender (``python tests/test_export_videos.py FILE`` runs the Blender side)."""

from __future__ import annotations

import dataclasses
import importlib.util
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pygltflib
import pytest
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).parent))
from test_export import (  # noqa: E402
    chain_rig,
    fit_like_rig,
    glb_camera_project,
    gltf_evaluate,
    read_accessor,
    two_bone_rig,
)

from s3o_warp.errors import InputError  # noqa: E402
from s3o_warp.export.gltf import export_gltf, export_gltf_videos  # noqa: E402
from s3o_warp.export.rig import top_k_error  # noqa: E402

NAMES = ["walk", "trot"]


def reversed_video(rig, fps: float):
    """``rig`` with its bone motion played backwards, at ``fps``."""
    return dataclasses.replace(rig, bone_motion=rig.bone_motion[::-1], fps=fps)


def videos():
    """Two videos of the bent cylinder: 5 frames at 12 fps in 192x144 (focal and principal point change per frame)
    and 7 frames at 25 fps in 320x240 bending back (the motion reversed), a different root path and principal point."""
    return [two_bone_rig(T=5), reversed_video(fit_like_rig(T=7), 25.0)]


def animation_first(path: Path, i: int, out: Path) -> Path:
    """A copy of the glb at ``path`` with its animation i moved first (the one :func:`gltf_evaluate` plays)."""
    gltf = pygltflib.GLTF2().load(str(path))
    gltf.animations.insert(0, gltf.animations.pop(i))
    gltf.save_binary(str(out))
    return out


def test_each_animation_skins_and_films_its_video(tmp_path):
    rigs = videos()
    assert np.abs(rigs[0].posed_world(0) - rigs[1].posed_world(0)).max() > 0.1  # the videos' poses differ
    report = export_gltf_videos(rigs, NAMES, tmp_path / "two.glb")
    gltf = pygltflib.GLTF2().load(str(report.path))
    blob = gltf.binary_blob()
    assert [a.name for a in gltf.animations] == NAMES
    assert len(gltf.meshes) == 1 and len(gltf.skins) == 1
    cam_nodes = {n.name: i for i, n in enumerate(gltf.nodes) if n.camera is not None}
    assert sorted(cam_nodes) == ["camera_trot", "camera_walk"]
    assert [v["fps"] for v in gltf.extras["videos"]] == [12.0, 25.0]
    worst = []
    for i, (rig, name) in enumerate(zip(rigs, NAMES)):
        anim, node = gltf.animations[i], cam_nodes[f"camera_{name}"]
        # its joints and its own camera, frame k at k / fps of its video
        assert {ch.target.node for ch in anim.channels} == set(range(rig.num_bones + 1)) | {node}
        for smp in anim.samplers:
            times = read_accessor(gltf, blob, smp.input)
            np.testing.assert_allclose(times, np.arange(rig.num_frames) / rig.fps, atol=1e-6)
        persp = gltf.cameras[gltf.nodes[node].camera].perspective
        h, w = rig.image_size
        assert persp.aspectRatio == pytest.approx(w / h)
        assert persp.yfov == pytest.approx(2 * np.arctan(h / (2 * np.median(rig.K[:, 1, 1]))))
        one = animation_first(report.path, i, tmp_path / f"{name}.glb")
        tol = 1e-4 * rig.bbox_diagonal()
        c2w, proj, px = rig.camera_to_world(), rig.project(), 0.0
        camera = types.SimpleNamespace(cameras=[gltf.cameras[gltf.nodes[node].camera]])
        for t in range(rig.num_frames):
            pts, world, _ = gltf_evaluate(one, t / rig.fps)
            np.testing.assert_allclose(pts, rig.posed_world(t), atol=tol, rtol=0)
            cam = world[f"camera_{name}"]
            assert np.linalg.norm(cam[:3, 3] - c2w[t][:3, 3]) < 0.2 * np.linalg.norm(c2w[t][:3, 3])
            assert np.degrees(Rotation.from_matrix(cam[:3, :3].T @ c2w[t][:3, :3]).magnitude()) < 10
            px = max(px, np.linalg.norm(glb_camera_project(camera, cam, pts, rig.image_size) - proj[t], axis=1).max())
        assert px < 2.0, (name, px)
        worst.append(px)
    assert abs(worst[0] - worst[1]) > 0.1
    assert report.camera_px_error == pytest.approx(max(worst), abs=0.01)  # the worst video's


def test_report_holds_the_worst_video(tmp_path):
    """A still first video (rest pose: 4 influences are exact) and a moving second one (they are not)."""
    still = chain_rig(T=5)
    still = dataclasses.replace(still, bone_motion=np.broadcast_to(np.eye(4), still.bone_motion.shape).copy())
    rigs = [still, reversed_video(chain_rig(T=7), 30.0)]
    report = export_gltf_videos(rigs, NAMES, tmp_path / "chain.glb")
    errs = [top_k_error(r, 4) for r in rigs]
    assert errs[0][0] < 1e-6 < errs[1][0]
    assert report.influences == 4
    assert report.topk_error == pytest.approx(max(e[0] for e in errs))
    assert report.topk_error_rel == pytest.approx(max(e[1] for e in errs))


def test_one_video_is_export_gltf(tmp_path):
    rig = two_bone_rig(T=5)
    single = pygltflib.GLTF2().load(str(export_gltf(rig, tmp_path / "a.glb").path))
    one = pygltflib.GLTF2().load(str(export_gltf_videos([rig], ["walk"], tmp_path / "b.glb").path))
    assert single.binary_blob() == one.binary_blob()
    assert [n.name for n in one.nodes] == [n.name for n in single.nodes][:-1] + ["camera_walk"]
    assert [a.name for a in single.animations] == ["Motion"] and [a.name for a in one.animations] == ["walk"]


@pytest.mark.parametrize(
    "change, names, match",
    [
        ({"faces": two_bone_rig(T=3).faces[:, ::-1]}, NAMES, "Rig.faces of video 'trot' differs"),
        ({"weights": two_bone_rig(T=3).weights[:, ::-1]}, NAMES, "Rig.weights"),
        ({"bone_names": ["a", "b"]}, NAMES, "Rig.bone_names"),
        ({}, ["walk", "walk"], "unique"),
        ({}, ["walk", ""], "non-empty"),
        ({}, ["walk"], "one name per video"),
    ],
)
def test_videos_of_different_objects_or_bad_names_are_refused(tmp_path, change, names, match):
    rigs = videos()
    rigs[1] = dataclasses.replace(rigs[1], **change)
    with pytest.raises(InputError, match=match) as info:
        export_gltf_videos(rigs, names, tmp_path / "x.glb")
    assert "\n" not in str(info.value)
    assert list(tmp_path.iterdir()) == []


def test_videos_need_a_rig_and_the_glb_extension(tmp_path):
    with pytest.raises(InputError, match="at least one video"):
        export_gltf_videos([], [], tmp_path / "x.glb")
    with pytest.raises(InputError, match=r"\.glb"):
        export_gltf_videos(videos(), NAMES, tmp_path / "x.gltf")


# ----------------------------------------------------------------------------- Blender
def blender_actions(path: str) -> None:
    """In Blender: import the glb of :func:`videos` and check one action per video (raises on a mismatch)."""
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)
    fps = bpy.context.scene.render.fps / bpy.context.scene.render.fps_base
    assert bpy.ops.import_scene.gltf(filepath=str(path)) == {"FINISHED"}
    actions = {a.name: a for a in bpy.data.actions}
    assert sorted(actions) == sorted(NAMES), sorted(actions)
    for rig, name in zip(videos(), NAMES):
        action = actions[name]
        assert action.frame_range[0] == 0.0
        assert action.frame_range[1] == pytest.approx((rig.num_frames - 1) / rig.fps * fps, abs=1e-3), name
        assert {s.identifier for s in action.slots} == {"OBSkeleton", f"OBcamera_{name}"}


@pytest.mark.dcc
@pytest.mark.skipif(
    importlib.util.find_spec("bpy") is None,
    reason="Blender as a Python module is absent: pip install -e '.[dcc]' (bpy 5.0.1)",
)
def test_blender_lists_one_action_per_video(tmp_path):
    path = export_gltf_videos(videos(), NAMES, tmp_path / "two.glb").path
    proc = subprocess.run([sys.executable, __file__, str(path)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "BLENDER CHECKS PASSED" in proc.stdout


if __name__ == "__main__":
    blender_actions(sys.argv[1])
    print("BLENDER CHECKS PASSED")
