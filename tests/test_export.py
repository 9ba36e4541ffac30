"""Rigged, animated export: the Rig contract, USD (UsdSkel's own skinning, Gf.Camera projection,
UsdValidation), baked USD, glTF (re-evaluated with the spec's formula in numpy), run-directory round
trip, atomic writes and the export script."""

from __future__ import annotations

import importlib.util
import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from s3o_warp.errors import InputError
from s3o_warp.export import (
    Rig,
    camera_apertures,
    export_gltf,
    export_usd,
    load_rig,
    save_rig,
    top_k_error,
)
from s3o_warp.export import usd as usd_mod
from s3o_warp.export.rig import dense_weights, top_k_weights

pxr = pytest.importorskip("pxr")
from pxr import Usd, UsdGeom, UsdSkel, UsdValidation  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


# ----------------------------------------------------------------------------- hand-made rigs
def rigid(rotvec=(0, 0, 0), t=(0, 0, 0)) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    m[:3, 3] = t
    return m


def cylinder(n_len=17, n_ring=12, radius=0.2):
    x = np.linspace(-1.0, 1.0, n_len)
    a = np.linspace(0, 2 * np.pi, n_ring, endpoint=False)
    xx, aa = np.meshgrid(x, a, indexing="ij")
    verts = np.stack([xx, radius * np.cos(aa), radius * np.sin(aa)], -1).reshape(-1, 3)
    faces = []
    for i in range(n_len - 1):
        for j in range(n_ring):
            p, q = i * n_ring + j, i * n_ring + (j + 1) % n_ring
            faces += [[p, p + n_ring, q], [q, p + n_ring, q + n_ring]]
    return verts, np.array(faces)


def bend(theta: float) -> np.ndarray:
    """Rotation by theta about the object z axis through the origin (the cylinder's middle)."""
    c, s = np.cos(theta), np.sin(theta)
    m = np.eye(4)
    m[:2, :2] = [[c, -s], [s, c]]
    return m


def bent_cylinder_rig(T: int, root_at, K_at, image_size) -> Rig:
    """A cylinder along x bent at its middle over T frames: vertices with x <= -0.25 follow bone 0 (a small drift),
    x >= 0.25 follow bone 1 (bend by 1.2 s rad about z, s = t/(T-1)), a linear ramp in between; the root and the
    intrinsics of frame t are ``root_at(s)`` and ``K_at(t, s)``."""
    verts, faces = cylinder()
    w1 = np.clip((verts[:, 0] + 0.25) / 0.5, 0, 1)
    motion, root, K = [], [], []
    for t in range(T):
        s = t / (T - 1)
        motion.append([rigid((0, 0.2 * s, 0), (0.0, -0.05 * s, 0)), bend(1.2 * s)])
        root.append(root_at(s))
        K.append(K_at(t, s))
    return Rig(
        verts=verts, faces=faces, colors=np.clip(0.5 + verts / 2, 0, 1), weights=np.stack([1 - w1, w1], 1),
        bone_names=["bone_00", "bone_01"], parents=np.array([-1, 0]),
        bind=np.stack([rigid((0, 0, 0.3), (-0.5, 0, 0)), rigid((0.2, 0, 0), (0.5, 0, 0))]),
        bone_motion=np.array(motion), root=np.array(root), K=np.array(K, float), image_size=image_size, fps=12.0,
    )


def two_bone_rig(T=10) -> Rig:
    """:func:`bent_cylinder_rig` with a moving root and a per-frame K (focal lengths and principal point)."""
    return bent_cylinder_rig(
        T, lambda s: rigid((0.1 * s, 0.6 * s, 0.05), (0.1 * s, -0.05, 4.0 + 0.5 * s)),
        lambda t, s: [[300 + 10 * t, 0, 95 + t], [0, 310 + 8 * t, 70 - 0.5 * t], [0, 0, 1]], (144, 192))


