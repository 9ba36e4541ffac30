"""The ops' index checks read a tensor's values back (a host sync on a GPU) once per fixed input, not every step:
``index_bounds`` keeps a tensor's bounds until it changes in place, ops record the bounds of what they produce, and
``cached`` keeps what is derived from a fixed input. Counted here on the CPU through ``torch.aminmax`` and
``mesh_edges``, the two ways the ops read indices back."""

from __future__ import annotations

import pytest
import torch
import trimesh

import s3o_warp.kernels._warp as W
import s3o_warp.kernels.regularisers as REG
from s3o_warp.kernels._warp import cached, index_bounds, set_index_bounds
from s3o_warp.ops import (
    interpolate,
    laplacian_loss,
    nearest_point,
    rasterize,
    soft_silhouette,
    symmetry_loss,
)


@pytest.fixture
def reads(monkeypatch):
    """Counts of value reads: ``aminmax`` (index bounds) and ``mesh_edges`` (the Laplacian's neighbour lists)."""
    n = {"aminmax": 0, "mesh_edges": 0}
    aminmax, mesh_edges = torch.aminmax, REG.mesh_edges

    def counted_aminmax(*a, **k):
        n["aminmax"] += 1
        return aminmax(*a, **k)

    def counted_edges(*a, **k):
        n["mesh_edges"] += 1
        return mesh_edges(*a, **k)

    monkeypatch.setattr(W.torch, "aminmax", counted_aminmax)
    monkeypatch.setattr(REG, "mesh_edges", counted_edges)
    return n


def test_index_bounds_read_once_per_version(reads):
    t = torch.tensor([[3, 1], [7, 2]])
    wide = (-100, 100)
    assert index_bounds(t, wide) == (1, 7) and reads["aminmax"] == 1
    assert index_bounds(t, wide) == (1, 7) and reads["aminmax"] == 1
    assert index_bounds(t[1:], wide) == (1, 7) and reads["aminmax"] == 1  # a view: its base's bounds hold
    assert index_bounds(t[1:], (0, 5)) == (2, 7) and reads["aminmax"] == 2  # ... unless they fail the check: read
    t[0, 0] = 9  # an in-place change (through the tensor or a view) is seen
    assert index_bounds(t, wide) == (1, 9) and reads["aminmax"] == 3
    t[1:].fill_(-4)
    assert index_bounds(t[1:], wide) == (-4, -4) and reads["aminmax"] == 4
    u = torch.tensor([0, 5])
    set_index_bounds(u, -1, 10)  # recorded by the op that made it: no read
    assert index_bounds(u, wide) == (-1, 10) and reads["aminmax"] == 4
    with torch.inference_mode():  # no version counter: read every time, nothing kept
        v = torch.tensor([4, 6])
        assert index_bounds(v, wide) == (4, 6) and index_bounds(v, wide) == (4, 6) and reads["aminmax"] == 6


def test_cached_recomputes_after_an_in_place_change():
    t = torch.arange(4)
    calls = []

    def fn():
        calls.append(1)
        return int(t.sum())

    assert cached(t, "sum", fn) == 6 and cached(t, "sum", fn) == 6 and len(calls) == 1
    t += 1
    assert cached(t, "sum", fn) == 10 and len(calls) == 2
    assert cached(t, "other", lambda: 0) == 0  # keys are independent


def _step(verts, faces, K, plane, S=24):
    """The ops of a joint step that take indices: silhouette, z-buffer + interpolation (of a slice too), the
    coverage loss's nearest point on the frames of a nonzero(), Laplacian, symmetry."""
    soft_silhouette(verts, faces, K, (S, S), sigma=1.0).sum()
    face_index, bary, _ = rasterize(verts, faces, K, (S, S))
    interpolate(verts, faces, face_index, bary)
    interpolate(verts[:-1], faces, face_index[:-1], bary[:-1])
    idx = (face_index < 0).nonzero()
    frame = idx[:, 0]
    set_index_bounds(frame, 0, verts.shape[0] - 1)
    xy = verts[..., :2] * 10 + S / 2
    nearest_point(idx[:, [2, 1]].float(), frame, xy.contiguous())
    laplacian_loss(verts[0], faces)
    symmetry_loss(verts[0], plane)


def test_a_step_reads_fixed_inputs_only_once(reads):
    mesh = trimesh.creation.icosphere(subdivisions=1, radius=0.4)
    v0 = torch.tensor(mesh.vertices, dtype=torch.float32) + torch.tensor([0.0, 0.0, 2.5])
    verts = torch.stack([v0, v0 + 0.05])
    faces = torch.tensor(mesh.faces, dtype=torch.int64)
    K = torch.tensor([[20.0, 0.0, 11.5], [0.0, 20.0, 11.5], [0.0, 0.0, 1.0]])
    plane = (torch.tensor([1.0, 0.0, 0.0]), 0.0)
    _step(verts, faces, K, plane)
    first = dict(reads)
    assert first["aminmax"] >= 1 and first["mesh_edges"] == 1
    for _ in range(2):
        _step(verts + 0.01, faces, K, plane)  # new vertices every step, the same faces and plane
    assert reads == first  # no index read back, no neighbour lists rebuilt
    faces[0, 0] = len(v0)  # changed in place to an out-of-range index: checked again, and refused
    with pytest.raises(ValueError, match="faces"):
        soft_silhouette(verts, faces, K, (24, 24))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (torch's sync debug mode)")
def test_cuda_ops_with_known_bounds_do_not_sync():
    """On a GPU, the index-taking ops a step repeats make no host sync once their fixed inputs were checked:
    torch's sync debug mode raises on any."""
    dev = torch.device("cuda")
    mesh = trimesh.creation.icosphere(subdivisions=1, radius=0.4)
    v0 = torch.tensor(mesh.vertices, dtype=torch.float32, device=dev) + torch.tensor([0.0, 0.0, 2.5], device=dev)
    verts = torch.stack([v0, v0 + 0.05])
    faces = torch.tensor(mesh.faces, dtype=torch.int64, device=dev)
    K = torch.tensor([[20.0, 0.0, 11.5], [0.0, 20.0, 11.5], [0.0, 0.0, 1.0]], device=dev)
    plane = (torch.tensor([1.0, 0.0, 0.0], device=dev), 0.0)
    face_index, bary, _ = rasterize(verts, faces, K, (24, 24))
    laplacian_loss(verts[0], faces)
    symmetry_loss(verts[0], plane)
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        interpolate(verts + 0.01, faces, face_index, bary)
        interpolate(verts[:-1], faces, face_index[:-1], bary[:-1])
        laplacian_loss(verts[0] + 0.01, faces)
        symmetry_loss(verts[0] + 0.01, plane)
    finally:
        torch.cuda.set_sync_debug_mode(0)
