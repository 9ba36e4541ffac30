"""Even resampling of the canonical mesh: the same closed surface, vertices spread about uniformly.

S3O (appendix B) resamples the canonical mesh every epoch so that optimisation does not leave
vertices bunched in some places and sparse in others (LASR and S3O use Manifold for this). Here the
surface is rebuilt from its own signed distance field: SDF of the current mesh on a cubic grid
(``s3o_warp.kernels.sdf.closest_point``, winding-number sign) -> marching cubes at level 0
(``skimage.measure.marching_cubes``) -> the largest connected component -> light Taubin smoothing
-> each vertex moved onto its closest point of the old surface -> one common offset along the
normals that gives back the old volume (so resampling every epoch does not shrink the mesh).
Marching-cubes vertices sit on grid edges that cross the surface, so their density follows the
grid, not the old mesh. Per-vertex attributes (colour logits) move to the new vertices through the
closest point of the old surface (its face and barycentric weights).

A part thinner than about one grid cell (a thin leg, an ear) falls apart into specks that the
largest-component step drops. That is detected (old vertices far from the new surface) and repaired
by marching a slightly dilated surface (level +offset, which thickens thin parts; the projection
puts the vertices back on the true surface), then by a finer grid.

Object frame and units are the input's; with ``symmetric_z`` the grid is mirror-symmetric about the
plane z = 0 (the model's symmetry plane, see ``s3o_warp.coarse.lift``) and its two halves are
marched separately, the lower one as the mirror image of an upper one, so a mirror-symmetric mesh
gets a mirror-symmetric triangulation and stays mirror-symmetric vertex for vertex.

``method="isotropic"`` skips the grid: pymeshlab's isotropic explicit remeshing works on the surface
itself (so thin parts stay, whatever the count), followed by the same projection, volume offset and
attribute transfer. It keeps the input's topology: self-intersections stay, and the triangulation is not
mirror-symmetric. The fit tries the methods of :data:`METHODS` in turn on one mesh.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
import torch
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from skimage.measure import marching_cubes

from s3o_warp import interrupt
from s3o_warp.errors import ConfigError, InputError
from s3o_warp.ops import closest_point

log = logging.getLogger(__name__)

__all__ = ["METHODS", "ResampleSettings", "even_resample"]

METHODS = ("marching", "isotropic")
"""The methods the fit tries in turn on one mesh, each when the one before is not used (it would lose more than
``max_lost`` of the old vertices): marching first (LASR's and S3O's way, a mirror-symmetric triangulation), then
isotropic, which remeshes the surface itself, so a surface folded or crumpled finer than marching's grid survives.
Where marching works (the synthetic Fox and horse) the second never runs; where it fails (DAVIS cows on some
machines) the fit gets an even mesh instead of keeping the coarse one (cows seed 0: PCK-T 82.5 against 82.8 with
the coarse mesh kept, one seed's spread; the dog's seed 2 at 192 px: 66.9 isotropic against 54.5 kept)."""

_MC_VERTS_PER_AREA = 1.5
"""Marching cubes makes about 1.5 vertices per h^2 of surface (mean of |nx| + |ny| + |nz| over directions)."""

_ISO_VERTS_PER_AREA = 1.7
"""First guess of the vertices per l^2 of surface that isotropic remeshing at target edge length l makes: an
equilateral mesh has 1.15; measured 1.2 on a smooth ball and 2.5 on a fitted Fox, whose thin parts and
creases keep extra vertices (edge collapses there would leave the surface); the count search corrects it."""


@dataclass
class ResampleSettings:
    """The constants of the even resampling of the canonical mesh (:func:`even_resample`): the method's, not a
    user's; the fit sets ``method`` (:data:`METHODS`) and ``target_vertices`` (``motion.resample_vertices``). Tests
    build their own to vary one."""

    method: str = "marching"
    """marching: rebuild the surface from its signed distance field (marching cubes, like the Manifold tool LASR
    and S3O use; a part thinner than the grid needs the dilate/refine repair below). isotropic: remesh the
    surface itself (pymeshlab's isotropic explicit remeshing: edge splits, collapses, flips and tangential
    smoothing towards one edge length), which keeps thin parts and needs no grid."""
    target_vertices: int | None = None
    """Vertex count the resampled mesh aims at; None = the input's count (each call lands within vertex_tolerance
    of it, so repeated calls random-walk: pass a number when resampling every epoch)."""
    vertex_tolerance: float = 0.15
    """Stop the grid-spacing search when the vertex count is within this fraction of the target."""
    trials: int = 4
    """At most this many grid spacings are tried while searching for the target count."""
    taubin_iterations: int = 10
    """Taubin smoothing passes on the marching-cubes mesh, even (shrink and inflate alternate; an odd count
    ends on a shrink); 0 = none. Evens out the marching-cubes sliver triangles."""
    taubin_lambda: float = 0.5
    """Taubin shrink step."""
    taubin_nu: float = 0.53
    """Taubin inflate step (nu > lambda keeps the volume)."""
    project: bool = True
    """Move each new vertex onto its closest point of the old surface (marching cubes cuts corners and smoothing
    moves vertices: without it the volume drops ~1% per resampling at ~600 vertices); see min_area_kept."""
    margin_cells: float = 2.0
    """Empty grid cells around the mesh's bounding box (>= 1 so the surface closes)."""
    symmetric_z: bool = True
    """Make the grid and the marching-cubes triangulation mirror-symmetric about z = 0 (and move mirror-image
    vertices alike), so a mirror-symmetric mesh stays so, vertex for vertex (the symmetry loss pairs each
    vertex with the nearest to its reflection)."""
    mirror_tolerance: float = 0.05
    """Two marching-cubes vertices are mirror partners when one's reflection is within this x the spacing of the other."""
    coverage_distance: float = 1.5
    """An old vertex farther than this x the grid spacing from the new surface counts as lost (a thin part that vanished)."""
    coverage_fraction: float = 0.002
    """Repair (dilate, then refine) while more than this fraction of the old vertices is lost (1% would let
    the synthetic quadruped's tail tip go at 2000 vertices)."""
    dilate_steps: tuple[float, ...] = (0.25, 0.5)
    """Repair, first: march the surface dilated by each of these x the spacing in turn (thin parts thicken;
    the projection brings vertices back). Needs project; () = never; gaps under 2 x offset may be bridged."""
    refine_step: float = 0.8
    """Repair, then: multiply the spacing by this per step (about 1 / refine_step^2 more vertices), at the
    largest dilation."""
    max_vertices_factor: float = 2.0
    """Refinement stops before the vertex count would pass this x the target, give or take vertex_tolerance
    (a repair candidate over that is not used)."""
    max_lost: float = 0.05
    """A result that still leaves more than this fraction of the old vertices off the new surface after every
    repair is not used: the input mesh comes back as it is, with a warning (1 = always use the best attempt). A
    fitted DAVIS cow whose surface is folded or crumpled finer than the grid would lose 26-49 % at the vertex cap;
    the synthetic Fox and horse lose 0.2-4.1 % at their worst."""
    isotropic_iterations: int = 6
    """method=isotropic: remeshing passes per trial."""
    isotropic_surface_distance: float = 0.2
    """method=isotropic: an edge flip or collapse is refused when it would move the surface more than this x the
    target edge length from the old one."""
    keep_volume: bool = True
    """Finally offset every vertex along its normal by one common distance so the volume equals the old mesh's
    (vertices on the old surface make an inscribed polygon: ~1% smaller per resampling on thin legs)."""
    max_volume_offset: float = 0.25
    """... unless that distance exceeds this x the spacing (the old mesh is then not one closed surface)."""
    min_area_kept: float = 0.05
    """The projection keeps a vertex where marching cubes put it when one of its faces would keep less than
    this fraction of its area along its old normal (a flip, or a collapse into a crease)."""
    max_grid_points: int = 8_000_000
    """Largest distance grid (samples) ever built (~100 MB of coordinates); a mesh that needs more is refused."""
    winding_accuracy: float = 2.0
    """Accuracy of the fast winding number that signs the distance field (larger = slower, more exact)."""

    def __post_init__(self) -> None:
        if self.method not in ("marching", "isotropic"):
            raise ConfigError(f"ResampleSettings.method must be 'marching' or 'isotropic', got {self.method!r}")
        if self.isotropic_iterations < 1:
            raise ConfigError(f"ResampleSettings.isotropic_iterations must be >= 1, got {self.isotropic_iterations}")
        if not self.isotropic_surface_distance > 0:
            raise ConfigError(f"ResampleSettings.isotropic_surface_distance must be > 0, got "
                              f"{self.isotropic_surface_distance}")
        if self.target_vertices is not None and self.target_vertices < 20:
            raise ConfigError(f"ResampleSettings.target_vertices must be >= 20 or None, got {self.target_vertices}")
        if not 0 < self.vertex_tolerance < 1:
            raise ConfigError(f"ResampleSettings.vertex_tolerance must be in (0, 1), got {self.vertex_tolerance}")
        if self.trials < 1:
            raise ConfigError(f"ResampleSettings.trials must be >= 1, got {self.trials}")
        if self.taubin_iterations < 0 or self.taubin_iterations % 2:
            raise ConfigError(f"ResampleSettings.taubin_iterations must be even and >= 0 (shrink/inflate pairs), "
                              f"got {self.taubin_iterations}")
        if not 0 < self.taubin_lambda <= 1:
            raise ConfigError(f"ResampleSettings.taubin_lambda must be in (0, 1], got {self.taubin_lambda}")
        if self.taubin_nu < self.taubin_lambda:
            raise ConfigError(f"ResampleSettings.taubin_nu must be >= taubin_lambda ({self.taubin_lambda}) so the "
                              f"volume does not shrink, got {self.taubin_nu}")
        if self.margin_cells < 1:
            raise ConfigError(f"ResampleSettings.margin_cells must be >= 1, got {self.margin_cells}")
        if self.mirror_tolerance < 0:
            raise ConfigError(f"ResampleSettings.mirror_tolerance must be >= 0, got {self.mirror_tolerance}")
        if self.coverage_distance <= 0:
            raise ConfigError(f"ResampleSettings.coverage_distance must be > 0, got {self.coverage_distance}")
        if not 0 <= self.coverage_fraction < 1:
            raise ConfigError(f"ResampleSettings.coverage_fraction must be in [0, 1), got {self.coverage_fraction}")
        if not 0 <= self.max_lost <= 1:
            raise ConfigError(f"ResampleSettings.max_lost must be in [0, 1] (1 = always use the best attempt), got "
                              f"{self.max_lost}")
        if any(not 0 < d <= 2 for d in self.dilate_steps) or list(self.dilate_steps) != sorted(self.dilate_steps):
            raise ConfigError(f"ResampleSettings.dilate_steps must be increasing offsets in (0, 2] (x the spacing), "
                              f"got {self.dilate_steps}")
        if self.max_volume_offset < 0:
            raise ConfigError(f"ResampleSettings.max_volume_offset must be >= 0, got {self.max_volume_offset}")
        if not 0 <= self.min_area_kept < 1:
            raise ConfigError(f"ResampleSettings.min_area_kept must be in [0, 1), got {self.min_area_kept}")
        if not 0 < self.refine_step < 1:
            raise ConfigError(f"ResampleSettings.refine_step must be in (0, 1), got {self.refine_step}")
        if self.max_vertices_factor < 1:
            raise ConfigError(f"ResampleSettings.max_vertices_factor must be >= 1, got {self.max_vertices_factor}")
        if self.max_grid_points < 1000:
            raise ConfigError(f"ResampleSettings.max_grid_points must be >= 1000, got {self.max_grid_points}")
        if self.winding_accuracy <= 0:
            raise ConfigError(f"ResampleSettings.winding_accuracy must be > 0, got {self.winding_accuracy}")


