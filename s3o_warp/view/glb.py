"""A static triangle mesh with vertex colours as a binary glTF (GLB) in memory: how the viewer sends a coloured mesh
(viser's plain meshes carry one colour; its GLB nodes carry a file's own). No normals: the page computes them."""

from __future__ import annotations

import json
import struct

import numpy as np

_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
_FLOAT, _UNSIGNED_INT = 5126, 5125


def _pad(b: bytes, fill: bytes) -> bytes:
    return b + fill * (-len(b) % 4)


def mesh_glb(verts: np.ndarray, faces: np.ndarray, colors: np.ndarray) -> bytes:
    """GLB bytes of one mesh: ``verts`` (N, 3) positions, ``faces`` (F, 3) vertex indices, ``colors`` (N, 3) linear
    RGB in [0, 1] (glTF's ``COLOR_0``), under a plain rough white material."""
    v = np.ascontiguousarray(verts, dtype="<f4")
    c = np.ascontiguousarray(np.clip(colors, 0, 1), dtype="<f4")
    f = np.ascontiguousarray(faces, dtype="<u4")
    blobs = [v.tobytes(), c.tobytes(), f.tobytes()]
    views, offset = [], 0
    for blob, target in zip(blobs, (_ARRAY_BUFFER, _ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER)):
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(blob), "target": target})
        offset += len(blob)  # each blob's length is a multiple of 4
    doc = {
        "asset": {"version": "2.0", "generator": "s3o-warp viewer"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "COLOR_0": 1}, "indices": 2, "material": 0}]}],
        "materials": [{"pbrMetallicRoughness": {"baseColorFactor": [1, 1, 1, 1], "metallicFactor": 0.0,
                                                "roughnessFactor": 0.9}}],
        "accessors": [
            {"bufferView": 0, "componentType": _FLOAT, "count": len(v), "type": "VEC3",
             "min": v.min(0).tolist() if len(v) else [0, 0, 0], "max": v.max(0).tolist() if len(v) else [0, 0, 0]},
            {"bufferView": 1, "componentType": _FLOAT, "count": len(c), "type": "VEC3"},
            {"bufferView": 2, "componentType": _UNSIGNED_INT, "count": int(f.size), "type": "SCALAR"},
        ],
        "bufferViews": views,
        "buffers": [{"byteLength": offset}],
    }
    js = _pad(json.dumps(doc, separators=(",", ":")).encode(), b" ")
    binary = _pad(b"".join(blobs), b"\0")
    total = 12 + 8 + len(js) + 8 + len(binary)
    return (struct.pack("<4sII", b"glTF", 2, total) + struct.pack("<I4s", len(js), b"JSON") + js
            + struct.pack("<I4s", len(binary), b"BIN\0") + binary)
