"""Synthetic sequences: procedural quadruped, glTF loader (against the spec formula), cameras,
rendering with the project's rasteriser, ground truth and the command line."""

from __future__ import annotations

import functools
import importlib.util
import json
from pathlib import Path

import cv2
import numpy as np
import pygltflib
import pytest
from scipy.ndimage import binary_dilation, distance_transform_edt
from scipy.spatial.transform import Rotation, Slerp

from s3o_warp.errors import InputError
from s3o_warp.synth import (
    build_quadruped,
    camera_path,
    gltf_keypoints,
    keypoint_vertices,
    load_gltf,
    look_at,
    make_sequence,
)
from s3o_warp.synth.gltf import sample_channel
from s3o_warp.synth.quadruped import forward_kinematics

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def quad():
    return build_quadruped(frames=24, fps=24.0, seed=0)


# ---------------------------------------------------------------------------------------------
# procedural quadruped


def test_quadruped_skeleton(quad):
    names = quad.joint_names
    for leg in ("fl", "fr", "bl", "br"):
        up = "shoulder" if leg[0] == "f" else "hip"
        knee, foot = names.index(f"knee_{leg}"), names.index(f"foot_{leg}")
        assert quad.parents[foot] == knee  # two segments per leg: a knee joint exists
        assert quad.parents[knee] == names.index(f"{up}_{leg}")
    for part in ("pelvis", "neck", "head", "tail_tip", "nose"):
        assert part in names
    assert np.sum(quad.parents < 0) == 1
    assert all(quad.parents[j] < j for j in range(len(names)) if quad.parents[j] >= 0)
    assert 2000 <= quad.rest_verts.shape[0] <= 4000
    np.testing.assert_allclose(quad.weights.sum(1), 1.0, atol=1e-5)
    assert ((quad.weights > 0).sum(1) <= 4).all()
    # left legs on the -z side, feet near the ground, head in front (+x), up is +y
    assert quad.rest_joints[names.index("foot_fl"), 2] < 0 < quad.rest_joints[names.index("foot_fr"), 2]
    assert quad.rest_joints[names.index("head"), 0] > quad.rest_joints[names.index("pelvis"), 0]
    assert abs(quad.rest_verts[:, 1].min()) < 0.03


def test_quadruped_walk_moves_feet(quad):
    names = quad.joint_names
    pelvis = quad.joints[:, names.index("pelvis")]
    rel = {leg: quad.joints[:, names.index(f"foot_{leg}")] - pelvis for leg in ("fl", "fr", "bl", "br")}
    for leg, r in rel.items():
        assert np.ptp(r[:, 0]) > 0.1, leg  # each foot swings forward and back relative to the body
    corr = lambda a, b: np.corrcoef(rel[a][:, 0], rel[b][:, 0])[0, 1]  # noqa: E731
    assert corr("fl", "br") > 0.9 and corr("fr", "bl") > 0.9  # diagonal pairs in phase
    assert corr("fl", "fr") < -0.9  # the two pairs in antiphase
    knee_angle = []
    for t in range(quad.num_frames):
        a, b, c = (quad.joints[t, names.index(n)] for n in ("shoulder_fl", "knee_fl", "foot_fl"))
        knee_angle.append(np.degrees(np.arccos(np.dot(a - b, c - b) / np.linalg.norm(a - b) / np.linalg.norm(c - b))))
    assert np.ptp(knee_angle) > 20.0  # knees bend
    assert quad.joints[-1, names.index("pelvis"), 0] > quad.joints[0, names.index("pelvis"), 0] + 0.2  # walks forward
    tail = quad.joints[:, names.index("tail_tip"), 2]
    assert np.ptp(tail) > 0.05  # tail sways sideways
    # skin follows the skeleton: the feet's vertices move with the feet
    assert np.ptp(quad.verts[:, :, 0] - pelvis[:, None, 0], axis=0).max() > 0.1