# --------------------------------------------------------------------------------------------------
# steps


def _grid_axes(lo: np.ndarray, hi: np.ndarray, h: float, margin: float, symmetric_z: bool) -> list[np.ndarray]:
    """Sample coordinates of a cubic grid of spacing h covering [lo, hi] plus ``margin`` cells (z symmetric)."""
    axes = []
    for i in range(3):
        if i == 2 and symmetric_z:
            half = max(abs(lo[2]), abs(hi[2])) + margin * h
            k = math.ceil(half / h)
            axes.append(h * np.arange(-k, k + 1, dtype=np.float64))  # z_j = -z_{-j} exactly
        else:
            a, b = lo[i] - margin * h, hi[i] + margin * h
            n = math.ceil((b - a) / h) + 1
            axes.append(a + h * np.arange(n, dtype=np.float64))
    return axes


def _largest_component(verts: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """The connected component with the most faces (vertices re-indexed), and the component count."""
    n = len(verts)
    i, j = faces.ravel(), faces[:, [1, 2, 0]].ravel()
    graph = coo_matrix((np.ones(len(i), np.int8), (i, j)), shape=(n, n))
    count, labels = connected_components(graph, directed=False)
    if count == 1:
        return verts, faces, 1
    face_label = labels[faces[:, 0]]
    keep = int(np.bincount(face_label, minlength=count).argmax())
    kept = faces[face_label == keep]
    used = np.unique(kept)
    remap = np.full(n, -1, np.int64)
    remap[used] = np.arange(len(used))
    return verts[used], remap[kept], int(count)


class _GridTooLarge(Exception):
    """The distance grid would exceed ``max_grid_points``."""


@dataclass
class _Surface:
    """One marching-cubes surface of the old mesh's SDF at spacing h (largest component, not smoothed)."""

    verts: np.ndarray
    faces: np.ndarray
    h: float
    dilate: float
    components: int


@dataclass
class _Candidate:
    """A finished resampled mesh (torch, float32 / int64 on the input's device) and how well it covers the old one."""

    verts: torch.Tensor
    faces: torch.Tensor
    surf: _Surface
    lost: float
    kept: int
    partner: np.ndarray | None


def _march(verts_t: torch.Tensor, faces_t: torch.Tensor, lo: np.ndarray, hi: np.ndarray, h: float,
           s: ResampleSettings, dilate: float = 0.0) -> _Surface | None:
    """SDF on the grid of spacing h -> marching cubes at level dilate x h -> largest component (None: no surface).
    A stop request (:mod:`s3o_warp.interrupt`) ends the resampling here, between grids."""
    interrupt.check("the even resampling")
    axes = _grid_axes(lo, hi, h, s.margin_cells, s.symmetric_z)
    shape = tuple(len(a) for a in axes)
    if math.prod(shape) > s.max_grid_points:
        raise _GridTooLarge(f"a grid of spacing {h:.4g} has {'x'.join(map(str, shape))} samples, "
                            f"over ResampleSettings.max_grid_points={s.max_grid_points}")
    dev, dt = verts_t.device, torch.float32
    grid = torch.stack(torch.meshgrid(*(torch.as_tensor(a, dtype=dt, device=dev) for a in axes), indexing="ij"), -1)
    dist, _, _ = closest_point(verts_t, faces_t, grid.reshape(-1, 3), accuracy=s.winding_accuracy)
    # > 0 inside the surface dilated by dilate x h, as marching cubes likes it
    inside = dilate * h - dist.reshape(shape).cpu().numpy().astype(np.float64)
    if not (inside.max() > 0 > inside.min()):
        return None
    inside[inside == 0.0] = 1e-9 * h  # no vertex exactly on a grid sample (duplicate vertices)
    origin = np.array([a[0] for a in axes])
    if s.symmetric_z:
        mv, mf = _march_halves(inside, h, origin)
    else:
        mv, mf, _, _ = marching_cubes(inside, level=0.0, spacing=(h, h, h))
        mv, mf = mv + origin, mf.astype(np.int64)
    if len(mf) == 0:
        return None
    mv, mf, count = _largest_component(mv, mf)
    return _Surface(mv, mf, h, dilate, count)


def _march_halves(inside: np.ndarray, h: float, origin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Marching cubes of the z >= 0 and z <= 0 halves of a z-symmetric grid, the lower one mirrored to look
    like an upper one, so a mirror-symmetric field gets a mirror-symmetric triangulation (the case
    tables are not mirror-symmetric); the halves share their samples on z = 0 and are welded there."""
    kc = (inside.shape[2] - 1) // 2  # the sample plane z = 0
    parts = []
    for sign, half in ((1.0, inside[:, :, kc:]), (-1.0, inside[:, :, kc::-1])):
        if half.shape[2] < 2 or not (half.max() > 0 > half.min()):
            continue
        mv, mf, _, _ = marching_cubes(np.ascontiguousarray(half), level=0.0, spacing=(h, h, h))
        mv = mv + np.array([origin[0], origin[1], 0.0])
        if sign < 0:  # mirror back; a reflection turns the winding around
            mv[:, 2] = -mv[:, 2]
            mf = mf[:, ::-1]
        parts.append((mv, mf.astype(np.int64)))
    if not parts:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    if len(parts) == 1:
        return parts[0]
    (v1, f1), (v2, f2) = parts
    verts = np.concatenate([v1, v2])
    faces = np.concatenate([f1, f2 + len(v1)])
    # weld the seam: vertices on z = 0 made by both halves from the same two samples (same position)
    on_plane = np.nonzero(verts[:, 2] == 0.0)[0]
    keys = np.round(verts[on_plane, :2] / h * 1e6).astype(np.int64)
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    remap = np.arange(len(verts))
    remap[on_plane] = on_plane[first[inverse.ravel()]]
    faces = remap[faces]
    used = np.unique(faces)
    compact = np.full(len(verts), -1, np.int64)
    compact[used] = np.arange(len(used))
    return verts[used], compact[faces]


def _mirror_partners(verts: np.ndarray, tol: float) -> np.ndarray:
    """(V,) index of each vertex's mirror image about z = 0 (mutual nearest, within tol), -1 if none."""
    mirrored = verts * np.array([1.0, 1.0, -1.0])
    dist, j = cKDTree(verts).query(mirrored, distance_upper_bound=tol)
    ok = np.isfinite(dist)
    partner = np.where(ok, j, -1)
    ok &= partner[np.where(ok, j, 0)] == np.arange(len(verts))  # mutual
    return np.where(ok, partner, -1)


def _symmetrise(moves: np.ndarray, partner: np.ndarray | None) -> np.ndarray:
    """Average each paired vertex's displacement with its partner's mirrored one (z = 0 plane)."""
    if partner is None:
        return moves
    paired = partner >= 0
    out = moves.copy()
    out[paired] = 0.5 * (moves[paired] + moves[partner[paired]] * np.array([1.0, 1.0, -1.0]))
    return out


def _smooth(surf: _Surface, s: ResampleSettings):
    """Orient counter-clockwise seen from outside, Taubin-smooth: (trimesh.Trimesh, mirror partners or None).

    With ``symmetric_z``, marching cubes' vertices come in mirror pairs wherever the field is mirror-
    symmetric, but its triangulation is not, so Taubin would move partners differently; their
    displacements are symmetrised (averaged with the mirrored partner's).
    """
    mesh = trimesh.Trimesh(surf.verts, surf.faces, process=True)
    if mesh.volume < 0:
        mesh.invert()
    partner = None
    if s.symmetric_z:
        partner = _mirror_partners(np.asarray(mesh.vertices), s.mirror_tolerance * surf.h)
        partner = partner if (partner >= 0).any() else None
    if s.taubin_iterations > 0:
        before = np.array(mesh.vertices)
        trimesh.smoothing.filter_taubin(mesh, lamb=s.taubin_lambda, nu=s.taubin_nu, iterations=s.taubin_iterations)
        mesh.vertices = before + _symmetrise(np.asarray(mesh.vertices) - before, partner)
    return mesh, partner


def _project(verts: torch.Tensor, faces: torch.Tensor, onto: torch.Tensor, min_area: float) -> tuple[torch.Tensor, int]:
    """Move vertices to ``onto``, except those of faces that would keep < min_area of their area along
    their old normal (flipped or collapsed); returns the vertices and how many were kept in place."""

    def normals(x):
        t = x[faces]
        return torch.linalg.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])

    before = normals(verts)
    area2 = (before * before).sum(-1)
    live = area2 > 0  # a face with all its vertices kept is unchanged, so the loop below ends
    moved = onto.clone()
    bad = ((normals(moved) * before).sum(-1) <= min_area * area2) & live
    while bad.any():  # keeping a vertex can spoil a neighbour face: repeat
        corners = faces[bad].reshape(-1)
        moved[corners] = verts[corners]
        bad = ((normals(moved) * before).sum(-1) <= min_area * area2) & live
    kept = int(((moved == verts).all(-1) & (onto != verts).any(-1)).sum())
    return moved, kept


