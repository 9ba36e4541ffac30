"""Load a skinned, animated glTF 2.0 model (``.glb`` or ``.gltf``) and sample one clip per frame.

What is read (pygltflib): the default scene's node hierarchy (TRS or matrix per node), every mesh
node's triangle primitives merged into one mesh (indices, POSITION, optional COLOR_0, TEXCOORD_0),
every skin the meshes use (joints, inverse bind matrices, JOINTS_0/WEIGHTS_0 with weights
renormalised; the joints of all skins form one skeleton), the materials' base colour
(baseColorFactor times the base-colour texture sampled at each vertex's UV, times COLOR_0, returned
in sRGB) and the animation channels (translation, rotation, scale; LINEAR, STEP and CUBICSPLINE
samplers; morph-target weights are ignored: the meshes keep their base shape).

Skinning follows the spec: ``v' = sum_i w_i * G(joint_i) * IBM_i * v`` with G the joint's global
transform (its ancestors' transforms included, animated channels over the nodes' rest TRS), IBM the
inverse bind matrices of the mesh's own skin and the skinned mesh node's own transform ignored. A mesh
without a skin moves rigidly with its node's global transform (a part parented to a bone, as in
three.js's RobotExpressive); its vertices get weight 1 on the nearest joint at or above that node.
Rest pose (``rest_verts``) = the same formulas with every node at its rest TRS, which may differ from
the bind pose (the raw POSITION data).

The result is turned into this project's object frame (+y up, +x forward) by a rotation of +90
degrees about +y (glTF assets face +z); units stay the file's (metres per the spec). Joints are
reordered so parents precede children; ``deforming[j]`` is False for helper joints that carry no
skin weight on any vertex (e.g. the Quaternius pole targets; their IK leg bones do carry weight).
"""

from __future__ import annotations

import base64
import functools
import logging
import re
from pathlib import Path

import cv2
import numpy as np
import pygltflib

from ..errors import InputError
from .model import AnimatedMesh

log = logging.getLogger(__name__)

_COMPONENT = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
_NCOMP = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
_NORM = {np.int8: 127.0, np.uint8: 255.0, np.int16: 32767.0, np.uint16: 65535.0}