def chain_rig(T=6) -> Rig:
    """Six bones with soft Gaussian weights (so 4 influences are an approximation), two roots and
    a parent list that is not in parent-first order."""
    verts, faces = cylinder(n_len=25)
    b = 6
    centres = np.stack([np.linspace(-0.9, 0.9, b), np.zeros(b), np.zeros(b)], 1)
    logits = -0.5 * ((verts[:, None, 0] - centres[None, :, 0]) / 0.35) ** 2
    w = np.exp(logits - logits.max(1, keepdims=True))
    w /= w.sum(1, keepdims=True)
    rng = np.random.default_rng(3)
    bind = np.stack([rigid(rng.normal(size=3) * 0.5, c) for c in centres])
    motion = [[rigid(rng.normal(size=3) * 0.3 * (t > 0), rng.normal(size=3) * 0.05 * (t > 0)) for _ in range(b)] for t in range(T)]
    root = [rigid((0, 0.3 * t, 0), (0, 0, 5.0)) for t in range(T)]
    K = [[[250.0, 0, 79.5], [0, 250.0, 59.5], [0, 0, 1]]] * T  # centred: W/2 - 0.5, H/2 - 0.5
    return Rig(
        verts=verts, faces=faces, colors=np.full((len(verts), 3), 0.7), weights=w,
        bone_names=[f"bone {i}" for i in range(b)], parents=np.array([1, -1, 1, 4, -1, 3]), bind=bind,
        bone_motion=np.array(motion), root=np.array(root), K=np.array(K), image_size=(120, 160), fps=25.0,
        joints=np.array([[-0.54, 0, 0], [0.18, 0, 0]]), joint_pairs=np.array([[0, 1], [2, 3]]),
        centres=centres, precisions=np.stack([np.eye(3) * 4] * b), lengths=np.full(b, 0.36),
    )


# ----------------------------------------------------------------------------- readers (twins)
def usd_skinned_world(stage, t) -> np.ndarray:
    """UsdSkel's own skinning of /World/Character/Mesh at time t, in world coordinates."""
    cache = UsdSkel.Cache()
    cache.Populate(UsdSkel.Root(stage.GetPrimAtPath("/World/Character")), Usd.PrimDefaultPredicate)
    skel_query = cache.GetSkelQuery(UsdSkel.Skeleton(stage.GetPrimAtPath("/World/Character/Skel")))
    mesh = stage.GetPrimAtPath("/World/Character/Mesh")
    pts = UsdGeom.Mesh(mesh).GetPointsAttr().Get(t)
    assert cache.GetSkinningQuery(mesh).ComputeSkinnedPoints(skel_query.ComputeSkinningTransforms(t), pts, t)
    m = np.array(UsdGeom.Xformable(mesh).ComputeLocalToWorldTransform(t))  # row-vector convention
    return np.array(pts, dtype=np.float64) @ m[:3, :3] + m[3, :3]


def gf_camera_project(stage, t, points_world, image_size) -> np.ndarray:
    """Pixels (column, row; OpenCV centres) of world points through the file's camera via Gf.Camera."""
    h, w = image_size
    frustum = UsdGeom.Camera(stage.GetPrimAtPath("/World/Camera")).GetCamera(t).frustum
    vp = np.array(frustum.ComputeViewMatrix()) @ np.array(frustum.ComputeProjectionMatrix())
    clip = np.concatenate([points_world, np.ones((len(points_world), 1))], 1) @ vp
    ndc = clip[:, :2] / clip[:, 3:]
    return np.stack([(ndc[:, 0] + 1) * w / 2 - 0.5, (1 - ndc[:, 1]) * h / 2 - 0.5], 1)


def validation_errors(stage) -> list[str]:
    ctx = UsdValidation.ValidationContext(UsdValidation.ValidationRegistry().GetOrLoadAllValidators())
    return [
        f"{e.GetName()}: {e.GetMessage()}" for e in ctx.Validate(stage) if e.GetType() == UsdValidation.ValidationErrorType.Error
    ]


def read_accessor(gltf, blob: bytes, i: int) -> np.ndarray:
    acc = gltf.accessors[i]
    view = gltf.bufferViews[acc.bufferView]
    dtype = {5126: np.float32, 5123: np.uint16, 5125: np.uint32, 5121: np.uint8}[acc.componentType]
    width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}[acc.type]
    assert view.byteStride in (None, 0, width * np.dtype(dtype).itemsize)
    start = (view.byteOffset or 0) + (acc.byteOffset or 0)
    a = np.frombuffer(blob, dtype=dtype, count=acc.count * width, offset=start)
    return a.reshape(acc.count, width) if width > 1 else a


def trs(t, q) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = Rotation.from_quat(q).as_matrix()  # glTF quaternions are x, y, z, w
    m[:3, 3] = t
    return m