def _finish(surf: _Surface, v: torch.Tensor, f: torch.Tensor, s: ResampleSettings) -> _Candidate:
    """Smooth, project onto the old surface (v, f), measure the old vertices' distance to the result."""
    mesh, partner = _smooth(surf, s)
    return _onto_old(np.asarray(mesh.vertices), np.asarray(mesh.faces), v, f, s, surf, partner)


def _onto_old(verts: np.ndarray, faces: np.ndarray, v: torch.Tensor, f: torch.Tensor, s: ResampleSettings,
              surf: _Surface, partner: np.ndarray | None) -> _Candidate:
    """A new mesh projected onto the old surface (v, f) with ``s.project``, and the old vertices' loss from it
    (farther than ``coverage_distance`` x ``surf.h``)."""
    dev = v.device
    nv = torch.as_tensor(verts, dtype=torch.float32, device=dev)
    nf = torch.as_tensor(faces, dtype=torch.int64, device=dev)
    kept = 0
    if s.project:
        _, face, bary = closest_point(v, f, nv, accuracy=s.winding_accuracy)
        onto = (bary[:, :, None] * v[f[face.clamp_min(0)]]).sum(1)  # face -1: every old face a sliver
        if partner is not None:  # closest points of mirror partners may differ (ties on the plane)
            moves = _symmetrise((onto - nv).double().cpu().numpy(), partner)
            onto = nv + torch.as_tensor(moves, dtype=torch.float32, device=dev)
        nv, kept = _project(nv, nf, onto, s.min_area_kept)
    dist, _, _ = closest_point(nv, nf, v, accuracy=s.winding_accuracy)
    lost = float((dist.abs() > s.coverage_distance * surf.h).float().mean())
    return _Candidate(nv, nf, surf, lost, kept, partner)