def test_quadruped_rest_pose_and_determinism(quad):
    nj = len(quad.joint_names)
    g = forward_kinematics(quad.rest_joints.astype(np.float64), quad.parents, np.tile(np.eye(3), (1, nj, 1, 1)), np.zeros((1, 3)))
    np.testing.assert_allclose(g[0], np.tile(np.eye(4), (nj, 1, 1)), atol=1e-12)
    again = build_quadruped(frames=24, fps=24.0, seed=0)
    np.testing.assert_array_equal(again.verts, quad.verts)
    other = build_quadruped(frames=24, fps=24.0, seed=1)
    assert other.verts.shape[1] != quad.verts.shape[1] or not np.allclose(other.verts, quad.verts)
    names, idx = keypoint_vertices(quad)
    assert len(names) == len(set(names)) >= 16 and len(set(idx.tolist())) == len(idx)
    with pytest.raises(InputError, match="frames"):
        build_quadruped(frames=0)


# ---------------------------------------------------------------------------------------------
# glTF: an independent evaluation of the spec formula


@functools.lru_cache(maxsize=2)
def _parse(path: str) -> pygltflib.GLTF2:
    return pygltflib.GLTF2().load(path)


def _spec_skin(path: Path, clip: str | None, times: np.ndarray | None):
    """v' = sum_i w_i * J_i * IBM_i * v for a skinned mesh (J the joints' global matrices, rest TRS where not
    animated, IBM its own skin's); v' = M * v for a mesh without a skin (M its node's global matrix). Every
    mesh node of the scene, merged in depth-first order."""
    g = _parse(str(path))
    blob = g.binary_blob()

    def acc(i):
        a = g.accessors[i]
        bv = g.bufferViews[a.bufferView]
        dt = np.dtype({5121: np.uint8, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}[a.componentType])
        n = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}[a.type]
        stride = bv.byteStride or dt.itemsize * n
        start = (bv.byteOffset or 0) + (a.byteOffset or 0)
        rows = [blob[start + k * stride:start + k * stride + dt.itemsize * n] for k in range(a.count)]
        return np.frombuffer(b"".join(rows), dt).reshape(a.count, n)

    anim = {}
    if clip is not None:
        an = [a for a in g.animations if a.name == clip][0]
        for ch in an.channels:
            if ch.target.path not in ("translation", "rotation", "scale"):
                continue  # morph-target weights: the loader keeps the base shape
            s = an.samplers[ch.sampler]
            key_t, key_v = acc(s.input)[:, 0].astype(np.float64), acc(s.output).astype(np.float64)
            tq = np.clip(times + key_t.min(), key_t.min(), key_t.max())
            if ch.target.path == "rotation":
                val = Slerp(key_t, Rotation.from_quat(key_v))(tq).as_quat()
            else:
                val = np.stack([np.interp(tq, key_t, key_v[:, c]) for c in range(3)], 1)
            anim[(ch.target.node, ch.target.path)] = val

    def local(n, k):
        node = g.nodes[n]
        if node.matrix is not None:
            return np.asarray(node.matrix).reshape(4, 4).T
        t = anim.get((n, "translation"), [node.translation or [0, 0, 0]] * (k + 1))[k]
        r = anim.get((n, "rotation"), [node.rotation or [0, 0, 0, 1]] * (k + 1))[k]
        s = anim.get((n, "scale"), [node.scale or [1, 1, 1]] * (k + 1))[k]
        m = np.eye(4)
        m[:3, :3] = Rotation.from_quat(r).as_matrix() @ np.diag(s)
        m[:3, 3] = t
        return m

    parent = {c: i for i, n in enumerate(g.nodes) for c in (n.children or [])}

    def world(n, k):
        return local(n, k) if n not in parent else world(parent[n], k) @ local(n, k)

    def depth_first(n):
        return [n] + [m for c in (g.nodes[n].children or []) for m in depth_first(c)]

    mesh_nodes = [n for r in g.scenes[g.scene or 0].nodes for n in depth_first(r) if g.nodes[n].mesh is not None]
    out = []
    for k in range(1 if times is None else len(times)):
        verts = []
        for n in mesh_nodes:
            node = g.nodes[n]
            if node.skin is not None:
                skin = g.skins[node.skin]
                ibm = acc(skin.inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1).astype(np.float64)
                jm = np.stack([world(j, k) @ ibm[i] for i, j in enumerate(skin.joints)])
            for prim in g.meshes[node.mesh].primitives:
                v = acc(prim.attributes.POSITION).astype(np.float64)
                vh = np.concatenate([v, np.ones((len(v), 1))], 1)
                if node.skin is None:
                    verts.append((vh @ world(n, k).T)[:, :3])
                    continue
                jj = acc(prim.attributes.JOINTS_0).astype(np.int64)
                ww = acc(prim.attributes.WEIGHTS_0).astype(np.float64)
                ww = ww / ww.sum(1, keepdims=True)
                verts.append(np.einsum("vk,vkab,vb->va", ww, jm[jj], vh)[:, :3])
        out.append(np.concatenate(verts))
    return np.stack(out)