def gltf_evaluate(path, time_s):
    """The glTF 2.0 spec's skinning, evaluated from the file at time time_s (seconds).

    Returns (skinned world points (N, 3), {node name: world matrix}).
    """
    import pygltflib

    gltf = pygltflib.GLTF2().load(str(path))
    blob = gltf.binary_blob()
    local = {}
    for i, node in enumerate(gltf.nodes):
        local[i] = [np.array(node.translation or [0, 0, 0], float), np.array(node.rotation or [0, 0, 0, 1], float)]
    for ch in gltf.animations[0].channels:
        smp = gltf.animations[0].samplers[ch.sampler]
        assert smp.interpolation == "LINEAR"
        times = read_accessor(gltf, blob, smp.input)
        vals = read_accessor(gltf, blob, smp.output).astype(np.float64)
        k = int(np.clip(np.searchsorted(times, time_s, side="right") - 1, 0, len(times) - 1))
        k1 = min(k + 1, len(times) - 1)
        a = 0.0 if k1 == k else (time_s - times[k]) / (times[k1] - times[k])
        if ch.target.path == "translation":
            local[ch.target.node][0] = (1 - a) * vals[k] + a * vals[k1]
        else:
            from scipy.spatial.transform import Slerp

            local[ch.target.node][1] = Slerp([0, 1], Rotation.from_quat(vals[[k, k1]]))(a).as_quat()
    world = {}

    def visit(i, parent):
        world[i] = parent @ trs(*local[i])
        for c in gltf.nodes[i].children or []:
            visit(c, world[i])

    for i in gltf.scenes[gltf.scene].nodes:
        visit(i, np.eye(4))
    mesh_node = next(i for i, n in enumerate(gltf.nodes) if n.skin is not None)
    skin = gltf.skins[gltf.nodes[mesh_node].skin]
    ibm = read_accessor(gltf, blob, skin.inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1)  # column-major
    joint_mats = np.stack([np.linalg.inv(world[mesh_node]) @ world[j] @ ibm[n] for n, j in enumerate(skin.joints)])
    prim = gltf.meshes[gltf.nodes[mesh_node].mesh].primitives[0]
    pos = read_accessor(gltf, blob, prim.attributes.POSITION).astype(np.float64)
    jts = read_accessor(gltf, blob, prim.attributes.JOINTS_0).astype(np.int64)
    wts = read_accessor(gltf, blob, prim.attributes.WEIGHTS_0).astype(np.float64)
    skin_m = np.einsum("nk,nkij->nij", wts, joint_mats[jts])
    pts = np.einsum("nij,nj->ni", skin_m[:, :3, :3], pos) + skin_m[:, :3, 3]
    pts = pts @ world[mesh_node][:3, :3].T + world[mesh_node][:3, 3]
    return pts, {gltf.nodes[i].name: m for i, m in world.items()}, gltf


# ----------------------------------------------------------------------------- the Rig itself
def test_two_bone_posed_vertices_are_the_analytic_answer():
    rig = two_bone_rig()
    x = rig.verts.astype(np.float64)
    left, right = x[:, 0] <= -0.25, x[:, 0] >= 0.25
    cam = rig.posed_camera()
    for t in (0, 4, 9):
        s = t / 9
        th = 1.2 * s
        r1 = np.array([[np.cos(th), -np.sin(th), 0], [np.sin(th), np.cos(th), 0], [0, 0, 1]])
        posed = rig.posed_object(t)
        np.testing.assert_allclose(posed[right], x[right] @ r1.T, atol=1e-12)
        r0 = Rotation.from_rotvec([0, 0.2 * s, 0]).as_matrix()
        np.testing.assert_allclose(posed[left], x[left] @ r0.T + [0, -0.05 * s, 0], atol=1e-12)
        root = rigid((0.1 * s, 0.6 * s, 0.05), (0.1 * s, -0.05, 4.0 + 0.5 * s))
        np.testing.assert_allclose(cam[t], posed @ root[:3, :3].T + root[:3, 3], atol=1e-12)
        fx, fy, cx, cy = 300 + 10 * t, 310 + 8 * t, 95 + t, 70 - 0.5 * t
        uv = np.stack([fx * cam[t, :, 0] / cam[t, :, 2] + cx, fy * cam[t, :, 1] / cam[t, :, 2] + cy], 1)
        np.testing.assert_allclose(rig.project()[t], uv, atol=1e-9)
    assert rig.joint_paths() == ["root/bone_00", "root/bone_00/bone_01"]