def _volume(verts: torch.Tensor, faces: torch.Tensor) -> float:
    """Signed volume of a closed mesh (divergence theorem, float64)."""
    t = verts.double()[faces]
    return float((t[:, 0] * torch.linalg.cross(t[:, 1], t[:, 2])).sum() / 6.0)


def _match_volume(c: _Candidate, volume: float, s: ResampleSettings, name: str) -> torch.Tensor:
    """The candidate's vertices moved along their (mirror-symmetrised) normals by the one distance that
    gives it ``volume`` (to first order: volume difference / area)."""
    t = c.verts.double()[c.faces]
    n_face = torch.linalg.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])  # 2 x area x unit normal
    area = float(n_face.norm(dim=1).sum()) / 2
    offset = (volume - _volume(c.verts, c.faces)) / max(area, 1e-30)
    if not abs(offset) <= s.max_volume_offset * c.surf.h:
        log.debug("%s: volume not matched: it needs an offset of %.3g (spacing %.3g)", name, offset, c.surf.h)
        return c.verts
    n_vert = torch.zeros_like(c.verts, dtype=torch.float64).index_add_(0, c.faces.reshape(-1), n_face.repeat_interleave(3, 0))
    n_vert = torch.nn.functional.normalize(n_vert, dim=1)
    moves = _symmetrise((offset * n_vert).cpu().numpy(), c.partner)
    log.debug("%s: vertices offset by %.3g along their normals to keep the volume", name, offset)
    return c.verts + torch.as_tensor(moves, dtype=torch.float32, device=c.verts.device)