def test_gltf_fox_matches_spec_formula(shared_data):
    path = shared_data / "gltf" / "khronos_Fox.glb"
    fps, frames = 30.0, 4
    mesh = load_gltf(path, clip="Walk", fps=fps, frames=frames, to_object_frame=False)
    ref = _spec_skin(path, "Walk", np.arange(frames) / fps)
    scale = np.ptp(ref[0], axis=0).max()
    assert np.abs(mesh.verts - ref).max() < 1e-5 * scale
    assert np.abs(mesh.verts[1] - mesh.verts[0]).max() > 1e-3 * scale  # the clip animates
    assert mesh.clip_names == ["Survey", "Walk", "Run"]
    # asking for more frames than the clip has loops it: time k / fps wraps modulo the duration
    looped = load_gltf(path, clip="Walk", fps=fps, frames=30, to_object_frame=False)
    g = _parse(str(path))
    duration = max(g.accessors[s.input].max[0] for s in g.animations[1].samplers) - min(
        g.accessors[s.input].min[0] for s in g.animations[1].samplers)
    assert 29 / fps > duration
    tail = np.arange(24, 30) / fps
    ref_loop = _spec_skin(path, "Walk", np.mod(tail, duration))
    assert np.abs(looped.verts[24:] - ref_loop).max() < 1e-5 * scale
    # the object frame is a +90 degree turn about +y: glTF +z (front) -> +x
    turned = load_gltf(path, clip="Walk", fps=fps, frames=frames)
    np.testing.assert_allclose(turned.verts[..., 0], mesh.verts[..., 2], atol=1e-4 * scale)
    np.testing.assert_allclose(turned.verts[..., 2], -mesh.verts[..., 0], atol=1e-4 * scale)


def test_gltf_rest_pose_differs_from_bind(shared_data):
    """Quaternius rigs: rest TRS != bind pose; rest_verts must follow the node hierarchy's rest TRS."""
    path = shared_data / "gltf" / "quaternius_Cow.glb"
    mesh = load_gltf(path, clip="Walk", fps=30.0, frames=2, to_object_frame=False)
    rest_ref = _spec_skin(path, None, None)[0]
    scale = np.ptp(rest_ref, axis=0).max()
    assert np.abs(mesh.rest_verts - rest_ref).max() < 1e-5 * scale
    ref = _spec_skin(path, "Walk", np.arange(2) / 30.0)
    assert np.abs(mesh.verts - ref).max() < 1e-5 * scale
    deforming = dict(zip(mesh.joint_names, mesh.deforming))
    # pole targets carry no weight; in these rigs the IK leg bones do carry the hooves' weights
    assert not deforming["PoleTarget.L"] and not deforming["PoleTargetBack.R"]
    assert deforming["IKBackLeg.L"] and deforming["FrontLowerLeg.L"]