def test_top_k_weights_and_error_against_dense_reference():
    rig = chain_rig()
    idx, val = top_k_weights(rig.weights, 2)
    np.testing.assert_allclose(val.sum(1), 1.0, atol=1e-12)
    assert (np.take_along_axis(rig.weights, idx, 1)[:, 0] == rig.weights.max(1)).all()
    dense = dense_weights(idx, val, rig.num_bones)
    want = max(np.linalg.norm(rig.posed_object(t) - rig.posed_object(t, dense), axis=1).max() for t in range(rig.num_frames))
    err, rel = top_k_error(rig, 2)
    assert err == pytest.approx(want) and err > 1e-3
    assert rel == pytest.approx(err / rig.bbox_diagonal())
    assert top_k_error(rig, rig.num_bones)[0] < 1e-6  # float32 weights renormalised in float64


@pytest.mark.parametrize(
    "change, match",
    [
        ({"parents": np.array([1, 0])}, "cycle"),
        ({"weights": np.full((204, 2), 0.3)}, "sum to 1"),
        ({"bind": np.stack([np.diag([2.0, 1, 1, 1]), np.eye(4)])}, "rigid"),
        ({"K": np.tile([[300.0, 5, 90], [0, 300, 70], [0, 0, 1]], (10, 1, 1))}, "skew"),
        ({"bone_names": ["a"]}, "one name per bone"),
        ({"image_size": (0, 10)}, "image_size"),
        ({"colors": np.zeros((3, 3))}, r"colors: must have shape \(204, 3\)"),
    ],
)
def test_rig_rejects_bad_input_with_one_line(change, match):
    rig = two_bone_rig()
    fields = {k: getattr(rig, k) for k in rig.__dataclass_fields__}
    fields.update(change)
    with pytest.raises(InputError, match=match) as info:
        Rig(**fields)
    assert "\n" not in str(info.value)


# ----------------------------------------------------------------------------- USD
@pytest.mark.parametrize("ext", [".usda", ".usdc"])
def test_usd_skinning_camera_and_validation(tmp_path, ext):
    rig = two_bone_rig()
    report = export_usd(rig, tmp_path / f"two_bone{ext}", influences=rig.num_bones)
    assert report.topk_error == 0.0
    stage = Usd.Stage.Open(str(report.path))
    tol = 1e-4 * rig.bbox_diagonal()
    proj = rig.project()
    for t in range(rig.num_frames):
        world = usd_skinned_world(stage, t)
        np.testing.assert_allclose(world, rig.posed_world(t), atol=tol, rtol=0)
        px = gf_camera_project(stage, t, world, rig.image_size)
        assert np.abs(px - proj[t]).max() < 0.5
    assert validation_errors(stage) == []


def test_usd_camera_attributes_follow_the_aperture_formulas(tmp_path):
    rig = two_bone_rig()
    stage = Usd.Stage.Open(str(export_usd(rig, tmp_path / "c.usda").path))
    cam = UsdGeom.Camera(stage.GetPrimAtPath("/World/Camera"))
    h, w = rig.image_size
    for t in (0, 7):
        fx, fy, cx, cy = rig.K[t, 0, 0], rig.K[t, 1, 1], rig.K[t, 0, 2], rig.K[t, 1, 2]
        f, hap, vap = cam.GetFocalLengthAttr().Get(t), cam.GetHorizontalApertureAttr().Get(t), cam.GetVerticalApertureAttr().Get(t)
        assert hap == pytest.approx(w * f / fx, rel=1e-5) and vap == pytest.approx(h * f / fy, rel=1e-5)
        assert cam.GetHorizontalApertureOffsetAttr().Get(t) == pytest.approx((w / 2 - 0.5 - cx) * hap / w, abs=1e-5)
        assert cam.GetVerticalApertureOffsetAttr().Get(t) == pytest.approx((cy + 0.5 - h / 2) * vap / h, abs=1e-5)
        assert camera_apertures(rig.K[t], rig.image_size)["focalLength"] == pytest.approx(f, rel=1e-6)
        # the camera's transform: world_from_object @ inv(root) @ diag(1, -1, -1, 1), stored row-vector
        m = np.array(cam.GetCamera(t).transform).T
        np.testing.assert_allclose(m, rig.camera_to_world()[t], atol=1e-6)


def fit_like_rig(T=12) -> Rig:
    """The fit's camera: one focal length (fx = fy) and a principal point per frame that follows the object across
    a 320x240 frame (each crop's centre, up to 36 px off the image centre, the most measured on a fitted clip), the
    object (about 160 px long) on its optical axis."""
    return bent_cylinder_rig(
        T, lambda s: rigid((0.1 * s, 0.6 * s, 0.05), (0.02 * s, -0.03, 4.2 + 0.5 * s)),
        lambda t, s: [[350.0, 0, 159.5 - 36 + 72 * s], [0, 350.0, 119.5 + 20 * np.sin(3 * s)], [0, 0, 1]], (240, 320))


