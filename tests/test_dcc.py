"""A real DCC client: Blender (``bpy``, the optional ``dcc`` extra) imports the exported USD and glb
headless; the armature, the skin binding, the frame range, the deformed mesh at two frames and the
USD camera's view are checked against the project's own posed vertices and projection.

Blender runs in a child process (``python tests/test_dcc.py usd|glb FILE``), so the test session
itself never loads bpy. Blender converts Y-up files to its Z-up world on import:
Blender (x, y, z) = (x, -z, y) of the file.
"""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from test_export import chain_rig, two_bone_rig  # noqa: E402

from s3o_warp.export import Rig, export_gltf, export_usd  # noqa: E402

pytestmark = [
    pytest.mark.dcc,
    pytest.mark.skipif(
        importlib.util.find_spec("bpy") is None,
        reason="Blender as a Python module is absent: pip install -e '.[dcc]' (bpy 5.0.1)",
    ),
]

Z_UP_FROM_Y_UP = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])


def square_pixel_rig() -> Rig:
    """The two-bone clip with fy = fx in every frame (Blender cameras have square pixels), while the
    focal length and the principal point still change per frame."""
    rig = two_bone_rig()
    fields = {k: getattr(rig, k) for k in rig.__dataclass_fields__}
    k = rig.K.copy()
    k[:, 1, 1] = k[:, 0, 0]
    fields["K"] = k
    return Rig(**fields)


def evaluated_world_points(obj) -> np.ndarray:
    """(N, 3) world coordinates of ``obj``'s evaluated (deformed) mesh at the current frame."""
    import bpy

    dg = bpy.context.evaluated_depsgraph_get()
    ev = obj.evaluated_get(dg)
    me = ev.to_mesh()
    co = np.empty(len(me.vertices) * 3)
    me.vertices.foreach_get("co", co)
    m = np.array(ev.matrix_world)
    ev.to_mesh_clear()
    return co.reshape(-1, 3) @ m[:3, :3].T + m[:3, 3]


def check_rigged_import(rig: Rig, frames=(3, 8)):
    """Common checks after an import: one armature with B bones + root, the mesh bound to it, and
    the deformed mesh at two frames on the posed vertices. Returns the mesh object."""
    import bpy

    arms = [o for o in bpy.data.objects if o.type == "ARMATURE"]
    assert len(arms) == 1
    assert len(arms[0].data.bones) == rig.num_bones + 1 and "root" in arms[0].data.bones
    mesh = next(o for o in bpy.data.objects if o.type == "MESH" and len(o.data.vertices) == len(rig.verts))
    mods = [m for m in mesh.modifiers if m.type == "ARMATURE"]
    assert len(mods) == 1 and mods[0].object == arms[0]
    assert set(mesh.vertex_groups.keys()) >= set(rig.joint_names())
    assert len(mesh.data.color_attributes) >= 1
    tol = 1e-4 * rig.bbox_diagonal()
    for f in frames:
        bpy.context.scene.frame_set(f)
        got = evaluated_world_points(mesh)
        want = rig.posed_world(f) @ Z_UP_FROM_Y_UP.T
        assert np.abs(got - want).max() < tol, (f, np.abs(got - want).max())
    rest = rig.posed_world(0) @ Z_UP_FROM_Y_UP.T
    assert np.abs(rest - rig.posed_world(frames[1]) @ Z_UP_FROM_Y_UP.T).max() > 100 * tol  # the frames differ
    return mesh


def blender_usd(path: str) -> None:
    """In Blender: import the USD of :func:`square_pixel_rig` and check it (raises on a mismatch)."""
    import bpy
    from bpy_extras.object_utils import world_to_camera_view
    from mathutils import Vector

    rig = square_pixel_rig()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    assert bpy.ops.wm.usd_import(filepath=str(path)) == {"FINISHED"}
    scene = bpy.context.scene
    assert (scene.frame_start, scene.frame_end) == (0, rig.num_frames - 1)
    mesh = check_rigged_import(rig)
    # looking through the imported camera, the mesh lands where the fit projects it
    h, w = rig.image_size
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = w, h, 100
    cam = next(o for o in bpy.data.objects if o.type == "CAMERA")
    proj = rig.project()
    for f in (0, 9):
        scene.frame_set(f)
        pts = evaluated_world_points(mesh)
        cam_eval = cam.evaluated_get(bpy.context.evaluated_depsgraph_get())
        uv = np.array([tuple(world_to_camera_view(scene, cam_eval, Vector(p)))[:2] for p in pts])
        px = np.stack([uv[:, 0] * w - 0.5, (1 - uv[:, 1]) * h - 0.5], 1)
        assert np.abs(px - proj[f]).max() < 0.5


def blender_glb(path: str) -> None:
    """In Blender: import the glb of :func:`chain_rig` and check it (raises on a mismatch)."""
    import bpy

    rig = chain_rig()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.context.scene.render.fps = int(rig.fps)  # glTF keys are seconds; Blender maps them with the scene fps
    assert bpy.ops.import_scene.gltf(filepath=str(path)) == {"FINISHED"}
    arm = next(o for o in bpy.data.objects if o.type == "ARMATURE")
    assert tuple(arm.animation_data.action.frame_range) == (0.0, rig.num_frames - 1.0)
    # glTF keeps the top 4 of 6 influences: compare with the pruned skinning the file holds
    from s3o_warp.export.rig import dense_weights, top_k_weights

    fields = {k: getattr(rig, k) for k in rig.__dataclass_fields__}
    fields["weights"] = dense_weights(*top_k_weights(rig.weights, 4), rig.num_bones)
    check_rigged_import(Rig(**fields), frames=(2, 5))


def run_blender(kind: str, path: Path) -> None:
    proc = subprocess.run([sys.executable, __file__, kind, str(path)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "BLENDER CHECKS PASSED" in proc.stdout


def test_blender_imports_usd(tmp_path):
    run_blender("usd", export_usd(square_pixel_rig(), tmp_path / "clip.usdc").path)


def test_blender_imports_glb(tmp_path):
    run_blender("glb", export_gltf(chain_rig(), tmp_path / "clip.glb").path)


if __name__ == "__main__":
    {"usd": blender_usd, "glb": blender_glb}[sys.argv[1]](sys.argv[2])
    print("BLENDER CHECKS PASSED")