def test_every_model_loads(shared_data):
    """Every four-legged animal model (the Khronos Fox and the six Quaternius animals) loads with its rig."""
    files = sorted(f for f in (shared_data / "gltf").glob("*.glb") if f.name.startswith(("khronos_", "quaternius_")))
    assert len(files) == 7
    for f in files:
        m = load_gltf(f, frames=2)
        nv, nj = m.rest_verts.shape[0], len(m.joint_names)
        assert m.verts.shape == (2, nv, 3) and m.joints.shape == (2, nj, 3), f.name
        assert np.isfinite(m.verts).all() and m.faces.max() < nv, f.name
        np.testing.assert_allclose(m.weights[m.weights.sum(1) > 0].sum(1), 1.0, atol=1e-5)
        assert all(m.parents[j] < j for j in range(nj)), f.name  # parents first
        assert m.colors is not None and m.colors.shape == (nv, 3)
        names, idx = gltf_keypoints(m)
        assert len(names) >= 12 and idx.max() < nv, (f.name, names)
        # the head is in front of the tail: the object frame faces +x
        head = [j for j, n in enumerate(m.joint_names) if "head" in n.lower()][0]
        tail = [j for j, n in enumerate(m.joint_names) if "tail" in n.lower()][0]
        assert m.rest_joints[head, 0] > m.rest_joints[tail, 0], f.name
        if f.name.startswith("quaternius"):
            assert 0 < (~m.deforming).sum() <= 6, f.name  # IK/pole helpers marked


def test_gltf_robot_merges_meshes_and_skins(shared_data):
    """three.js's RobotExpressive: 14 meshes (12 moved rigidly by a bone, the two hands each by its own skin)
    merged into one posed mesh that matches the spec formula, every vertex weighted on a joint of its side."""
    path = shared_data / "gltf" / "threejs_RobotExpressive.glb"
    g = _parse(str(path))
    mesh_nodes = [n for n in g.nodes if n.mesh is not None]
    counts = [sum(g.accessors[p.attributes.POSITION].count for p in g.meshes[n.mesh].primitives) for n in mesh_nodes]
    assert len(mesh_nodes) == 14 and len({n.skin for n in mesh_nodes if n.skin is not None}) == 2
    fps, frames = 30.0, 3
    mesh = load_gltf(path, clip="Walking", fps=fps, frames=frames, to_object_frame=False)
    assert mesh.rest_verts.shape[0] == sum(counts) == 7214
    ref = _spec_skin(path, "Walking", np.arange(frames) / fps)
    scale = np.ptp(ref[0], axis=0).max()
    assert np.abs(mesh.verts - ref).max() < 1e-5 * scale
    assert np.abs(mesh.rest_verts - _spec_skin(path, None, None)[0]).max() < 1e-5 * scale
    assert np.abs(mesh.verts[2] - mesh.verts[0]).max() > 1e-2 * scale  # the clip animates
    np.testing.assert_allclose(mesh.weights.sum(1), 1.0, atol=1e-5)  # every part moves with a joint
    names = mesh.joint_names
    owner = [names[j] for j in mesh.weights.argmax(1)]
    start = np.cumsum([0] + counts)
    for k, node in enumerate(mesh_nodes):  # each hand on its own side's arm and fingers
        side = {"Hand.L": ".L", "Hand.R": ".R"}.get(node.name)
        if side:
            assert all(o.endswith(side) for o in owner[start[k]:start[k + 1]]), node.name
    assert not dict(zip(names, mesh.deforming))["PoleTarget.L"] and dict(zip(names, mesh.deforming))["Head"]
    kp, idx = gltf_keypoints(mesh)
    assert {"Head_tip", "Foot.L_tip", "Foot.R_tip", "LowerArm.L", "LowerArm.R", "Middle2.L_tip",
            "Middle2.R_tip", "LowerLeg.L", "LowerLeg.R"} <= set(kp) and idx.max() < 7214


def test_gltf_errors(shared_data, tmp_path):
    with pytest.raises(InputError, match="no animation clip named"):
        load_gltf(shared_data / "gltf" / "khronos_Fox.glb", clip="Fly", frames=2)
    with pytest.raises(InputError, match="not found"):
        load_gltf(tmp_path / "missing.glb")
    bad = tmp_path / "bad.glb"
    bad.write_bytes(b"not a gltf")
    with pytest.raises(InputError, match="glTF"):
        load_gltf(bad)