def _check_inputs(name: str, verts, faces, attributes) -> None:
    if not isinstance(verts, torch.Tensor) or verts.dim() != 2 or verts.shape[1] != 3 or not verts.dtype.is_floating_point:
        raise InputError(f"{name}(): verts must be a float (N, 3) tensor, got {getattr(verts, 'shape', type(verts))}")
    if not isinstance(faces, torch.Tensor) or faces.dim() != 2 or faces.shape[1] != 3 or faces.dtype.is_floating_point:
        raise InputError(f"{name}(): faces must be an integer (F, 3) tensor, got {getattr(faces, 'shape', type(faces))}")
    if verts.shape[0] == 0 or faces.shape[0] == 0:
        raise InputError(f"{name}(): the mesh is empty ({verts.shape[0]} vertices, {faces.shape[0]} faces); "
                         "resample a non-empty closed mesh")
    if attributes is not None and (not isinstance(attributes, torch.Tensor) or attributes.dim() != 2
                                   or attributes.shape[0] != verts.shape[0] or not attributes.dtype.is_floating_point):
        raise InputError(f"{name}(): attributes must be a float (N, C) tensor with N = {verts.shape[0]} vertices, "
                         f"got {getattr(attributes, 'dtype', type(attributes))} {tuple(getattr(attributes, 'shape', ()))}")


