"""Rigged, animated glTF 2.0 binary (``.glb``) export of a :class:`~s3o_warp.export.rig.Rig`, or of one object
fitted to several videos (one Rig per video, :func:`export_gltf_videos`).

Contents (everything in the WORLD frame, Y up, metres = scene units):

- node ``root`` (identity joint, scene root) with the learned bone tree below it; one skin whose
  ``joints`` are [root, bones in parent-first order], ``inverseBindMatrices`` = inv(world bind)
  stored column-major, ``skeleton`` = root;
- a mesh node with POSITION, NORMAL, COLOR_0 (linear RGB), JOINTS_0 (unsigned short) and
  WEIGHTS_0: the top 4 weights of every vertex, renormalised (glTF skins hold 4 influences per
  attribute set; the approximation error is reported);
- one animation (LINEAR samplers, time k / fps for frame k) with a translation and a rotation
  (x, y, z, w) channel per joint and for the camera node;
- a perspective camera node looking down -Z with +Y up. glTF cameras have square pixels, a centred
  principal point and one field of view for the whole clip: ``yfov = 2 atan(H / (2 fy))`` with the
  median fy, ``aspectRatio = W / H``. Each frame's principal point offset (and any fx != fy or focal
  change) is folded into the camera's pose instead (:func:`camera_folds`: a small turn and shift per
  frame that puts the posed vertices where the frame's own intrinsics put them); the largest pixel
  error left on the posed vertices is reported as ``ExportReport.camera_px_error``. Use the USD export
  for pixel-exact cameras.

Several videos share the mesh, the skin and the skeleton; each video has its own camera node
``camera_<name>`` (and glTF camera) and its own animation ``<name>`` of the joints and that camera
node, frame k at time k / fps of that video; the file's ``extras`` list each video's name, fps,
frame names and image size.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import cv2
import numpy as np
import pygltflib as g

from s3o_warp.data.io import atomic_path
from s3o_warp.errors import InputError
from s3o_warp.export.rig import (
    CAMERA_GL_FROM_CV,
    Rig,
    decompose_rigid,
    top_k_error,
    top_k_weights,
    vertex_normals,
)
from s3o_warp.export.usd import ExportReport
from s3o_warp.geometry import project_np

logger = logging.getLogger(__name__)

GLTF_INFLUENCES = 4
_FLOAT, _USHORT, _UINT = 5126, 5123, 5125
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
_TYPES = {1: "SCALAR", 3: "VEC3", 4: "VEC4", 16: "MAT4"}


class _Blob:
    """Accumulates the binary chunk and the bufferViews/accessors that point into it."""

    def __init__(self, gltf):
        self.gltf = gltf
        self.data = bytearray()

    def add(self, array: np.ndarray, target: int | None = None, minmax: bool = False) -> int:
        a = np.ascontiguousarray(array)
        comp = {np.dtype(np.float32): _FLOAT, np.dtype(np.uint16): _USHORT, np.dtype(np.uint32): _UINT}[a.dtype]
        width = 1 if a.ndim == 1 else int(np.prod(a.shape[1:]))
        while len(self.data) % 4:
            self.data.append(0)
        offset = len(self.data)
        self.data += a.tobytes()
        self.gltf.bufferViews.append(g.BufferView(buffer=0, byteOffset=offset, byteLength=a.nbytes, target=target))
        acc = g.Accessor(bufferView=len(self.gltf.bufferViews) - 1, componentType=comp, count=int(a.shape[0]), type=_TYPES[width])
        if minmax:
            flat = a.reshape(a.shape[0], -1)
            acc.min = flat.min(0).tolist()
            acc.max = flat.max(0).tolist()
        self.gltf.accessors.append(acc)
        return len(self.gltf.accessors) - 1


def glb_intrinsics(rig: Rig, focal: float) -> np.ndarray:
    """(3, 3) intrinsics a glTF camera has: fx = fy = ``focal``, principal point at the image centre."""
    h, w = rig.image_size
    return np.array([[focal, 0, w / 2 - 0.5], [0, focal, h / 2 - 0.5], [0, 0, 1.0]])


def camera_folds(rig: Rig, focal: float, cam: np.ndarray | None = None) -> np.ndarray:
    """(T, 4, 4) rigid moves M_t of each frame's OpenCV camera that fold the frame's intrinsics into a glTF camera
    (:func:`glb_intrinsics`): ``glb_K @ (M_t X)`` lands where ``K_t @ X`` does, X the posed vertices.

    A principal point off the image centre moves the whole picture; a small turn of the camera about its centre
    moves it almost uniformly (by f times the angle; what is left is a perspective term of about f a u^2 for a
    turn a and an object u radians wide). M_t starts as the smallest turn taking the ray of the vertices' mean
    pixel under K_t onto its ray under the glTF intrinsics; its rotation and position are then refined together on
    all vertices' pixels (Levenberg-Marquardt, :func:`cv2.solvePnPRefineLM`), which roughly halves what a turn alone
    leaves (largest error 0.43 px against 0.82 px on a fitted 320x240 Fox, 2.8 against 5.6 on DAVIS cows; the
    figures in ``docs/results.md``). The camera moves by 1-3 % of the object's distance.
    """
    cam = rig.posed_camera() if cam is None else cam
    k_glb = glb_intrinsics(rig, focal)
    exact = rig.project(cam)
    out = np.broadcast_to(np.eye(4), (rig.num_frames, 4, 4)).copy()
    for t in range(rig.num_frames):
        pts, px = np.ascontiguousarray(cam[t], dtype=np.float64), np.ascontiguousarray(exact[t], dtype=np.float64)
        centre = np.append(px.mean(0), 1.0)
        d0 = np.linalg.solve(rig.K[t], centre)
        d1 = np.linalg.solve(k_glb, centre)
        d0, d1 = d0 / np.linalg.norm(d0), d1 / np.linalg.norm(d1)
        axis = np.cross(d0, d1)
        angle = np.arctan2(np.linalg.norm(axis), float(d0 @ d1))
        rvec = (axis / max(np.linalg.norm(axis), 1e-300) * angle).reshape(3, 1)
        turn = (rvec, np.zeros((3, 1)))
        refined = cv2.solvePnPRefineLM(pts, px, k_glb, None, rvec.copy(), np.zeros((3, 1)))

        def worst(rt):
            return np.linalg.norm(project_np(pts @ cv2.Rodrigues(rt[0])[0].T + rt[1].ravel(), k_glb) - px, axis=1).max()

        rvec, tvec = refined if worst(refined) <= worst(turn) else turn  # never worse than the turn
        out[t, :3, :3] = cv2.Rodrigues(rvec)[0]
        out[t, :3, 3] = tvec.ravel()
    return out


def glb_camera_to_world(rig: Rig, folds: np.ndarray) -> np.ndarray:
    """(T, 4, 4) camera-to-world of the glTF camera: the fit's (:meth:`Rig.camera_to_world`) moved by ``folds``
    (OpenCV camera frame, :func:`camera_folds`): the object-to-camera pose is ``folds[t] @ root[t]``."""
    return rig.world_from_object @ np.linalg.inv(folds @ rig.root) @ CAMERA_GL_FROM_CV


def gltf_camera_error(
    rig: Rig, focal: float, cam: np.ndarray | None = None, folds: np.ndarray | None = None
) -> float:
    """Largest pixel distance over all frames between the fit's projection and a glTF camera's.

    The glTF camera has intrinsics fx = fy = ``focal``, cx = W/2 - 0.5, cy = H/2 - 0.5 (square pixels, centred
    principal point) and the fit's pose moved by ``folds`` (T, 4, 4) (:func:`camera_folds`; None: the fit's pose).
    ``cam``: optional (T, N, 3) :meth:`Rig.posed_camera`, to avoid recomputing it.
    """
    cam = rig.posed_camera() if cam is None else cam
    exact = rig.project(cam)
    if folds is not None:
        cam = np.einsum("tij,tnj->tni", folds[:, :3, :3], cam) + folds[:, None, :3, 3]
    ideal = project_np(cam, glb_intrinsics(rig, focal))
    return float(np.linalg.norm(ideal - exact, axis=-1).max())


def export_gltf(rig: Rig, path: str | os.PathLike) -> ExportReport:
    """Write ``rig`` as a skinned, animated ``.glb`` with a camera node.

    The file is written atomically (:mod:`s3o_warp.data.io`).

    Args:
        rig: the reconstruction to export.
        path: output ``.glb`` file.

    Returns:
        An :class:`~s3o_warp.export.usd.ExportReport` with the 4-influence approximation error and
        the camera model's pixel error (see the module docstring).

    Raises:
        InputError: the extension is not ``.glb`` or the output folder does not exist.
    """
    return _write_glb([rig], ["Camera"], ["Motion"], _video_extras(rig), path)


def export_gltf_videos(rigs: list[Rig], names: list[str], path: str | os.PathLike) -> ExportReport:
    """Write one object fitted to several videos as one ``.glb``: one mesh and skin, and per video a camera node
    ``camera_<name>`` and an animation ``<name>`` of the joints and that camera (as :func:`export_gltf`).

    Args:
        rigs: one :class:`Rig` per video, equal in mesh, colours, weights and skeleton.
        names: one unique, non-empty name per video.
        path: output ``.glb`` file, written atomically.

    Returns:
        An :class:`~s3o_warp.export.usd.ExportReport` holding the worst of each figure over the videos.

    Raises:
        InputError: no rigs, names missing, empty or repeated, rigs differing in a shared field, the extension is
            not ``.glb`` or the output folder does not exist.
    """
    names = check_one_object(rigs, names)
    extras = {"videos": [{"name": n, **_video_extras(r)} for r, n in zip(rigs, names)]}
    return _write_glb(rigs, [f"camera_{n}" for n in names], names, extras, path)


#: Rig fields that the videos of one object share (one mesh, skin and skeleton in the file).
SHARED_FIELDS = ("verts", "faces", "colors", "weights", "bone_names", "parents", "bind", "world_from_object")


def check_one_object(rigs: list[Rig], names: list[str]) -> list[str]:
    """The video names as strings, once ``rigs`` are checked to be one object (equal :data:`SHARED_FIELDS`).

    Raises:
        InputError: no rigs, not one name per rig, an empty or repeated name, or a shared field that differs.
    """
    names = [str(n) for n in names]
    if not rigs:
        raise InputError("export_gltf_videos: needs the rig of at least one video")
    if len(names) != len(rigs):
        raise InputError(f"export_gltf_videos: need one name per video ({len(rigs)}), got {len(names)}")
    if any(not n.strip() for n in names) or len(set(names)) != len(names):
        raise InputError(f"export_gltf_videos: video names must be non-empty and unique, got {names}")
    for name, rig in zip(names[1:], rigs[1:]):
        for f in SHARED_FIELDS:
            a, b = getattr(rigs[0], f), getattr(rig, f)
            if np.shape(a) != np.shape(b) or not np.array_equal(a, b):
                raise InputError(
                    f"export_gltf_videos: Rig.{f} of video {name!r} differs from video {names[0]!r}'s; "
                    "the videos of one object share the mesh, colours, weights and skeleton"
                )
    return names


def _video_extras(rig: Rig) -> dict:
    return {"fps": rig.fps, "frame_names": rig.frame_names, "image_size": list(rig.image_size)}


def _write_glb(
    rigs: list[Rig], camera_names: list[str], animation_names: list[str], extras: dict, path: str | os.PathLike
) -> ExportReport:
    """The ``.glb`` of one object (mesh and skeleton of ``rigs[0]``) with one camera node and one animation per rig."""
    path = Path(path)
    if path.suffix.lower() != ".glb":
        raise InputError(f"{path}: a glTF export needs the extension .glb")
    rig = rigs[0]
    b_count = rig.num_bones
    k = min(GLTF_INFLUENCES, b_count)
    gltf = g.GLTF2(asset=g.Asset(version="2.0", generator="s3o-warp"))
    gltf.scene = 0
    blob = _Blob(gltf)

    # -------------------------------------------------------------- joints (root + bones, parent first)
    order = rig.topological_order()
    names = rig.joint_names()
    joint_of_bone = np.empty(b_count, dtype=np.int64)
    joint_of_bone[order] = np.arange(1, b_count + 1)
    bind_world = rig.bind_world()
    rest_local = rig.local_transforms(bind_world)
    rest_t, rest_q = decompose_rigid(rest_local)
    gltf.nodes.append(g.Node(name="root", children=[]))
    for b in order:
        gltf.nodes.append(g.Node(name=names[b], translation=rest_t[b].tolist(), rotation=rest_q[b].tolist(), children=[]))
    for b in order:
        parent_node = 0 if rig.parents[b] < 0 else int(joint_of_bone[rig.parents[b]])
        gltf.nodes[parent_node].children.append(int(joint_of_bone[b]))
    for node in gltf.nodes:
        if not node.children:
            node.children = None  # the spec requires non-empty arrays

    # -------------------------------------------------------------- mesh
    g_rest = rig.verts.astype(np.float64) @ rig.world_from_object[:3, :3].T + rig.world_from_object[:3, 3]

    idx, val = top_k_weights(rig.weights, k)
    joints0 = np.zeros((len(idx), 4), dtype=np.uint16)
    weights0 = np.zeros((len(idx), 4), dtype=np.float32)
    weights0[:, :k] = val
    joints0[:, :k] = np.where(weights0[:, :k] > 0, joint_of_bone[idx], 0)  # the spec: unused slots point at joint 0
    attrs = g.Attributes(
        POSITION=blob.add(g_rest.astype(np.float32), _ARRAY_BUFFER, minmax=True),
        NORMAL=blob.add(vertex_normals(g_rest, rig.faces), _ARRAY_BUFFER),
        COLOR_0=blob.add(np.clip(rig.colors, 0, 1).astype(np.float32), _ARRAY_BUFFER),
        JOINTS_0=blob.add(joints0, _ARRAY_BUFFER),
        WEIGHTS_0=blob.add(weights0, _ARRAY_BUFFER),
    )
    indices = blob.add(rig.faces.reshape(-1).astype(np.uint32), _ELEMENT_ARRAY_BUFFER)
    gltf.meshes.append(g.Mesh(name="Mesh", primitives=[g.Primitive(attributes=attrs, indices=indices, mode=4)]))
    ibm = np.linalg.inv(np.concatenate([np.eye(4)[None], bind_world[order]]))
    ibm_acc = blob.add(np.swapaxes(ibm, 1, 2).reshape(-1, 16).astype(np.float32))  # column-major
    gltf.skins.append(g.Skin(name="Skeleton", joints=list(range(b_count + 1)), skeleton=0, inverseBindMatrices=ibm_acc))
    mesh_node = len(gltf.nodes)
    gltf.nodes.append(g.Node(name="Mesh", mesh=0, skin=0))

    cam_nodes, cam_errs, topk_errs = [], [], []
    for video, cam_name, anim_name in zip(rigs, camera_names, animation_names):
        node, cam_err = _add_video(gltf, blob, video, order, cam_name, anim_name)
        cam_nodes.append(node)
        cam_errs.append(cam_err)
        topk_errs.append(top_k_error(video, k))

    gltf.scenes.append(g.Scene(name="Scene", nodes=[0, mesh_node, *cam_nodes]))
    gltf.extras = extras
    gltf.buffers.append(g.Buffer(byteLength=len(blob.data)))
    gltf.set_binary_blob(bytes(blob.data))

    err = max(e[0] for e in topk_errs), max(e[1] for e in topk_errs)
    cam_err = max(cam_errs)
    with atomic_path(path) as tmp:
        gltf.save_binary(str(tmp))
    logger.info(
        "wrote %s (%d video(s), %s frames, %d bones, top-%d error %.3g = %.2g of the bbox diagonal, "
        "camera model error %.3g px)",
        path, len(rigs), "+".join(str(r.num_frames) for r in rigs), b_count, k, err[0], err[1], cam_err,
    )
    return ExportReport(path=path, influences=k, topk_error=err[0], topk_error_rel=err[1], camera_px_error=cam_err)


def _add_video(gltf, blob: _Blob, rig: Rig, order: list[int], cam_name: str, anim_name: str) -> tuple[int, float]:
    """Add ``rig``'s camera (node ``cam_name``) and its animation ``anim_name`` of the joints and that camera node.

    Returns:
        (the camera node, the camera model's pixel error :func:`gltf_camera_error`).
    """
    t_count, b_count = rig.num_frames, rig.num_bones

    # -------------------------------------------------------------- camera
    h, w = rig.image_size
    cam_pts = rig.posed_camera()
    depth = cam_pts[..., 2]
    focal = float(np.median(rig.K[:, 1, 1]))
    gltf.cameras.append(
        g.Camera(
            name=cam_name,
            type="perspective",
            perspective=g.Perspective(
                yfov=float(2 * np.arctan(h / (2 * focal))),
                aspectRatio=float(w / h),
                znear=float(max(depth.min() * 0.1, 1e-4)),
                zfar=float(depth.max() * 10),
            ),
        )
    )
    folds = camera_folds(rig, focal, cam_pts)
    c2w = glb_camera_to_world(rig, folds)
    cam_node = len(gltf.nodes)
    cam_t, cam_q = decompose_rigid(c2w)
    gltf.nodes.append(
        g.Node(name=cam_name, camera=len(gltf.cameras) - 1, translation=cam_t[0].tolist(), rotation=cam_q[0].tolist())
    )

    # -------------------------------------------------------------- animation
    local = np.stack([rig.local_transforms(rig.bone_world(t))[order] for t in range(t_count)])
    local = np.concatenate([np.broadcast_to(np.eye(4), (t_count, 1, 4, 4)), local], 1)
    anim_t, anim_q = decompose_rigid(local)
    times = blob.add((np.arange(t_count) / rig.fps).astype(np.float32), minmax=True)
    samplers, channels = [], []

    def channel(node: int, prop: str, values: np.ndarray) -> None:
        samplers.append(g.AnimationSampler(input=times, output=blob.add(values.astype(np.float32)), interpolation="LINEAR"))
        channels.append(g.AnimationChannel(sampler=len(samplers) - 1, target=g.AnimationChannelTarget(node=node, path=prop)))

    for j in range(b_count + 1):
        channel(j, "translation", anim_t[:, j])
        channel(j, "rotation", anim_q[:, j])
    channel(cam_node, "translation", cam_t)
    channel(cam_node, "rotation", cam_q)
    gltf.animations.append(g.Animation(name=anim_name, samplers=samplers, channels=channels))
    return cam_node, gltf_camera_error(rig, focal, cam_pts, folds)