def test_sample_channel_interpolations():
    times = np.array([0.0, 1.0, 2.0])
    vals = np.array([[0.0], [2.0], [4.0]])
    t = np.array([-1.0, 0.25, 1.5, 3.0])
    np.testing.assert_allclose(sample_channel(times, vals, "LINEAR", t, False)[:, 0], [0.0, 0.5, 3.0, 4.0])
    np.testing.assert_allclose(sample_channel(times, vals, "STEP", t, False)[:, 0], [0.0, 0.0, 2.0, 4.0])
    # cubic Hermite with zero tangents is the smoothstep between keys
    cubic = np.stack([np.zeros(3), vals[:, 0], np.zeros(3)], 1).reshape(-1, 1)
    s = 0.25
    np.testing.assert_allclose(sample_channel(times, cubic, "CUBICSPLINE", np.array([s]), False)[0, 0],
                               2.0 * (3 * s * s - 2 * s ** 3))
    # slerp: halfway between identity and 90 degrees about z is 45 degrees
    q = np.array([[0, 0, 0, 1.0], [0, 0, np.sin(np.pi / 4), np.cos(np.pi / 4)]])
    half = sample_channel(np.array([0.0, 1.0]), q, "LINEAR", np.array([0.5]), True)[0]
    np.testing.assert_allclose(Rotation.from_quat(half).magnitude(), np.pi / 4, atol=1e-9)


# ---------------------------------------------------------------------------------------------
# cameras, rendering, ground truth


def test_cameras_look_at_target(quad):
    k, cams = camera_path(quad.verts, (48, 64), "orbit", (-30.0, 60.0), 15.0)
    assert cams.shape == (quad.num_frames, 4, 4)
    rot = cams[:, :3, :3]
    np.testing.assert_allclose(rot @ rot.transpose(0, 2, 1), np.tile(np.eye(3), (len(cams), 1, 1)), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-12)
    eye = np.array([[0.0, 0.0, 5.0]])
    m = look_at(eye, np.zeros((1, 3)))[0]
    p = m[:3, :3] @ np.array([1.0, 0.0, 0.0]) + m[:3, 3]
    assert p[0] > 0 and abs(p[1]) < 1e-12 and p[2] > 0  # +x world = image right seen from +z
    up = m[:3, :3] @ np.array([0.0, 1.0, 0.0]) + m[:3, 3]
    assert up[1] < 0  # world up = image up (OpenCV y down)
    _, pan = camera_path(quad.verts, (48, 64), "pan", (0.0, 0.0), 0.0)
    np.testing.assert_allclose(np.linalg.inv(pan)[:, :3, 3], np.linalg.inv(pan)[:1, :3, 3].repeat(len(pan), 0))
    with pytest.raises(InputError, match="orbit"):
        camera_path(quad.verts, (48, 64), "dolly")


def test_tiny_sequence(tmp_path, device):
    out = make_sequence(tmp_path / "seq", frames=4, size=(64, 48), device=device, progress=False)
    gt = np.load(out / "ground_truth" / "ground_truth.npz")
    assert tuple(gt["image_size"]) == (48, 64) and gt["verts"].shape[0] == 4
    kp = json.loads((out / "keypoints.json").read_text())
    assert len(kp["names"]) == 19 and sorted(kp["frames"]) == [f"{t:06d}" for t in range(4)]
    for t in range(4):
        name = f"{t:06d}"
        img = cv2.imread(str(out / "images" / f"{name}.png"), cv2.IMREAD_UNCHANGED)
        mask = cv2.imread(str(out / "masks" / f"{name}.png"), cv2.IMREAD_UNCHANGED)
        assert img.shape == (48, 64, 3) and mask.shape == (48, 64)
        assert set(np.unique(mask).tolist()) == {0, 255}
        fg = mask > 127
        assert 0.05 < fg.mean() < 0.8
        # ground-truth vertices project inside the mask (within a pixel; sub-pixel-thin ear and tail
        # tips at this tiny size cover no pixel centre, hence the 2.5 px bound on the rest)
        v = gt["verts"][t].astype(np.float64)
        uv = (v @ gt["K"][t].T)[:, :2] / v[:, 2:]
        c, r = np.rint(uv[:, 0]).astype(int), np.rint(uv[:, 1]).astype(int)
        assert (c >= 0).all() and (c < 64).all() and (r >= 0).all() and (r < 48).all()
        dist = distance_transform_edt(~fg)[r, c]
        assert (dist <= 1.5).mean() > 0.99 and dist.max() <= 2.5
        pts = np.array(kp["frames"][name])
        vis = pts[:, 2] == 1
        assert vis.sum() >= 6
        assert (pts[vis, 0] >= -0.5).all() and (pts[vis, 0] < 63.5).all()
        assert (pts[vis, 1] >= -0.5).all() and (pts[vis, 1] < 47.5).all()
        # the depth test found a covered pixel in the 3x3 neighbourhood of each visible keypoint
        near_fg = binary_dilation(fg, structure=np.ones((3, 3), bool))
        assert near_fg[np.rint(pts[vis, 1]).astype(int), np.rint(pts[vis, 0]).astype(int)].all()
        # keypoints are the stored surface vertices
        kv = gt["verts"][t][gt["keypoint_vertex"]].astype(np.float64)
        np.testing.assert_allclose((kv @ gt["K"][t].T)[:, :2] / kv[:, 2:], pts[:, :2], atol=2e-3)
    assert (gt["verts"][..., 2] > 0).all()
    assert gt["joints"].shape == (4, len(gt["joint_names"]), 3) and gt["joint_parents"][0] == -1