def glb_camera_project(gltf, camera_world: np.ndarray, points_world, image_size) -> np.ndarray:
    """Pixels (column, row; OpenCV centres) of world points through a glb's perspective camera (the spec's: square
    pixels, centred, looking down -Z with +Y up) whose node has the world matrix ``camera_world``."""
    h, w = image_size
    persp = gltf.cameras[0].perspective
    assert persp.aspectRatio == pytest.approx(w / h)
    f = h / 2 / np.tan(persp.yfov / 2)
    x = (points_world - camera_world[:3, 3]) @ camera_world[:3, :3]  # GL camera frame
    return np.stack([f * x[:, 0] / -x[:, 2] + w / 2 - 0.5, -f * x[:, 1] / -x[:, 2] + h / 2 - 0.5], 1)


def test_glb_camera_within_two_pixels_of_the_usd_camera(tmp_path):
    """Both files read back (usd-core, pygltflib): the glb's camera shows UsdSkel's posed vertices within 2 px of
    where the USD camera shows them, on a clip whose principal point wanders 36 px off the image centre."""
    rig = fit_like_rig()
    stage = Usd.Stage.Open(str(export_usd(rig, tmp_path / "r.usda", influences=rig.num_bones).path))
    report = export_gltf(rig, tmp_path / "r.glb")
    worst = worst_unturned = 0.0
    for t in range(rig.num_frames):
        world = usd_skinned_world(stage, t)
        usd_px = gf_camera_project(stage, t, world, rig.image_size)
        _, nodes, gltf = gltf_evaluate(report.path, t / rig.fps)
        glb_px = glb_camera_project(gltf, nodes["Camera"], world, rig.image_size)
        worst = max(worst, np.linalg.norm(glb_px - usd_px, axis=1).max())
        # negative control: the glb's intrinsics with the USD camera's own pose (no turn) miss by far more
        unturned = glb_camera_project(gltf, rig.camera_to_world()[t], world, rig.image_size)
        worst_unturned = max(worst_unturned, np.linalg.norm(unturned - usd_px, axis=1).max())
    assert worst < 2.0, worst
    assert worst_unturned > 20.0, worst_unturned
    assert report.camera_px_error == pytest.approx(worst, abs=0.01)  # the reported error is the file's


def test_usd_stage_metadata_and_hierarchy(tmp_path):
    rig = chain_rig()
    stage = Usd.Stage.Open(str(export_usd(rig, tmp_path / "m.usdc", meters_per_unit=0.01).path))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    assert UsdGeom.GetStageMetersPerUnit(stage) == pytest.approx(0.01)
    assert stage.GetTimeCodesPerSecond() == 25.0
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0, rig.num_frames - 1)
    assert stage.GetDefaultPrim().GetPath() == "/World"
    joints = list(UsdSkel.Skeleton(stage.GetPrimAtPath("/World/Character/Skel")).GetJointsAttr().Get())
    # two roots (bones 1 and 4) go under one "root" joint; names are made path-safe
    assert joints[0] == "root" and len(joints) == rig.num_bones + 1
    assert "root/bone_1/bone_0" in joints and "root/bone_4/bone_3/bone_5" in joints and "root/bone_1/bone_2" in joints
    assert UsdSkel.Topology(joints).Validate()[0]
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Character/Mesh"))
    assert len(mesh.GetDisplayColorPrimvar().Get()) == len(rig.verts)
    assert len(mesh.GetNormalsAttr().Get()) == len(rig.verts) and mesh.GetNormalsInterpolation() == "vertex"
    assert mesh.GetExtentAttr().Get() is not None
    binding = UsdSkel.BindingAPI(mesh.GetPrim())
    assert binding.GetJointIndicesPrimvar().GetElementSize() == 4
    w = np.array(binding.GetJointWeightsPrimvar().Get()).reshape(-1, 4)
    np.testing.assert_allclose(w.sum(1), 1.0, atol=1e-6)