def _marching(v: torch.Tensor, f: torch.Tensor, lo: np.ndarray, hi: np.ndarray, target: int, area: float,
              s: ResampleSettings, name: str) -> _Candidate:
    """Steps 1-6 of :func:`even_resample` with ``method="marching"``: spacing search, marching cubes, repair."""
    # 1-3: spacing search for the vertex count
    h = math.sqrt(_MC_VERTS_PER_AREA * area / target)
    best: tuple[float, _Surface] | None = None
    for trial in range(s.trials):
        try:
            surf = _march(v, f, lo, hi, h, s)
        except _GridTooLarge as e:
            if best is None:
                raise InputError(f"{name}(): {e}; the mesh is very thin or elongated for target_vertices={target}: "
                                 "lower the target (motion.resample_vertices)") from None
            break
        if surf is None:  # no grid sample inside: a part thinner than the grid, or no inside at all
            log.debug("%s: trial %d spacing %.4g -> no surface", name, trial, h)
            h *= 0.5
            continue
        err = abs(len(surf.verts) - target) / target
        log.debug("%s: trial %d spacing %.4g -> %d vertices (%d components)", name, trial, h, len(surf.verts),
                  surf.components)
        if best is None or err < best[0]:
            best = (err, surf)
        if err <= s.vertex_tolerance:
            break
        h *= math.sqrt(len(surf.verts) / target)
    if best is None:
        raise InputError(f"{name}(): no inside found (the winding number never exceeds 1/2 on the grid): the mesh "
                         "is not closed or its faces wind inconsistently; resample a closed mesh")
    base = best[1]

    # 4-6: smooth, project, and repair lost parts (7: volume)
    result = _finish(base, v, f, s)
    tried = [result]
    ladder = [(base.h, d) for d in (s.dilate_steps if s.project else ())]
    cap = int(s.max_vertices_factor * target * (1 + s.vertex_tolerance))
    h_min = base.h * math.sqrt(len(base.verts) / (s.max_vertices_factor * target))  # count grows as 1 / h^2
    h_next, dil = base.h * s.refine_step, (s.dilate_steps[-1] if s.project and s.dilate_steps else 0.0)
    while h_next > h_min * 1.001:
        ladder.append((h_next, dil))
        h_next *= s.refine_step
    if h_min < base.h * 0.99 and (not ladder or ladder[-1][0] > h_min * 1.001):
        ladder.append((h_min, dil))
    for h_try, d_try in ladder:
        if result.lost <= s.coverage_fraction:
            break
        log.debug("%s: %.2f%% of the old vertices lost at spacing %.4g, dilation %.2f; trying %.4g, %.2f", name,
                  100 * result.lost, result.surf.h, result.surf.dilate, h_try, d_try)
        try:
            surf = _march(v, f, lo, hi, h_try, s, dilate=d_try)
        except _GridTooLarge as e:
            log.debug("%s: stopped repairing: %s", name, e)
            break
        if surf is not None and len(surf.verts) > cap:
            log.debug("%s: %d vertices at spacing %.4g, dilation %.2f: over the cap of %d, stopped repairing", name,
                      len(surf.verts), h_try, d_try, cap)
            break
        if surf is not None:
            tried.append(_finish(surf, v, f, s))
            result = tried[-1]
    n = len(result.verts)
    if result.lost <= s.coverage_fraction and result.surf.dilate > 0 and abs(n - target) > s.vertex_tolerance * target:
        # a dilated surface has more vertices: one more try at the spacing that brings the count back
        h_fit = result.surf.h * math.sqrt(n / target)
        try:
            surf = _march(v, f, lo, hi, h_fit, s, dilate=result.surf.dilate)
        except _GridTooLarge:
            surf = None
        if surf is not None:
            fit = _finish(surf, v, f, s)
            log.debug("%s: dilated surface at spacing %.4g: %d vertices, %.2f%% lost", name, h_fit, len(fit.verts),
                      100 * fit.lost)
            if fit.lost <= s.coverage_fraction:
                result = fit
    if result.lost > s.coverage_fraction:
        result = min(tried, key=lambda c: c.lost)  # first (coarsest) of the equally good
        log.warning("%s: %.1f%% of the old vertices stay farther than %.3g from the new surface (a part thinner "
                    "than the grid?) after dilating by %s and refining to %d vertices; a higher target "
                    "(motion.resample_vertices) may keep it", name, 100 * result.lost,
                    s.coverage_distance * result.surf.h, list(s.dilate_steps), cap)

    return result