def test_masks_match_depth_and_hidden_keypoints(quad):
    """The rasteriser's coverage is the mask; a keypoint behind the body fails the depth test."""
    from s3o_warp.synth.render import SolidTexture, shade_chunk
    from s3o_warp.synth.sequence import keypoint_visibility

    k, cams = camera_path(quad.verts[:2], (48, 64), "orbit", (0.0, 0.0), 0.0)
    vc = np.einsum("tab,tvb->tva", cams[:, :3, :3], quad.verts[:2]) + cams[:, None, :3, 3]
    image, mask, face_index, depth = shade_chunk(vc.astype(np.float32), quad.faces, k, cams, quad.rest_verts,
                                                 quad.colors, SolidTexture(1.5, 0), (48, 64), 0)
    np.testing.assert_array_equal(mask, depth > 0)
    np.testing.assert_array_equal(mask, face_index >= 0)
    assert image.dtype == np.uint8 and image.shape == (2, 48, 64, 3)
    names, idx = keypoint_vertices(quad)
    xy, vis = keypoint_visibility(vc[:, idx], k, face_index, depth, tol=0.03)
    # camera at azimuth 0 looks at the right flank: right-side knees visible, left ones hidden
    assert vis[0, names.index("knee_fr")] and vis[0, names.index("knee_br")]
    assert not vis[0, names.index("knee_fl")] and not vis[0, names.index("knee_bl")]


def test_cli_writes_contract(tmp_path):
    spec = importlib.util.spec_from_file_location("make_synthetic", REPO / "scripts" / "make_synthetic.py")
    cli = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(cli)
    out = tmp_path / "cli_seq"
    assert cli.main(["--out", str(out), "--frames", "2", "--size", "40x32", "--seed", "3"]) == 0
    assert sorted(p.name for p in (out / "images").iterdir()) == ["000000.png", "000001.png"]
    assert sorted(p.name for p in (out / "masks").iterdir()) == ["000000.png", "000001.png"]
    assert (out / "keypoints.json").is_file() and (out / "ground_truth" / "ground_truth.npz").is_file()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temp folder left behind
    assert cli.main(["--out", str(out), "--frames", "2", "--size", "40x32"]) == 2  # exists, no --overwrite
    assert cli.main(["--out", str(out), "--frames", "2", "--size", "40x32", "--overwrite"]) == 0


def test_vertex_normals_of_a_sphere():
    import trimesh

    from s3o_warp.synth import vertex_normals

    sphere = trimesh.creation.icosphere(subdivisions=2)
    v, f = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    n = vertex_normals(v, f)
    assert np.min(np.sum(n * v, 1)) > 0.99  # outward unit normals = positions on the unit sphere
    np.testing.assert_allclose(vertex_normals(np.stack([v, 2 * v]), f)[1], n, atol=1e-6)  # batched