def test_usd_multi_root_and_top_k_influences(tmp_path):
    """With 2 of 6 influences UsdSkel reproduces the pruned skinning exactly and the full skinning
    within the reported approximation error."""
    rig = chain_rig()
    report = export_usd(rig, tmp_path / "chain.usda", influences=2)
    assert report.influences == 2 and report.topk_error == pytest.approx(top_k_error(rig, 2)[0])
    idx, val = top_k_weights(rig.weights, 2)
    dense = dense_weights(idx, val, rig.num_bones)
    stage = Usd.Stage.Open(str(report.path))
    tol = 1e-4 * rig.bbox_diagonal()
    worst = 0.0
    for t in range(rig.num_frames):
        world = usd_skinned_world(stage, t)
        np.testing.assert_allclose(world, rig.posed_world(t, dense), atol=tol, rtol=0)
        worst = max(worst, np.linalg.norm(world - rig.posed_world(t), axis=1).max())
    assert report.topk_error - tol < worst < report.topk_error + tol
    assert validation_errors(stage) == []
    exact = export_usd(rig, tmp_path / "chain_full.usdc", influences=99)
    assert exact.influences == rig.num_bones
    stage = Usd.Stage.Open(str(exact.path))
    for t in range(rig.num_frames):
        np.testing.assert_allclose(usd_skinned_world(stage, t), rig.posed_world(t), atol=tol, rtol=0)


def test_usd_baked_points(tmp_path):
    rig = two_bone_rig()
    stage = Usd.Stage.Open(str(export_usd(rig, tmp_path / "baked.usdc", baked=True).path))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Mesh"))
    assert not stage.GetPrimAtPath("/World/Character")
    proj = rig.project()
    for t in range(rig.num_frames):
        pts = np.array(mesh.GetPointsAttr().Get(t), dtype=np.float64)
        np.testing.assert_allclose(pts, rig.posed_world(t), atol=1e-5 * rig.bbox_diagonal(), rtol=0)
        ext = np.array(mesh.GetExtentAttr().Get(t))
        np.testing.assert_allclose(ext, [pts.min(0), pts.max(0)], atol=1e-6)
        assert np.abs(gf_camera_project(stage, t, pts, rig.image_size) - proj[t]).max() < 0.5
    assert validation_errors(stage) == []


def test_usd_validation_negative_control(tmp_path):
    """The validators do fire: no metadata, and a mesh pointing at a skeleton without BindingAPI."""
    stage = Usd.Stage.CreateInMemory()
    UsdSkel.Root.Define(stage, "/Character")
    skel = UsdSkel.Skeleton.Define(stage, "/Character/Skel")
    skel.CreateJointsAttr(["root"])
    mesh = UsdGeom.Mesh.Define(stage, "/Character/Mesh")
    mesh.GetPrim().CreateRelationship("skel:skeleton").SetTargets([skel.GetPath()])
    errors = " ".join(validation_errors(stage))
    assert "MissingUpAxisMetadata" in errors and "MissingDefaultPrim" in errors
    assert "MissingSkelBindingAPI" in errors


def test_usd_and_gltf_reject_bad_arguments(tmp_path):
    rig = two_bone_rig()
    with pytest.raises(InputError, match=r"\.usda, \.usdc or \.usd"):
        export_usd(rig, tmp_path / "x.obj")
    with pytest.raises(InputError, match="influences"):
        export_usd(rig, tmp_path / "x.usda", influences=0)
    with pytest.raises(InputError, match=r"\.glb"):
        export_gltf(rig, tmp_path / "x.gltf")
    with pytest.raises(InputError, match="does not exist"):
        export_usd(rig, tmp_path / "missing" / "x.usda")