def _isotropic(v: torch.Tensor, f: torch.Tensor, target: int, area: float, s: ResampleSettings,
               name: str) -> _Candidate:
    """Steps 1-6 of :func:`even_resample` with ``method="isotropic"``: pymeshlab's isotropic explicit remeshing
    at the edge length l that gives the target count (searched like the grid spacing), then the projection."""
    try:
        import pymeshlab  # imported here: loading it takes a second, and most fits never remesh isotropically
    except ImportError as e:
        raise InputError(f"isotropic remeshing needs pymeshlab, a dependency of s3o-warp that does not import "
                         f"({e}); reinstall it: pip install pymeshlab") from None
    X = v.cpu().double().numpy()
    F = f.cpu().numpy().astype(np.int32)
    length = math.sqrt(_ISO_VERTS_PER_AREA * area / target)
    best: tuple[float, np.ndarray, np.ndarray, float] | None = None
    for trial in range(s.trials):
        interrupt.check("the even resampling")
        ms = pymeshlab.MeshSet()
        ms.add_mesh(pymeshlab.Mesh(vertex_matrix=X, face_matrix=F))
        ms.meshing_isotropic_explicit_remeshing(
            iterations=s.isotropic_iterations, adaptive=False, targetlen=pymeshlab.PureValue(length),
            checksurfdist=True, maxsurfdist=pymeshlab.PureValue(s.isotropic_surface_distance * length))
        m = ms.current_mesh()
        V, Fn = np.asarray(m.vertex_matrix(), dtype=np.float64), np.asarray(m.face_matrix(), dtype=np.int64)
        err = abs(len(V) - target) / target
        log.debug("%s: trial %d edge length %.4g -> %d vertices", name, trial, length, len(V))
        if len(V) and (best is None or err < best[0]):
            best = (err, V, Fn, length)
        if err <= s.vertex_tolerance or not len(V):
            break
        length *= math.sqrt(len(V) / target)
    if best is None:
        raise InputError(f"{name}(): isotropic remeshing left no vertices; resample a closed, manifold mesh")
    _, V, Fn, length = best
    result = _onto_old(V, Fn, v, f, s, _Surface(V, Fn, length, 0.0, 1), None)
    if result.lost > s.coverage_fraction:
        log.warning("%s: %.1f%% of the old vertices stay farther than %.3g from the remeshed surface (more "
                    "ResampleSettings.isotropic_iterations or a lower isotropic_surface_distance may keep them)", name,
                    100 * result.lost, s.coverage_distance * length)
    return result


# --------------------------------------------------------------------------------------------------
# entry point