# glTF (+z front, +x left) -> object frame (+x front, +z right): rotation of +90 degrees about +y.
GLTF_TO_OBJECT = np.array([[0.0, 0.0, 1.0, 0.0], [0.0, 1.0, 0.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])


class _Reader:
    """Accessor reads over a loaded glTF (GLB blob, data URI or external .bin buffers)."""

    def __init__(self, gltf: pygltflib.GLTF2, path: Path):
        self.gltf = gltf
        self.path = path
        self._buffers: dict[int, bytes] = {}

    def buffer(self, index: int) -> bytes:
        if index not in self._buffers:
            uri = self.gltf.buffers[index].uri
            if uri is None:
                data = self.gltf.binary_blob()
            elif uri.startswith("data:"):
                data = base64.b64decode(uri.split(",", 1)[1])
            else:
                file = self.path.parent / uri
                if not file.is_file():
                    raise InputError(f"{self.path}: buffer file {uri} not found next to it; keep the .bin beside the .gltf")
                data = file.read_bytes()
            if data is None:
                raise InputError(f"{self.path}: buffer {index} has no data; re-export the model as .glb")
            self._buffers[index] = data
        return self._buffers[index]

    def view_bytes(self, view_index: int) -> bytes:
        bv = self.gltf.bufferViews[view_index]
        start = bv.byteOffset or 0
        return self.buffer(bv.buffer)[start:start + bv.byteLength]

    def accessor(self, index: int, as_float: bool = True) -> np.ndarray:
        """(count, ncomp) array of an accessor (normalised integers scaled to [0, 1] / [-1, 1])."""
        acc = self.gltf.accessors[index]
        dtype = np.dtype(_COMPONENT[acc.componentType])
        ncomp = _NCOMP[acc.type]
        if acc.bufferView is None:
            arr = np.zeros((acc.count, ncomp), dtype=dtype)
        else:
            bv = self.gltf.bufferViews[acc.bufferView]
            data = self.buffer(bv.buffer)
            start = (bv.byteOffset or 0) + (acc.byteOffset or 0)
            stride = bv.byteStride or dtype.itemsize * ncomp
            arr = np.ndarray((acc.count, ncomp), dtype=dtype, buffer=data, offset=start,
                             strides=(stride, dtype.itemsize)).copy()
        if acc.sparse is not None and acc.sparse.count:
            sp = acc.sparse
            idx_t = np.dtype(_COMPONENT[sp.indices.componentType])
            ib = self.gltf.bufferViews[sp.indices.bufferView]
            idx = np.frombuffer(self.buffer(ib.buffer), idx_t, sp.count,
                                (ib.byteOffset or 0) + (sp.indices.byteOffset or 0))
            vb = self.gltf.bufferViews[sp.values.bufferView]
            vals = np.frombuffer(self.buffer(vb.buffer), dtype, sp.count * ncomp,
                                 (vb.byteOffset or 0) + (sp.values.byteOffset or 0)).reshape(sp.count, ncomp)
            arr[idx.astype(np.int64)] = vals
        if as_float and acc.normalized and dtype.type in _NORM:
            return np.maximum(arr.astype(np.float64) / _NORM[dtype.type], -1.0)
        return arr.astype(np.float64) if as_float else arr


def _quat_to_mat(q: np.ndarray) -> np.ndarray:
    """(..., 4) quaternions (x, y, z, w), normalised here -> (..., 3, 3) rotation matrices."""
    q = q / np.maximum(np.linalg.norm(q, axis=-1, keepdims=True), 1e-12)
    x, y, z, w = np.moveaxis(q, -1, 0)
    m = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    return np.moveaxis(np.array(m), (0, 1), (-2, -1))


def _trs_matrix(t: np.ndarray, r: np.ndarray, s: np.ndarray) -> np.ndarray:
    """(..., 4, 4) = T * R * S from translation (..., 3), quaternion xyzw (..., 4), scale (..., 3)."""
    m = np.zeros(t.shape[:-1] + (4, 4))
    m[..., :3, :3] = _quat_to_mat(r) * s[..., None, :]
    m[..., :3, 3] = t
    m[..., 3, 3] = 1.0
    return m


def _slerp(q0: np.ndarray, q1: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Shortest-path spherical interpolation of (N, 4) quaternions at fractions (N,)."""
    dot = np.sum(q0 * q1, -1)
    q1 = np.where(dot[:, None] < 0, -q1, q1)
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    sin = np.sin(theta)
    small = sin < 1e-6
    w0 = np.where(small, 1 - s, np.sin((1 - s) * theta) / np.where(small, 1.0, sin))
    w1 = np.where(small, s, np.sin(s * theta) / np.where(small, 1.0, sin))
    q = w0[:, None] * q0 + w1[:, None] * q1
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def sample_channel(times: np.ndarray, values: np.ndarray, interpolation: str, t: np.ndarray,
                   rotation: bool) -> np.ndarray:
    """Evaluate one animation sampler at times ``t`` (clamped to its key range).

    Args:
        times: (K,) key times, seconds, increasing.
        values: (K, C) key values, or (3K, C) for CUBICSPLINE (in-tangent, value, out-tangent).
        interpolation: "LINEAR", "STEP" or "CUBICSPLINE".
        t: (N,) query times, seconds.
        rotation: the channel is a quaternion (slerp for LINEAR, renormalised for CUBICSPLINE).

    Returns:
        (N, C) values.
    """
    num_k = times.shape[0]
    cubic = interpolation == "CUBICSPLINE"
    val = values.reshape(num_k, 3, -1)[:, 1] if cubic else values
    if num_k == 1:
        return np.repeat(val[:1], t.shape[0], 0)
    i0 = np.clip(np.searchsorted(times, t, side="right") - 1, 0, num_k - 2)
    i1 = i0 + 1
    dt = times[i1] - times[i0]
    s = np.clip((t - times[i0]) / np.maximum(dt, 1e-12), 0.0, 1.0)
    if interpolation == "STEP":
        return val[np.where(s >= 1.0, i1, i0)]
    if cubic:
        tri = values.reshape(num_k, 3, -1)
        s2, s3 = s * s, s * s * s
        out = ((2 * s3 - 3 * s2 + 1)[:, None] * tri[i0, 1] + ((s3 - 2 * s2 + s) * dt)[:, None] * tri[i0, 2]
               + (-2 * s3 + 3 * s2)[:, None] * tri[i1, 1] + ((s3 - s2) * dt)[:, None] * tri[i1, 0])
        if rotation:
            out /= np.linalg.norm(out, axis=-1, keepdims=True)
        return out
    if rotation:
        return _slerp(val[i0], val[i1], s)
    return val[i0] * (1 - s)[:, None] + val[i1] * s[:, None]


def _scene_nodes(gltf: pygltflib.GLTF2, path: Path) -> tuple[list[int], np.ndarray]:
    """Nodes of the default scene in depth-first order (parents first) and each node's parent."""
    parent = np.full(len(gltf.nodes), -1, dtype=np.int64)
    for i, n in enumerate(gltf.nodes):
        for c in n.children or []:
            parent[c] = i
    if gltf.scenes:
        roots = list(gltf.scenes[gltf.scene or 0].nodes or [])
    else:
        roots = [i for i in range(len(gltf.nodes)) if parent[i] < 0]
    order: list[int] = []
    stack = list(reversed(roots))
    while stack:
        i = stack.pop()
        order.append(i)
        stack.extend(reversed(gltf.nodes[i].children or []))
    if not order:
        raise InputError(f"{path}: the scene has no nodes; export the model with its armature and mesh")
    return order, parent


def _global_transforms(gltf: pygltflib.GLTF2, order: list[int], parent: np.ndarray,
                       anim: dict[int, dict[str, np.ndarray]], num_t: int) -> np.ndarray:
    """(T, N, 4, 4) global matrices of every node; animated TRS paths override the rest TRS."""
    glob = np.tile(np.eye(4), (num_t, len(gltf.nodes), 1, 1))
    for i in order:
        n = gltf.nodes[i]
        a = anim.get(i, {})
        if n.matrix is not None and not a:
            local = np.tile(np.asarray(n.matrix, dtype=np.float64).reshape(4, 4).T, (num_t, 1, 1))
        else:
            t = a.get("translation", np.tile(np.asarray(n.translation or [0.0, 0.0, 0.0], float), (num_t, 1)))
            r = a.get("rotation", np.tile(np.asarray(n.rotation or [0.0, 0.0, 0.0, 1.0], float), (num_t, 1)))
            s = a.get("scale", np.tile(np.asarray(n.scale or [1.0, 1.0, 1.0], float), (num_t, 1)))
            local = _trs_matrix(t, r, s)
        glob[:, i] = local if parent[i] < 0 else glob[:, parent[i]] @ local
    return glob


def _sample_clip(reader: _Reader, clip_index: int | None, fps: float, frames: int | None
                 ) -> tuple[dict[int, dict[str, np.ndarray]], int]:
    """Sample one animation's channels at ``frames`` times k / fps, looping past its end."""
    gltf = reader.gltf
    if clip_index is None:
        return {}, frames or 1
    anim = gltf.animations[clip_index]
    inputs = {}
    for smp in anim.samplers:
        if smp.input not in inputs:
            inputs[smp.input] = reader.accessor(smp.input)[:, 0]
    start = min(float(v.min()) for v in inputs.values())
    end = max(float(v.max()) for v in inputs.values())
    duration = end - start
    if frames is None:
        frames = int(np.floor(duration * fps + 1e-6)) + 1
    tk = np.arange(frames) / fps
    if duration > 0:  # loop: times past the end wrap around (the clip's last key = its first)
        tk = np.where(tk > duration + 1e-9, np.mod(tk, duration), tk)
    tk = start + tk
    out: dict[int, dict[str, np.ndarray]] = {}
    for ch in anim.channels:
        path = ch.target.path
        if ch.target.node is None or path not in ("translation", "rotation", "scale"):
            continue
        smp = anim.samplers[ch.sampler]
        values = reader.accessor(smp.output)
        out.setdefault(ch.target.node, {})[path] = sample_channel(
            inputs[smp.input], values, smp.interpolation or "LINEAR", tk, path == "rotation")
    return out, frames


def _decode_image(reader: _Reader, image_index: int) -> np.ndarray | None:
    """(H, W, 3) float sRGB in [0, 1] of a glTF image, or None when it cannot be read."""
    img = reader.gltf.images[image_index]
    try:
        if img.bufferView is not None:
            data = reader.view_bytes(img.bufferView)
        elif img.uri and img.uri.startswith("data:"):
            data = base64.b64decode(img.uri.split(",", 1)[1])
        elif img.uri:
            data = (reader.path.parent / img.uri).read_bytes()
        else:
            return None
    except OSError:
        return None
    arr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if arr is None:
        return None
    return arr[..., ::-1].astype(np.float64) / 255.0


def _sample_texture(tex: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear, repeat-wrapped lookup of (H, W, 3) at glTF UVs (N, 2) (origin top-left)."""
    h, w = tex.shape[:2]
    x = uv[:, 0] * w - 0.5
    y = uv[:, 1] * h - 0.5
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    def at(yy, xx):
        return tex[np.mod(yy, h), np.mod(xx, w)]
    return ((1 - fy) * ((1 - fx) * at(y0, x0) + fx * at(y0, x0 + 1))
            + fy * ((1 - fx) * at(y0 + 1, x0) + fx * at(y0 + 1, x0 + 1)))


def _srgb_to_linear(c: np.ndarray) -> np.ndarray:
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _linear_to_srgb(c: np.ndarray) -> np.ndarray:
    c = np.clip(c, 0.0, 1.0)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055)


def clip_names(path: str | Path) -> list[str]:
    """Names of the animation clips in a glTF file (unnamed clips are called ``clip<k>``)."""
    gltf = _load(Path(path))
    return [a.name or f"clip{k}" for k, a in enumerate(gltf.animations)]


def _load(path: Path) -> pygltflib.GLTF2:
    """Parse a glTF file (cached on path, size and mtime: pygltflib's JSON decoding takes ~1 s)."""
    if not path.is_file():
        raise InputError(f"{path}: glTF file not found; pass an existing .glb/.gltf with --glb")
    st = path.stat()
    return _load_cached(str(path.resolve()), st.st_size, st.st_mtime_ns)


@functools.lru_cache(maxsize=8)
def _load_cached(path: str, size: int, mtime_ns: int) -> pygltflib.GLTF2:
    try:
        return pygltflib.GLTF2().load(path)
    except Exception as exc:  # pygltflib raises assorted errors for non-glTF input
        raise InputError(f"{path}: not a readable glTF 2.0 file ({type(exc).__name__}: {exc}); pass a .glb or .gltf") from exc


def load_gltf(path: str | Path, clip: str | None = None, fps: float = 30.0, frames: int | None = None,
              to_object_frame: bool = True) -> AnimatedMesh:
    """Load a skinned glTF and sample one animation clip.

    Args:
        path: a ``.glb`` (or ``.gltf``) file.
        clip: animation name; None = the first clip (a model without animations gives its rest pose).
        fps: sampling rate, frames per second.
        frames: T, frames to sample at times k / fps from the clip's start, looping past its end;
            None = the clip's own length (duration * fps + 1).
        to_object_frame: rotate glTF's +z-front frame to this project's +x-front frame.

    Returns:
        An :class:`AnimatedMesh` (float32 vertices in the file's units, metres).

    Raises:
        InputError: missing/unreadable file, unknown clip name, no triangle mesh.
    """
    path = Path(path)
    gltf = _load(path)
    reader = _Reader(gltf, path)
    names = [a.name or f"clip{k}" for k, a in enumerate(gltf.animations)]
    if clip is None:
        clip_index = 0 if names else None
    elif clip in names:
        clip_index = names.index(clip)
    else:
        raise InputError(f"{path}: no animation clip named {clip!r}; choose one of {names} with --clip")
    if fps <= 0:
        raise InputError(f"{path}: fps must be > 0, got {fps}; pass --fps F with F > 0")
    if frames is not None and frames < 1:
        raise InputError(f"{path}: frames must be >= 1, got {frames}; pass --frames N with N >= 1")

    order, parent = _scene_nodes(gltf, path)
    anim, num_t = _sample_clip(reader, clip_index, fps, frames)
    glob = _global_transforms(gltf, order, parent, anim, num_t)
    rest = _global_transforms(gltf, order, parent, {}, 1)

    mesh_nodes = [i for i in order if gltf.nodes[i].mesh is not None]
    if not mesh_nodes:
        raise InputError(f"{path}: the scene has no mesh; export the model with its mesh")
    skin_ids = sorted({gltf.nodes[i].skin for i in mesh_nodes if gltf.nodes[i].skin is not None})
    # Joints: every skin's, in hierarchy order (parents first); non-skin models get one joint per mesh node.
    skin_nodes = list(dict.fromkeys(n for s in skin_ids for n in gltf.skins[s].joints)) if skin_ids else mesh_nodes
    pos_in_order = {n: k for k, n in enumerate(order)}
    joint_nodes = sorted(skin_nodes, key=lambda n: pos_in_order.get(n, len(order)))
    nj = len(joint_nodes)
    col_of_node = {n: k for k, n in enumerate(joint_nodes)}
    # per skin: its joint index -> column, and the inverse bind matrix of each column (identity where unused)
    col_of_skin = {s: np.array([col_of_node[n] for n in gltf.skins[s].joints]) for s in skin_ids}
    ibm = np.tile(np.eye(4), (max(len(skin_ids), 1), nj, 1, 1))
    for k, s in enumerate(skin_ids):
        if gltf.skins[s].inverseBindMatrices is not None:
            ibm[k, col_of_skin[s]] = reader.accessor(gltf.skins[s].inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1)
    parents = np.full(nj, -1, dtype=np.int32)
    for k, n in enumerate(joint_nodes):
        p = parent[n]
        while p >= 0 and p not in col_of_node:
            p = parent[p]
        parents[k] = col_of_node[p] if p >= 0 else -1

    pos_parts, face_parts, w_parts, col_parts, rigid_parts, skin_parts = [], [], [], [], [], []
    offset = 0
    for node_index in mesh_nodes:
        node = gltf.nodes[node_index]
        for prim in gltf.meshes[node.mesh].primitives:
            if prim.mode not in (None, 4):
                log.warning("%s: skipping a non-triangle primitive (mode %s)", path, prim.mode)
                continue
            attrs = prim.attributes
            if attrs.POSITION is None:
                continue
            p = reader.accessor(attrs.POSITION)
            nv = p.shape[0]
            idx = (reader.accessor(prim.indices, as_float=False).reshape(-1, 3).astype(np.int64)
                   if prim.indices is not None else np.arange(nv).reshape(-1, 3))
            w = np.zeros((nv, nj))
            if node.skin is not None and attrs.JOINTS_0 is not None and attrs.WEIGHTS_0 is not None:
                jj = reader.accessor(attrs.JOINTS_0, as_float=False).astype(np.int64)
                ww = reader.accessor(attrs.WEIGHTS_0)
                np.add.at(w, (np.repeat(np.arange(nv), 4), col_of_skin[node.skin][jj.reshape(-1)]), ww.reshape(-1))
                s = w.sum(1, keepdims=True)
                w = np.where(s > 0, w / np.where(s > 0, s, 1.0), 0.0)
                rigid_parts.append(np.full(nv, -1))
                skin_parts.append(np.full(nv, skin_ids.index(node.skin)))
            else:  # moves with its node; weight 1 on the nearest joint at or above it (none: a static part)
                holder = node_index
                while holder >= 0 and holder not in col_of_node:
                    holder = parent[holder]
                if holder >= 0:
                    w[:, col_of_node[holder]] = 1.0
                rigid_parts.append(np.full(nv, node_index))
                skin_parts.append(np.full(nv, -1))
            pos_parts.append(p)
            face_parts.append(idx + offset)
            w_parts.append(w)
            col_parts.append(_primitive_colours(reader, prim, nv))
            offset += nv
    if not pos_parts:
        raise InputError(f"{path}: no triangle primitive with POSITION found; export the mesh as triangles")
    bind = np.concatenate(pos_parts)
    faces = np.concatenate(face_parts)
    weights = np.concatenate(w_parts)
    rigid = np.concatenate(rigid_parts)
    skin_of = np.concatenate(skin_parts)
    colors = _linear_to_srgb(np.concatenate(col_parts))

    def skin_verts(g: np.ndarray) -> np.ndarray:  # g: (T, nodes, 4, 4) -> (T, V, 3)
        out = np.zeros((g.shape[0], bind.shape[0], 3))
        for k in range(len(skin_ids)):  # each skin with its own inverse bind matrices
            sel = skin_of == k
            mats = g[:, joint_nodes] @ ibm[k]  # (T, J, 4, 4)
            blend = np.einsum("vj,tjab->tvab", weights[sel], mats[:, :, :3, :], optimize=True)
            out[:, sel] = np.einsum("tvab,vb->tva", blend[..., :3], bind[sel]) + blend[..., 3]
        for node_index in np.unique(rigid[rigid >= 0]):
            sel = rigid == node_index
            m = g[:, node_index]
            out[:, sel] = np.einsum("tab,vb->tva", m[:, :3, :3], bind[sel]) + m[:, None, :3, 3]
        return out

    verts = skin_verts(glob)
    rest_verts = skin_verts(rest)[0]
    joints = glob[:, joint_nodes][..., :3, 3]  # (T, J, 3)
    rest_joints = rest[0][joint_nodes][:, :3, 3]  # (J, 3)
    if to_object_frame:
        r = GLTF_TO_OBJECT[:3, :3]
        verts, rest_verts, joints, rest_joints = (x @ r.T for x in (verts, rest_verts, joints, rest_joints))
    deforming = weights.max(0) > 0 if skin_ids else np.ones(nj, dtype=bool)
    jnames = [gltf.nodes[n].name or f"node{n}" for n in joint_nodes]
    log.info("%s: %d vertices, %d faces, %d joints (%d deforming), clip %r, %d frames",
             path.name, bind.shape[0], faces.shape[0], nj, int(deforming.sum()),
             names[clip_index] if clip_index is not None else "", num_t)
    return AnimatedMesh(
        rest_verts=rest_verts.astype(np.float32),
        faces=faces.astype(np.int32),
        verts=verts.astype(np.float32),
        joint_names=jnames,
        parents=parents,
        joints=joints.astype(np.float32),
        deforming=np.asarray(deforming, dtype=bool),
        weights=weights.astype(np.float32),
        rest_joints=rest_joints.astype(np.float32),
        fps=float(fps),
        clip_names=names,
        clip=names[clip_index] if clip_index is not None else "",
        colors=colors.astype(np.float32),
        source=f"glTF {path.name}",
    )


def _primitive_colours(reader: _Reader, prim, nv: int) -> np.ndarray:
    """(nv, 3) linear base colour: baseColorFactor x texture(UV) x COLOR_0."""
    col = np.ones((nv, 3))
    gltf = reader.gltf
    if prim.material is not None:
        pbr = gltf.materials[prim.material].pbrMetallicRoughness
        if pbr is not None:
            if pbr.baseColorFactor is not None:
                col *= np.asarray(pbr.baseColorFactor[:3], float)
            tex_info = pbr.baseColorTexture
            uv_acc = getattr(prim.attributes, f"TEXCOORD_{(tex_info.texCoord or 0) if tex_info else 0}", None)
            if tex_info is not None and uv_acc is not None:
                src = gltf.textures[tex_info.index].source
                img = _decode_image(reader, src) if src is not None else None
                if img is not None:
                    col *= _srgb_to_linear(_sample_texture(img, reader.accessor(uv_acc)))
    if prim.attributes.COLOR_0 is not None:
        c0 = reader.accessor(prim.attributes.COLOR_0)
        if c0.max() > 1.0:  # unnormalised integers (not spec-conformant); assume 8 or 16 bit
            c0 = c0 / (255.0 if c0.max() <= 255 else 65535.0)
        col *= c0[:, :3]
    return col


_TIP = re.compile(r"foot|hand|paw|hoof|toe|ear|tail|head|nose|jaw|lowerleg|leg02|leg2|forearm|middle", re.I)
_KNEE = re.compile(r"knee|lowerleg|forearm|lowerarm|leg02|leg2|shin|calf|hock", re.I)
_UPPER = re.compile(r"upperleg|upperarm|leg01|leg1$|thigh|shoulder|hip", re.I)


def gltf_keypoints(mesh: AnimatedMesh, max_points: int = 20) -> tuple[list[str], np.ndarray]:
    """Anatomical keypoints of a glTF model from its named deforming joints, as rest vertex indices.

    Rules, in priority order (later rules fill up to ``max_points``; repeated vertices dropped):
    1. ``<joint>_tip`` for end joints of the deforming tree (no deforming descendant): if the name
       suggests an extremity (foot, hand, paw, hoof, toe, ear, tail, head, nose, jaw, lower leg,
       forearm, a middle finger), the vertex whose strongest weight is that joint farthest from
       the joint (a toe, an ear's or the tail's tip, a fingertip); for other names, when that joint's skin reaches the ground
       (within 5 % of the height, +y up), its lowest vertex (a hoof's sole: the Quaternius IK
       foot bones). Ground-reaching ends come first;
    2. knees and elbows (knee, lower leg, forearm, lower arm, leg02, shin, calf, hock): the rest
       surface vertex nearest to the joint;
    3. the head joint, the first neck and tail joints, then upper legs / shoulders / hips.

    Returns:
        (names (K,), vertex indices int64 (K,)), K <= max_points.
    """
    names = mesh.joint_names
    deform = np.where(mesh.deforming)[0]
    has_child: set[int] = set()  # joints with a deforming descendant
    for j in deform:
        p = int(mesh.parents[j])
        while p >= 0 and p not in has_child:
            has_child.add(p)
            p = int(mesh.parents[p])
    owner = np.argmax(mesh.weights, axis=1)
    rest = mesh.rest_verts
    picked: list[tuple[str, int]] = []

    def nearest(j: int) -> int:
        return int(np.argmin(np.linalg.norm(rest - mesh.rest_joints[j], axis=1)))

    ground, height = float(rest[:, 1].min()), float(np.ptp(rest[:, 1]))
    for j in deform:  # feet of any name: end joints whose skin reaches the ground (y up)
        sel = np.where(owner == j)[0]
        if j in has_child or _TIP.search(names[j]) or sel.size == 0:
            continue
        if rest[sel, 1].min() <= ground + 0.05 * height:
            picked.append((f"{names[j]}_tip", int(sel[np.argmin(rest[sel, 1])])))
    for j in deform:
        sel = np.where(owner == j)[0]
        if j in has_child or not _TIP.search(names[j]) or sel.size == 0:
            continue
        far = sel[np.argmax(np.linalg.norm(rest[sel] - mesh.rest_joints[j], axis=1))]
        picked.append((f"{names[j]}_tip", int(far)))
    for j in deform:
        if _KNEE.search(names[j]):
            picked.append((names[j], nearest(j)))
    heads = [j for j in deform if re.search(r"head", names[j], re.I)]
    picked += [(names[j], nearest(j)) for j in heads[:1]]
    for part in ("neck", "tail"):
        chain = [j for j in deform if re.search(part, names[j], re.I)]
        if chain:  # the joint of the chain closest to the root (fewest ancestors)
            depth = [_depth(mesh.parents, j) for j in chain]
            j = chain[int(np.argmin(depth))]
            picked.append((names[j], nearest(j)))
    picked += [(names[j], nearest(j)) for j in deform if _UPPER.search(names[j])]
    out_names, out_idx, seen = [], [], set()
    for name, v in picked:
        if v in seen or name in out_names:
            continue
        seen.add(v)
        out_names.append(name)
        out_idx.append(v)
        if len(out_idx) == max_points:
            break
    return out_names, np.asarray(out_idx, dtype=np.int64)


def _depth(parents: np.ndarray, j: int) -> int:
    d = 0
    while parents[j] >= 0:
        j = int(parents[j])
        d += 1
    return d