# ----------------------------------------------------------------------------- glTF
def test_gltf_two_bone_is_exact_and_camera_follows_root(tmp_path):
    rig = two_bone_rig()
    report = export_gltf(rig, tmp_path / "two_bone.glb")
    tol = 1e-5 * rig.bbox_diagonal()
    c2w = rig.camera_to_world()
    proj, worst = rig.project(), 0.0
    for t in range(rig.num_frames):
        pts, world, gltf = gltf_evaluate(report.path, t / rig.fps)
        np.testing.assert_allclose(pts, rig.posed_world(t), atol=tol, rtol=0)
        # the camera follows the root: near the fit's camera (moved to fold in the intrinsics it cannot store)
        assert np.linalg.norm(world["Camera"][:3, 3] - c2w[t][:3, 3]) < 0.2 * np.linalg.norm(c2w[t][:3, 3])
        assert np.degrees(Rotation.from_matrix(world["Camera"][:3, :3].T @ c2w[t][:3, :3]).magnitude()) < 10
        glb_px = glb_camera_project(gltf, world["Camera"], pts, rig.image_size)
        worst = max(worst, np.linalg.norm(glb_px - proj[t], axis=1).max())
    # halfway between two frames the spec's interpolation stays on the cylinder (no flipped quaternions)
    mid, _, _ = gltf_evaluate(report.path, 4.5 / rig.fps)
    assert np.linalg.norm(mid - 0.5 * (rig.posed_world(4) + rig.posed_world(5)), axis=1).max() < 0.05
    cam = gltf.cameras[0].perspective
    h, w = rig.image_size
    fy = np.median(rig.K[:, 1, 1])
    assert cam.yfov == pytest.approx(2 * np.arctan(h / (2 * fy))) and cam.aspectRatio == pytest.approx(w / h)
    # the camera model error is the file's: its camera's projection against the fit's, read back from the glb
    assert report.camera_px_error == pytest.approx(worst, abs=0.01)
    # with the fit's own pose (fx = fy = median fy, centred principal point) it would be far larger: this clip's K
    # changes focal and principal point per frame, and the moved camera folds most of it in
    cams = rig.posed_camera()
    ideal = np.stack([fy * cams[..., 0] / cams[..., 2] + w / 2 - 0.5, fy * cams[..., 1] / cams[..., 2] + h / 2 - 0.5], -1)
    unfolded = np.linalg.norm(ideal - rig.project(), axis=-1).max()
    assert unfolded > 10.0 and report.camera_px_error < 2.0, (unfolded, report.camera_px_error)
    prim = gltf.meshes[0].primitives[0]
    assert prim.attributes.COLOR_0 is not None and prim.attributes.NORMAL is not None
    blob = gltf.binary_blob()
    jts, wts = read_accessor(gltf, blob, prim.attributes.JOINTS_0), read_accessor(gltf, blob, prim.attributes.WEIGHTS_0)
    assert (jts[wts == 0] == 0).all() and (wts == 0).any()  # unused influence slots point at joint 0
    np.testing.assert_allclose(np.linalg.norm(read_accessor(gltf, blob, prim.attributes.NORMAL), axis=1), 1, atol=1e-5)
    assert [n.name for n in gltf.nodes[: rig.num_bones + 1]] == ["root", "bone_00", "bone_01"]


def test_gltf_four_influences_within_reported_error(tmp_path):
    rig = chain_rig()
    report = export_gltf(rig, tmp_path / "chain.glb")
    assert report.influences == 4
    err4 = top_k_error(rig, 4)[0]
    assert report.topk_error == pytest.approx(err4) and err4 > 1e-5
    idx, val = top_k_weights(rig.weights, 4)
    dense = dense_weights(idx, val, rig.num_bones)
    tol = 1e-5 * rig.bbox_diagonal()
    for t in range(rig.num_frames):
        pts, _, _ = gltf_evaluate(report.path, t / rig.fps)
        np.testing.assert_allclose(pts, rig.posed_world(t, dense), atol=tol, rtol=0)
        assert np.linalg.norm(pts - rig.posed_world(t), axis=1).max() <= err4 + tol
    assert report.camera_px_error < 1e-6  # constant, square, centred intrinsics are exact in glTF


def test_joints_move_like_the_surface_at_their_rest_position():
    import dataclasses

    import torch

    from s3o_warp.reference.skinning import (
        blend_skinning_reference,
        skinning_weights_reference,
    )

    rig = chain_rig()
    t = lambda a: torch.as_tensor(np.asarray(a, np.float64))  # noqa: E731
    w = skinning_weights_reference(t(rig.joints), t(rig.centres), t(rig.precisions))
    ref = blend_skinning_reference(t(rig.joints), w, t(rig.bone_motion[:, :, :3]), t(rig.root[:, :3]))
    np.testing.assert_allclose(rig.joints_camera(), ref.numpy(), atol=1e-9)
    # without the Gaussians: the equal blend of the joint's two bones
    bare = dataclasses.replace(rig, centres=None, precisions=None)
    w2 = torch.zeros(len(rig.joints), rig.num_bones, dtype=torch.float64)
    for j, (a, b) in enumerate(rig.joint_pairs):
        w2[j, a] += 0.5
        w2[j, b] += 0.5
    ref2 = blend_skinning_reference(t(rig.joints), w2, t(rig.bone_motion[:, :, :3]), t(rig.root[:, :3]))
    np.testing.assert_allclose(bare.joints_camera(), ref2.numpy(), atol=1e-9)
    assert np.abs(ref2.numpy() - ref.numpy()).max() > 1e-3  # the two rules differ on this rig