def even_resample(
    verts: torch.Tensor,
    faces: torch.Tensor,
    settings: ResampleSettings | None = None,
    attributes: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Rebuild a closed mesh with about evenly spaced vertices on the same surface.

    Steps with ``settings.method="marching"`` (the default); ``"isotropic"`` replaces 1-4 and 6 with
    pymeshlab's isotropic remeshing at the edge length that gives the target count (see the module).

    1. Signed distance (winding-number sign) of the mesh on a cubic grid of spacing h covering its
       bounding box plus ``margin_cells`` cells; the z axis is mirror-symmetric about z = 0 when
       ``symmetric_z``.
    2. Marching cubes (``skimage.measure.marching_cubes``) at level 0 (with ``symmetric_z``, of the
       halves z >= 0 and z <= 0, the lower one mirrored, welded on z = 0); keep the connected
       component with the most faces (specks of a self-intersecting or nearly open input go).
    3. h is searched (at most ``trials`` tries, first guess from the surface area, then rescaled by
       sqrt(V / target); halved when no grid sample falls inside) until the vertex count is within
       ``vertex_tolerance`` of the target.
    4. Taubin smoothing (``trimesh.smoothing.filter_taubin``, topology kept). Faces wind
       counter-clockwise seen from outside (trimesh volume > 0); the mesh is watertight.
    5. With ``project``, each vertex moves to its closest point on the old surface, except where a
       face would flip or collapse (``min_area_kept``); mirror partners move by the mean of their
       mirrored moves, so a vertex on the plane z = 0 stays on it.
    6. Coverage: if more than ``coverage_fraction`` of the old vertices lie farther than
       ``coverage_distance`` x h from the result (a part thinner than the grid fell apart), it is
       rebuilt from the surface dilated by each of ``dilate_steps`` x h (with ``project`` only), then
       on finer grids (h x ``refine_step`` per step, at most ``max_vertices_factor`` x the target
       vertices), until coverage holds (a dilated result far over the target count is marched once
       more at the spacing that fits the count, kept if coverage still holds). Otherwise the attempt
       that lost the fewest is kept, with a warning; if that one still loses more than ``max_lost``, the input
       comes back unchanged (nothing below is done), with a warning.
    7. With ``keep_volume``, all vertices move along their normals by one distance
       (at most ``max_volume_offset`` x h) so the volume equals the old mesh's; repeated resampling
       then does not shrink the mesh.
    8. ``attributes`` of each new vertex: the old vertices' values interpolated with the barycentric
       weights of its closest point on the old surface.

    Args:
        verts: ``(N, 3)`` float vertices of a closed, consistently wound mesh (any device).
        faces: ``(F, 3)`` integer vertex indices.
        settings: ``ResampleSettings``.
        attributes: optional ``(N, C)`` float per-vertex values (e.g. colour logits) to carry over.

    Returns:
        ``(new_verts (V, 3), new_faces (F', 3) int64, new_attributes (V, C) or None)`` on verts'
        device; new_verts in verts' dtype, new_attributes in attributes' dtype. Nothing carries a
        gradient.

    Raises:
        InputError: empty or non-finite mesh, wrong shapes, attributes of the wrong length, a mesh
            so far from closed that its distance field has no inside (no surface found), or one that
            needs a grid over ``max_grid_points``.
    """
    s = settings or ResampleSettings()
    name = "even_resample"
    _check_inputs(name, verts, faces, attributes)
    dev, dtype = verts.device, verts.dtype
    v = verts.detach().to(torch.float32).contiguous()
    f = faces.detach().to(device=dev, dtype=torch.int64).contiguous()
    if not torch.isfinite(v).all():
        raise InputError(f"{name}(): verts contain NaN or inf; resample a finite mesh")
    if int(f.min()) < 0 or int(f.max()) >= v.shape[0]:
        raise InputError(f"{name}(): faces index vertices {int(f.min())}..{int(f.max())} but there are {v.shape[0]}")

    target = int(s.target_vertices) if s.target_vertices is not None else int(v.shape[0])
    vn, fn = v.cpu().double().numpy(), f.cpu().numpy()
    lo, hi = vn.min(axis=0), vn.max(axis=0)
    tri = vn[fn]
    area = 0.5 * float(np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum())
    if not area > 0:
        raise InputError(f"{name}(): the mesh has zero surface area; resample a closed mesh with volume")

    if s.method == "isotropic":
        result = _isotropic(v, f, target, area, s, name)
    else:
        result = _marching(v, f, lo, hi, target, area, s, name)

    if result.lost > s.max_lost:
        log.warning("%s: not used: %.1f%% of the old vertices would be lost (over max_lost=%.3g); the mesh "
                    "is kept as it is (%d vertices)", name, 100 * result.lost, s.max_lost, v.shape[0])
        return (verts.detach().clone(), faces.detach().to(dtype=torch.int64).clone(),
                None if attributes is None else attributes.detach().clone())
    new_verts, new_faces = result.verts, result.faces
    if s.keep_volume:
        new_verts = _match_volume(result, _volume(v, f), s, name)
    log.debug("%s: %d -> %d vertices, %d faces, spacing %.4g, dilation %.2f, %d components dropped, %d vertices "
              "not projected, %.2f%% old vertices lost", name, v.shape[0], len(new_verts), len(new_faces),
              result.surf.h, result.surf.dilate, result.surf.components - 1, result.kept, 100 * result.lost)
    check = trimesh.Trimesh(new_verts.cpu().double().numpy(), new_faces.cpu().numpy(), process=False)
    if not (check.is_watertight and check.is_winding_consistent and check.volume > 0):
        log.warning("%s: the resampled mesh is not watertight/consistently wound (%d vertices)", name, len(new_verts))

    # 8: attributes
    new_attr = None
    if attributes is not None:
        _, face, bary = closest_point(v, f, new_verts, accuracy=s.winding_accuracy)
        a = attributes.detach().to(dev)
        new_attr = (bary.to(a.dtype)[:, :, None] * a[f[face.clamp_min(0)]]).sum(1)
    return new_verts.to(dtype), new_faces, new_attr