# ----------------------------------------------------------------------------- run directory
def test_save_load_round_trip(tmp_path):
    rig = chain_rig()
    save_rig(tmp_path, rig)
    back = load_rig(tmp_path)
    for name in ("verts", "faces", "colors", "weights", "parents", "bind", "bone_motion", "root", "K", "world_from_object",
                 "joints", "joint_pairs", "centres", "precisions", "lengths"):
        np.testing.assert_allclose(getattr(back, name), getattr(rig, name), atol=1e-6, err_msg=name)
    assert back.bone_names == rig.bone_names and back.frame_names == rig.frame_names
    assert back.image_size == rig.image_size and back.fps == rig.fps
    with np.load(tmp_path / "motion.npz") as z:
        assert z["verts_cam"].dtype == np.float32 and z["faces"].dtype == np.int32
        np.testing.assert_allclose(z["verts_cam"], rig.posed_camera(), atol=1e-5)
        np.testing.assert_allclose(z["joints_cam"], rig.joints_camera(), atol=1e-5)
        assert list(z["image_size"]) == [120, 160] and z["frame_names"].shape == (rig.num_frames,)
    skel = json.loads((tmp_path / "skeleton.json").read_text())
    assert skel["root"] == [1, 4] and skel["bones"][0]["length"] == pytest.approx(0.36)
    assert skel["joints"][1] == {"bones": [2, 3], "position": [0.18, 0.0, 0.0]}
    assert not [p for p in tmp_path.iterdir() if ".tmp-" in p.name]


def test_load_rig_missing_file_is_one_line(tmp_path):
    with pytest.raises(InputError, match="canonical.ply: missing") as info:
        load_rig(tmp_path)
    assert "\n" not in str(info.value)


# ----------------------------------------------------------------------------- atomic writes
def test_crash_during_usd_write_keeps_the_good_file(tmp_path, monkeypatch):
    rig = two_bone_rig()
    out = tmp_path / "r.usda"
    export_usd(rig, out)
    good = out.read_bytes()

    def crash(layer, tmp):
        tmp.write_bytes(b"#usda 1.0\n(half a file")
        raise RuntimeError("simulated crash mid-write")

    monkeypatch.setattr(usd_mod, "_write_layer", crash)
    with pytest.raises(RuntimeError, match="simulated crash"):
        export_usd(two_bone_rig(T=3), out)
    assert out.read_bytes() == good
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.usda"]


def test_killed_writer_never_replaces_the_good_file(tmp_path):
    """A process killed (SIGKILL) while writing the .glb leaves the old file intact; the stale
    temporary file is removed by the next export."""
    rig = two_bone_rig()
    out = tmp_path / "r.glb"
    export_gltf(rig, out)
    good = out.read_bytes()
    child = textwrap.dedent(
        f"""
        import sys, time, pygltflib
        sys.path.insert(0, {str(Path(__file__).parent)!r})
        from test_export import two_bone_rig
        from s3o_warp.export import export_gltf
        def slow(self, path):
            with open(path, "wb") as f:
                f.write(b"glTF" + bytes(100)); f.flush()
                print("writing", flush=True)
                time.sleep(60)
        pygltflib.GLTF2.save_binary = slow
        export_gltf(two_bone_rig(T=3), {str(out)!r})
        """
    )
    proc = subprocess.Popen([sys.executable, "-c", child], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "writing"
        stale = [p for p in tmp_path.iterdir() if ".tmp-" in p.name]
        assert len(stale) == 1 and stale[0].suffix == ".glb"
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    assert out.read_bytes() == good
    export_gltf(rig, out)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.glb"]


# ----------------------------------------------------------------------------- the script
def _script():
    spec = importlib.util.spec_from_file_location("export_script", REPO / "scripts" / "export.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_export_script_defaults_and_options(tmp_path, capsys):
    run = tmp_path / "cat_run"
    save_rig(run, two_bone_rig(T=4))
    script = _script()
    assert script.main([str(run)]) == 0
    assert (run / "cat_run.usdc").is_file() and (run / "cat_run.glb").is_file()
    assert script.main([str(run), "--out", str(run / "b.usda"), "--baked"]) == 0
    stage = Usd.Stage.Open(str(run / "b.usda"))
    assert stage.GetPrimAtPath("/World/Mesh") and stage.GetEndTimeCode() == 3
    assert script.main([str(run), "--out", str(run / "k1.usda"), "--influences", "1"]) == 0
    assert script.main([str(tmp_path / "nope")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "canonical.ply: missing" in err[0]
