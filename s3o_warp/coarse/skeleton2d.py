"""Phase 1, 2D part: a silhouette's skeleton graph, the canonical frame and part masks (paper 3.2).

Everything here is plain numpy on one mask at a time; pixel coordinates follow the project's OpenCV
convention: ``(x, y)`` = (column, row), the centre of pixel (c, r) is at (c, r).

The 2D skeleton follows Hi-LASSIE's ``extract_skeleton`` (Yao et al. 2023) as the S3O paper does:
thin the silhouette to a one-pixel curve, classify its pixels as junction (>= 3 skeleton neighbours),
endpoint (1) or connection (2), rebuild a graph of junctions and endpoints whose edges are the pixel
chains between them, prune short spurs and merge close junctions until nothing changes.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Literal

import cv2
import numpy as np
from scipy import ndimage
from skimage.morphology import medial_axis, skeletonize
from tqdm import tqdm

from s3o_warp.errors import ConfigError, InputError

log = logging.getLogger(__name__)

JUNCTION = "junction"
ENDPOINT = "endpoint"
ISOLATED = "isolated"

_NEIGHBOURS = [(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)]


@dataclass
class CoarseSettings:
    """The constants of the coarse model initialisation (Phase 1): the method's, not a user's; the fit sets only
    ``target_vertices`` (``coarse.target_vertices``). Tests build their own to vary one."""

    smooth_sigma: float = 1.0
    """Gaussian blur (pixels) of the mask before thinning, re-thresholded at 0.5; 0 = none (calms jagged masks)."""
    fill_holes: bool = True
    """Fill holes of the silhouette first, so the skeleton is a tree (a hole would make a loop)."""
    skeleton_method: Literal["skeletonize", "medial_axis"] = "skeletonize"
    """Thinning: skimage ``skeletonize`` (Zhang, fewer spurs) or ``medial_axis`` (exact ridge, more spurs)."""
    prune_factor: float = 1.0
    """Drop an endpoint edge whose path is shorter than prune_factor x the radius at its junction (Hi-LASSIE: 1.0)."""
    spur_protrusion: float = 0.5
    """Also drop an endpoint edge whose tip disc sticks out of its junction's disc by less than this x the
    junction radius (|p_end - p_junction| + r_end - r_junction): boundary noise makes long spurs that barely
    protrude, real limbs protrude by their length."""
    merge_factor: float = 0.8
    """Merge two junctions joined by an edge when closer than merge_factor x the larger radius (Hi-LASSIE: 0.8)."""
    canonical_size: int = 320
    """canonical_frame() shrinks each mask so its longer side is at most this many pixels (speed); 0 = as is."""
    canonical_tolerance: float = 0.9
    """canonical_frame(): frames whose extent ratio is at least this x the best one's compete on how many leg
    pairs they show (the most wins, then the ratio): a side view where paired legs are apart, so the lift
    pairs them; 1 = the most horizontal frame only (the paper's rule)."""
    canonical_stride_tolerance: float = 0.6
    """Among the competing frames with the most leg pairs, those whose :func:`leg_stride` (the closest leg
    pair's feet apart) is at least this x the widest compete on the ratio; 0 = the ratio alone. A frame just
    after a leg crossing gives the lift legs it cannot tell apart, and the fit swaps them at every crossing
    (the 120-degree Fox's frame 18: 0.46 of the widest). Frames whose feet are clearly apart stay in (the
    horse's, quadruped's and cows' ratio-picked frames: 0.69-0.74); 0.8 also dropped those."""
    leg_band: float = 0.15
    """A symmetric limb pair counts as legs when one of its ends lies in the lowest leg_band of the 2D skeleton's
    vertical extent (a foot on the ground, not a tail or ears)."""
    sym_length_ratio: float = 2.0
    """Two leaf edges of one junction may be a symmetric limb pair if longer / shorter length <= this."""
    sym_radius_ratio: float = 1.6
    """... and larger / smaller mean radius <= this ..."""
    sym_max_angle_deg: float = 75.0
    """... and the angle between their 2D directions (from the junction) <= this (stands in for DINO features)."""
    dz_fraction: float = 0.5
    """Symmetric limbs' end nodes go to z = +-dz_fraction x torso (root) radius, in metres of the object frame."""
    junction_dz_fraction: float = 0.8
    """Without girdles: a paired limb's junction end goes off the plane by min(dz, this x the junction's 2D radius)."""
    girdles: bool = True
    """Paired limbs move off the plane by the full dz, parallel to it, and a 'girdle' ellipsoid at their junction
    (radii r_junction, r_junction, dz + r_limb) joins them to the body, like hips and shoulders; false = only
    their junction ends move, by at most junction_dz_fraction x the junction's radius (limbs nearly touch)."""
    end_pad: float = 1.0
    """Ellipsoid long semi-axis = half the 3D edge length + end_pad x its short radius (Hi-LASSIE: 1.0)."""
    target_vertices: int = 2000
    """Vertex count the initial union mesh aims at (marching-cubes resolution is searched for it)."""
    vertex_tolerance: float = 0.12
    """Stop the resolution search when the vertex count is within this fraction of target_vertices."""
    mesh_trials: int = 5
    """At most this many marching-cubes resolutions are tried."""
    smooth_max: float = 0.05
    """Smooth-max softness of the ellipsoid union, as a fraction of the mean short radius; 0 = hard max."""
    taubin_iterations: int = 10
    """Taubin smoothing passes on the union mesh (0 = none)."""
    taubin_lambda: float = 0.5
    """Taubin shrink step."""
    taubin_nu: float = 0.53
    """Taubin inflate step (nu > lambda keeps the volume)."""
    precision_sharpness: float = 2.0
    """Bone precision Q = V^T diag(k / r^2) V with k this; larger = sharper skinning Gaussians."""

    def __post_init__(self) -> None:
        positive = ("prune_factor", "spur_protrusion", "merge_factor", "end_pad", "smooth_max", "smooth_sigma",
                    "dz_fraction", "junction_dz_fraction", "taubin_iterations", "canonical_size")
        for name in positive:
            if getattr(self, name) < 0:
                raise ConfigError(f"CoarseSettings.{name} must be >= 0, got {getattr(self, name)}")
        for name in ("sym_length_ratio", "sym_radius_ratio"):
            if getattr(self, name) < 1:
                raise ConfigError(f"CoarseSettings.{name} must be >= 1 (a max/min ratio), got {getattr(self, name)}")
        if not 0 < self.sym_max_angle_deg <= 180:
            raise ConfigError(f"CoarseSettings.sym_max_angle_deg must be in (0, 180], got {self.sym_max_angle_deg}")
        for name in ("canonical_tolerance", "leg_band"):
            if not 0 < getattr(self, name) <= 1:
                raise ConfigError(f"CoarseSettings.{name} must be in (0, 1], got {getattr(self, name)}")
        if not 0 <= self.canonical_stride_tolerance <= 1:
            raise ConfigError(f"CoarseSettings.canonical_stride_tolerance must be in [0, 1], got "
                              f"{self.canonical_stride_tolerance}; 0 turns the stride rule off")
        if self.target_vertices < 100:
            raise ConfigError(f"coarse.target_vertices must be >= 100, got {self.target_vertices}")
        if not 0 < self.vertex_tolerance < 1:
            raise ConfigError(f"CoarseSettings.vertex_tolerance must be in (0, 1), got {self.vertex_tolerance}")
        if self.mesh_trials < 1:
            raise ConfigError(f"CoarseSettings.mesh_trials must be >= 1, got {self.mesh_trials}")
        if self.precision_sharpness <= 0:
            raise ConfigError(f"CoarseSettings.precision_sharpness must be > 0, got {self.precision_sharpness}")
        if self.skeleton_method not in ("skeletonize", "medial_axis"):
            raise ConfigError(
                f"CoarseSettings.skeleton_method must be 'skeletonize' or 'medial_axis', got {self.skeleton_method!r}")


@dataclass
class Skeleton2D:
    """A silhouette's skeleton as a graph of junctions and endpoints (pixel units, (x, y) = (col, row)).

    Attributes:
        nodes: (N, 2) float64 node positions (x, y) in pixels. A junction sits at the mean of its
            pixel cluster, an endpoint on its pixel.
        node_radius: (N,) float64 distance-transform value (pixels to the background) at the node; for
            a junction the largest value over its cluster.
        node_type: (N,) str, ``"junction"`` (>= 3 edges), ``"endpoint"`` (1 edge) or ``"isolated"``
            (the only node of an edgeless skeleton, e.g. a disc).
        edges: (E, 2) int64 node indices. Concretely, ``edges[e] = (u, v)`` means edge e runs along
            ``paths[e]`` from node u to node v.
        paths: E arrays (K_e, 2) int64 of skeleton pixels (x, y), ordered from node u to node v.
        edge_radius: (E,) float64 mean distance-transform value (pixels) along the path, leaving out
            pixels inside a junction end's disc (those measure the parent part, not this one).
        edge_length: (E,) float64 polyline length of the path in pixels.
        root: index of the junction with the largest radius (the torso), or -1 when there is none.
        shape: (H, W) of the mask.
    """

    nodes: np.ndarray
    node_radius: np.ndarray
    node_type: np.ndarray
    edges: np.ndarray
    paths: list[np.ndarray]
    edge_radius: np.ndarray
    edge_length: np.ndarray
    root: int
    shape: tuple[int, int]

    @property
    def junctions(self) -> np.ndarray:
        """(J,) int64 indices of junction nodes."""
        return np.flatnonzero(self.node_type == JUNCTION)

    @property
    def endpoints(self) -> np.ndarray:
        """(P,) int64 indices of endpoint nodes."""
        return np.flatnonzero(self.node_type == ENDPOINT)

    def degree(self) -> np.ndarray:
        """(N,) int64 number of edges at each node."""
        return np.bincount(self.edges.reshape(-1), minlength=len(self.nodes))

    def pixels(self) -> np.ndarray:
        """(K, 2) int64 every skeleton pixel (x, y) of the kept graph (paths, plus a lone node)."""
        if self.paths:
            return np.unique(np.concatenate(self.paths), axis=0)
        return np.round(self.nodes).astype(np.int64)

    def extent_ratio(self) -> float:
        """Horizontal-to-vertical extent: (x_max - x_min + 1) / (y_max - y_min + 1) over :meth:`pixels`.

        The +1 makes both extents inclusive pixel counts, so a horizontal line is finite (its width).
        """
        p = self.pixels()
        return float((np.ptp(p[:, 0]) + 1.0) / (np.ptp(p[:, 1]) + 1.0))


# --------------------------------------------------------------------------------------------------
# input checks


def _check_mask(mask, what: str = "mask") -> np.ndarray:
    m = np.asarray(mask)
    if m.ndim == 3 and m.shape[2] in (1, 3, 4):
        m = m[..., 0]
    if m.ndim != 2:
        raise InputError(f"{what} must be a 2D (H, W) array, got shape {np.shape(mask)}; pass one frame's mask")
    if m.dtype != bool:
        m = m > (127 if m.dtype == np.uint8 and m.max() > 1 else 0)
    if not m.any():
        raise InputError(f"{what} has no foreground pixel; pass a mask with the object (value > 127 or True)")
    return m


def _clean_mask(mask: np.ndarray, s: CoarseSettings) -> np.ndarray:
    """Blurred, hole-filled, largest 8-connected component of the mask."""
    m = mask
    if s.smooth_sigma > 0:
        blurred = ndimage.gaussian_filter(m.astype(np.float32), s.smooth_sigma)
        if (blurred > 0.5).any():
            m = blurred > 0.5
    if s.fill_holes:
        m = ndimage.binary_fill_holes(m)
    lab, n = ndimage.label(m, structure=np.ones((3, 3), bool))
    if n > 1:
        sizes = np.bincount(lab.ravel())
        sizes[0] = 0
        m = lab == int(np.argmax(sizes))
    return m


# --------------------------------------------------------------------------------------------------
# pixel graph -> junction / endpoint graph


class _Graph:
    """Mutable multigraph used while simplifying: nodes hold position/radius, edges hold paths."""

    def __init__(self, dist: np.ndarray):
        self.dist = dist
        self.pos: dict[int, np.ndarray] = {}
        self.rad: dict[int, float] = {}
        self.edges: dict[int, tuple[int, int, np.ndarray]] = {}  # id -> (u, v, path (K,2) x,y from u to v)
        self.inc: dict[int, set[int]] = {}
        self._next_node = 0
        self._next_edge = 0

    def add_node(self, pos, rad) -> int:
        i = self._next_node
        self._next_node += 1
        self.pos[i] = np.asarray(pos, np.float64)
        self.rad[i] = float(rad)
        self.inc[i] = set()
        return i

    def add_edge(self, u: int, v: int, path: np.ndarray) -> int:
        e = self._next_edge
        self._next_edge += 1
        self.edges[e] = (u, v, path)
        self.inc[u].add(e)
        self.inc[v].add(e)
        return e

    def remove_edge(self, e: int) -> None:
        u, v, _ = self.edges.pop(e)
        self.inc[u].discard(e)
        self.inc[v].discard(e)

    def remove_node(self, n: int) -> None:
        for e in list(self.inc[n]):
            self.remove_edge(e)
        del self.inc[n], self.pos[n], self.rad[n]

    def deg(self, n: int) -> int:
        return sum(2 if self.edges[e][0] == self.edges[e][1] else 1 for e in self.inc[n])

    def path_from(self, e: int, n: int) -> np.ndarray:
        """Edge e's path oriented to start at node n."""
        u, v, p = self.edges[e]
        return p if u == n else p[::-1]

    def other(self, e: int, n: int) -> int:
        u, v, _ = self.edges[e]
        return v if u == n else u

    @staticmethod
    def length(path: np.ndarray) -> float:
        return float(np.linalg.norm(np.diff(path.astype(np.float64), axis=0), axis=1).sum()) if len(path) > 1 else 0.0


def _trace_graph(skel: np.ndarray, dist: np.ndarray) -> _Graph:
    """Junction/endpoint graph of a one-pixel-wide skeleton image (pixel chains as edge paths)."""
    h, w = skel.shape
    count = ndimage.convolve(skel.astype(np.int32), np.ones((3, 3), np.int32), mode="constant") - 1
    count = np.where(skel, count, -1)
    is_node = skel & (count != 2)
    # Adjacent junction pixels form one junction (staircases and true crossings give clusters).
    junction_px = skel & (count >= 3)
    jlab, nj = ndimage.label(junction_px, structure=np.ones((3, 3), bool))
    g = _Graph(dist)
    node_of = np.full(skel.shape, -1, np.int64)
    for k, sl in enumerate(ndimage.find_objects(jlab), start=1):
        rr, cc = np.nonzero(jlab[sl] == k)
        rr = rr + sl[0].start
        cc = cc + sl[1].start
        n = g.add_node((cc.mean(), rr.mean()), dist[rr, cc].max())
        node_of[rr, cc] = n
    for r, c in zip(*np.nonzero(skel & (count <= 1))):  # endpoints and lone pixels
        node_of[r, c] = g.add_node((c, r), dist[r, c])

    visited = np.zeros(skel.shape, bool)  # connection pixels already on a path
    direct: set[tuple[int, int]] = set()

    def nbrs(r, c):
        for dr, dc in _NEIGHBOURS:
            rr, cc = r + dr, c + dc
            if 0 <= rr < h and 0 <= cc < w and skel[rr, cc]:
                yield rr, cc

    for r0, c0 in zip(*np.nonzero(is_node)):
        n0 = int(node_of[r0, c0])
        for r1, c1 in nbrs(r0, c0):
            n1 = int(node_of[r1, c1])
            if n1 == n0:
                continue
            if n1 >= 0:  # two nodes touching: a one-step edge
                key = (min(n0, n1), max(n0, n1))
                if key not in direct:
                    direct.add(key)
                    g.add_edge(n0, n1, np.array([[c0, r0], [c1, r1]], np.int64))
                continue
            if visited[r1, c1]:
                continue
            path = [(c0, r0), (c1, r1)]
            visited[r1, c1] = True
            prev, cur = (r0, c0), (r1, c1)
            end = -1
            while True:
                cand_nodes, cand_conn = [], []
                for rr, cc in nbrs(*cur):
                    if (rr, cc) == prev:
                        continue
                    m = node_of[rr, cc]
                    if m >= 0:
                        if m != n0:
                            cand_nodes.append((rr, cc))
                    elif not visited[rr, cc]:
                        cand_conn.append((rr, cc))
                if cand_nodes:
                    rr, cc = cand_nodes[0]
                    path.append((cc, rr))
                    end = int(node_of[rr, cc])
                    break
                if not cand_conn:
                    break  # a loop back to the start node or a dead end: dropped
                prev, cur = cur, cand_conn[0]
                visited[cur] = True
                path.append((cur[1], cur[0]))
            if end >= 0:
                g.add_edge(n0, end, np.asarray(path, np.int64))
    return g


def _simplify(g: _Graph, s: CoarseSettings) -> None:
    """Prune short spurs, dissolve degree-2 nodes, merge close junctions; repeat until stable."""
    for _ in range(10000):
        changed = False
        # self-loops (only possible from holes) carry no limb
        for e, (u, v, _) in list(g.edges.items()):
            if u == v:
                g.remove_edge(e)
                changed = True
        # prune spurs (short, or barely protruding from the junction's disc); keep >= 1 edge per junction
        for j in list(g.inc):
            if j not in g.inc or g.deg(j) < 3:
                continue
            spurs = []
            for e in g.inc[j]:
                o = g.other(e, j)
                if o != j and g.deg(o) == 1:
                    length = g.length(g.edges[e][2])
                    protrusion = float(np.linalg.norm(g.pos[o] - g.pos[j])) + g.rad[o] - g.rad[j]
                    if length < s.prune_factor * g.rad[j] or protrusion < s.spur_protrusion * g.rad[j]:
                        spurs.append((length, e, o))
            spurs.sort()
            n_keep = g.deg(j) - len(spurs)
            if n_keep == 0:
                spurs = spurs[:-1]  # never strip a junction bare: keep its longest edge
            for _, e, o in spurs:
                g.remove_node(o)
                changed = True
        # dissolve degree-2 nodes: join their two edges
        for n in list(g.inc):
            if n in g.inc and len(g.inc[n]) == 2 and g.deg(n) == 2:
                e1, e2 = tuple(g.inc[n])
                a, b = g.other(e1, n), g.other(e2, n)
                path = np.concatenate([g.path_from(e1, a), g.path_from(e2, n)[1:]])
                g.remove_node(n)
                g.add_edge(a, b, path)
                changed = True
        # merge junctions joined by an edge and closer than merge_factor x the larger radius (shortest first)
        best = None
        for e, (u, v, path) in g.edges.items():
            if u != v and g.deg(u) >= 3 and g.deg(v) >= 3:
                d = float(np.linalg.norm(g.pos[u] - g.pos[v]))
                if d < s.merge_factor * max(g.rad[u], g.rad[v]) and (best is None or d < best[0]):
                    best = (d, e)
        if best is not None:
            e = best[1]
            u, v, _ = g.edges[e]
            keep, gone = (u, v) if g.rad[u] >= g.rad[v] else (v, u)
            bridge = g.path_from(e, keep)  # keep -> gone
            g.remove_edge(e)
            for e2 in list(g.inc[gone]):
                far = g.other(e2, gone)
                far = keep if far == gone else far
                path = np.concatenate([bridge, g.path_from(e2, gone)[1:]])
                g.remove_edge(e2)
                g.add_edge(keep, far, path)
            g.remove_node(gone)
            changed = True
        if not changed:
            return
    log.warning("skeleton_2d: graph simplification did not settle after 10000 rounds")


def _largest_component(g: _Graph) -> set[int]:
    seen: set[int] = set()
    best: tuple[float, set[int]] = (-1.0, set())
    for start in g.inc:
        if start in seen:
            continue
        comp, stack, size = {start}, [start], 0.0
        while stack:
            n = stack.pop()
            for e in g.inc[n]:
                o = g.other(e, n)
                if o not in comp:
                    comp.add(o)
                    stack.append(o)
        seen |= comp
        size = sum(len(g.edges[e][2]) for n in comp for e in g.inc[n]) / 2.0 + len(comp)
        if size > best[0]:
            best = (size, comp)
    return best[1]


def _edge_mean_radius(path: np.ndarray, dist: np.ndarray, ends: list[tuple[np.ndarray, float]]) -> float:
    vals = dist[path[:, 1], path[:, 0]]
    keep = np.ones(len(path), bool)
    for p, r in ends:
        keep &= np.linalg.norm(path - p, axis=1) >= r
    return float(vals[keep].mean() if keep.any() else vals.mean())


def skeleton_2d(mask, settings: CoarseSettings | None = None, *, prune_factor: float | None = None,
                merge_factor: float | None = None) -> Skeleton2D:
    """The 2D skeleton graph of one silhouette (junctions, endpoints, the pixel paths between them).

    Steps: blur + re-threshold the mask (``smooth_sigma``), fill holes, keep the largest 8-connected
    blob; thin it (``skimage.morphology.skeletonize`` or ``medial_axis``); radius = Euclidean distance
    transform (``scipy.ndimage.distance_transform_edt``, pixels to the nearest background pixel);
    classify skeleton pixels by their 8-neighbour count (1 endpoint, 2 connection, >= 3 junction;
    adjacent junction pixels are one junction); trace the connection chains between nodes as edges;
    then repeat until stable: drop endpoint edges shorter than ``prune_factor`` x their junction's
    radius or whose tip disc protrudes from the junction's disc by less than ``spur_protrusion`` x
    that radius (a junction keeps at least one edge), join the two edges of a node left with two,
    merge junctions joined by an edge and closer than ``merge_factor`` x the larger radius. The
    largest connected part is kept.

    Args:
        mask: (H, W) bool silhouette (uint8 > 127 or any non-zero number also accepted).
        settings: ``CoarseSettings``; default settings when None.
        prune_factor: overrides ``settings.prune_factor``.
        merge_factor: overrides ``settings.merge_factor``.

    Returns:
        Skeleton2D in pixel coordinates (x, y) of this mask.

    Raises:
        InputError: the mask is not 2D or has no foreground.
    """
    s = settings or CoarseSettings()
    over = {k: v for k, v in (("prune_factor", prune_factor), ("merge_factor", merge_factor)) if v is not None}
    if over:
        s = replace(s, **over)
    m = _clean_mask(_check_mask(mask), s)
    if s.skeleton_method == "medial_axis":
        skel = medial_axis(m)
    else:
        skel = skeletonize(m)
    # distance_transform_edt measures to the nearest zero; pad so the image border counts as background
    dist = ndimage.distance_transform_edt(np.pad(m, 1))[1:-1, 1:-1]
    if not skel.any():  # a blob thinner than the thinning can represent: its brightest pixel
        r, c = np.unravel_index(int(np.argmax(dist)), dist.shape)
        skel = np.zeros_like(m)
        skel[r, c] = True
    g = _trace_graph(skel, dist)
    _simplify(g, s)
    comp = _largest_component(g)
    ids = sorted(comp)
    index = {n: i for i, n in enumerate(ids)}
    nodes = np.array([g.pos[n] for n in ids], np.float64).reshape(-1, 2)
    node_radius = np.array([g.rad[n] for n in ids], np.float64)
    edge_ids = sorted({e for n in ids for e in g.inc[n]})
    edges = np.array([[index[g.edges[e][0]], index[g.edges[e][1]]] for e in edge_ids], np.int64).reshape(-1, 2)
    paths = [g.edges[e][2].copy() for e in edge_ids]
    deg = np.bincount(edges.reshape(-1), minlength=len(ids))
    node_type = np.where(deg >= 3, JUNCTION, np.where(deg == 1, ENDPOINT, ISOLATED)).astype("<U8")
    edge_radius = np.array([
        _edge_mean_radius(p, dist, [(nodes[u], node_radius[u]) for u in (a, b) if node_type[u] == JUNCTION])
        for p, (a, b) in zip(paths, edges)], np.float64)
    edge_length = np.array([_Graph.length(p) for p in paths], np.float64)
    junctions = np.flatnonzero(node_type == JUNCTION)
    root = int(junctions[np.argmax(node_radius[junctions])]) if len(junctions) else -1
    sk = Skeleton2D(nodes, node_radius, node_type, edges, paths, edge_radius, edge_length, root, tuple(m.shape))
    log.debug("skeleton_2d: %d junctions, %d endpoints, %d edges, root %d",
              len(junctions), len(sk.endpoints), len(edges), root)
    return sk


MIRROR_TOL_DEG = 30.0
"""Two leaf limbs of one junction are mirror images (:func:`mirror_pairs`) when one's 2D direction, reflected about
the image's vertical axis, is within this many degrees of the other's."""


def _leaf_pairs(skel: Skeleton2D, s: CoarseSettings):
    """Every pair of leaf edges (ending in an endpoint) at one junction whose lengths and mean radii are within
    ``sym_length_ratio`` and ``sym_radius_ratio``: ``(junction, e1, e2, d1, d2, lr, rr)``, d the unit 2D directions
    from the junction, lr / rr the length and radius ratios."""
    deg = skel.degree()
    for j in skel.junctions:
        leaves = []
        for e, (u, v) in enumerate(skel.edges):
            if j in (u, v):
                o = v if u == j else u
                if o != j and skel.node_type[o] == ENDPOINT and deg[o] == 1:
                    d = skel.nodes[o] - skel.nodes[j]
                    leaves.append((e, o, d / max(np.linalg.norm(d), 1e-9)))
        for i in range(len(leaves)):
            for k in range(i + 1, len(leaves)):
                (e1, _, d1), (e2, _, d2) = leaves[i], leaves[k]
                lr = max(skel.edge_length[e1], skel.edge_length[e2]) / max(
                    min(skel.edge_length[e1], skel.edge_length[e2]), 1e-9)
                rr = max(skel.edge_radius[e1], skel.edge_radius[e2]) / max(
                    min(skel.edge_radius[e1], skel.edge_radius[e2]), 1e-9)
                if lr <= s.sym_length_ratio and rr <= s.sym_radius_ratio:
                    yield j, e1, e2, d1, d2, lr, rr


def _far(skel: Skeleton2D, e: int, j: int) -> int:
    """The node of edge e that is not j."""
    u, v = (int(x) for x in skel.edges[e])
    return v if u == j else u


def _pairs(skel: Skeleton2D, s: CoarseSettings, score) -> list[tuple[int, int, int]]:
    """``(junction, e1, e2)`` with e1 < e2: the :func:`_leaf_pairs` that ``score(d1, d2, lr, rr)`` accepts (a float,
    lower is better; None rejects), paired greedily best first within each junction, each edge in at most one pair."""
    cands: dict[int, list] = {}
    for j, e1, e2, d1, d2, lr, rr in _leaf_pairs(skel, s):
        sc = score(d1, d2, lr, rr)
        if sc is not None:
            cands.setdefault(j, []).append((sc, e1, e2))
    out = []
    for j, c in cands.items():  # the junctions in order; the pairs of one junction compete only among themselves
        used: set[int] = set()
        for _, e1, e2 in sorted(c):
            if e1 not in used and e2 not in used:
                used |= {e1, e2}
                out.append((j, min(e1, e2), max(e1, e2)))
    return out


def symmetric_pairs(skel: Skeleton2D, s: CoarseSettings) -> list[tuple[int, int]]:
    """Leaf-edge pairs at one junction with similar length, radius and 2D direction (greedy, best first)."""
    cos_max = np.cos(np.deg2rad(s.sym_max_angle_deg))

    def score(d1, d2, lr, rr):
        cos = float(np.dot(d1, d2))
        return abs(np.log(lr)) + abs(np.log(rr)) + np.arccos(np.clip(cos, -1, 1)) / np.pi if cos >= cos_max else None

    return [(e1, e2) for _, e1, e2 in _pairs(skel, s, score)]


def mirror_pairs(skel: Skeleton2D, s: CoarseSettings) -> list[tuple[int, int]]:
    """Leaf-edge pairs at one junction with similar length and radius whose 2D directions are mirror images about
    the image's vertical axis (within :data:`MIRROR_TOL_DEG`), greedy best first; each pair ``(left, right)``: the
    first ends nearer the image's left."""
    tol = np.deg2rad(MIRROR_TOL_DEG)

    def score(d1, d2, lr, rr):
        err = np.arccos(np.clip(float(-d1[0] * d2[0] + d1[1] * d2[1]), -1, 1))
        return abs(np.log(lr)) + abs(np.log(rr)) + err / np.pi if err <= tol else None

    return [(e1, e2) if skel.nodes[_far(skel, e1, j)][0] <= skel.nodes[_far(skel, e2, j)][0] else (e2, e1)
            for j, e1, e2 in _pairs(skel, s, score)]


def front_view(skel: Skeleton2D, s: CoarseSettings, pairs: list[tuple[int, int]] | None = None) -> bool:
    """Whether the frame shows the body from the front (or the back): one of its :func:`mirror_pairs` spreads to
    both sides of its junction, more than 90 degrees apart, and does not hang (not both limbs pointing down): a
    person's arms held out, level or raised. A side view's paired limbs hang the same way, and legs or toes spread
    wide still hang down (without that test a few side-view frames of the horse, the walking robot and the cows
    passed); a front view with arms down cannot be told from a side view and is lifted as one."""
    pairs = mirror_pairs(skel, s) if pairs is None else pairs
    for e1, e2 in pairs:
        j = int(np.intersect1d(skel.edges[e1], skel.edges[e2])[0])
        d = [skel.nodes[_far(skel, e, j)] - skel.nodes[j] for e in (e1, e2)]
        if d[0][0] * d[1][0] < 0 and float(np.dot(d[0], d[1])) < 0 and min(d[0][1], d[1][1]) <= 0:
            return True  # image rows grow downwards: a limb pointing down has d_y > 0
    return False


def _leg_pair_ends(skel: Skeleton2D, s: CoarseSettings, pairs: list[tuple[int, int]] | None = None) -> list:
    """The two end nodes (pixel positions) of every symmetric limb pair that looks like legs (see leg_pairs)."""
    pairs = symmetric_pairs(skel, s) if pairs is None else pairs
    if not pairs or not skel.paths:
        return []
    y = skel.pixels()[:, 1]
    floor = y.max() - s.leg_band * (np.ptp(y) + 1.0)
    out = []
    for e1, e2 in pairs:
        ends = [u if skel.node_type[u] == ENDPOINT else v for u, v in (skel.edges[e1], skel.edges[e2])]
        if any(skel.nodes[u][1] >= floor for u in ends):
            out.append((np.asarray(skel.nodes[ends[0]], np.float64), np.asarray(skel.nodes[ends[1]], np.float64)))
    return out


def leg_pairs(skel: Skeleton2D, s: CoarseSettings, pairs: list[tuple[int, int]] | None = None) -> int:
    """How many symmetric limb pairs look like legs: a leaf end in the lowest ``leg_band`` of the skeleton.

    Image rows grow downwards, so "lowest" is the largest y. A walking animal seen from the side has at
    least one foot of a leg pair on the ground (the other may be lifted); ears and tails end higher up.
    """
    return len(_leg_pair_ends(skel, s, pairs))


def leg_stride(skel: Skeleton2D, s: CoarseSettings, pairs: list[tuple[int, int]] | None = None) -> float:
    """How far apart the feet of the closest leg pair are: min over leg pairs of |end_1 - end_2| / extent.

    ``extent`` is the longer side of the skeleton's pixel bounding box (inclusive). 0 without leg pairs.
    A pair whose feet nearly touch is a leg crossing: seen once, the lift cannot tell which leg is which.
    """
    ends = _leg_pair_ends(skel, s, pairs)
    if not ends:
        return 0.0
    p = skel.pixels()
    extent = float(max(np.ptp(p[:, 0]), np.ptp(p[:, 1])) + 1.0)
    return min(float(np.linalg.norm(a - b)) for a, b in ends) / extent


# --------------------------------------------------------------------------------------------------
# canonical frame and part masks


def canonical_frame(masks: Sequence | np.ndarray, settings: CoarseSettings | None = None,
                    *, progress: bool = True) -> tuple[int, np.ndarray]:
    """A side-view frame whose 2D skeleton is nearly the most horizontal and shows the most leg pairs.

    The ratio of a frame is :meth:`Skeleton2D.extent_ratio`: the bounding box of every skeleton pixel
    of the kept graph (edge paths), width / height with both extents counted inclusively in pixels,
    ``(x_max - x_min + 1) / (y_max - y_min + 1)``, computed on the mask shrunk (area interpolation,
    > 0.5) so its longer side is at most ``canonical_size`` pixels. An empty mask gets ratio 0.
    S3O takes the frame with the highest ratio. Here every frame with a ratio of at least
    ``canonical_tolerance`` x the highest competes on :func:`leg_pairs` (the most win); of those, the frames
    whose :func:`leg_stride` is at least ``canonical_stride_tolerance`` x the widest compete on the ratio:
    a walking animal's most horizontal frame often shows a pair of legs overlapping, and the lift can
    only place legs it sees apart on either side of the body (``canonical_tolerance=1`` is S3O's rule).

    Args:
        masks: T masks, a list of (H, W) arrays or a (T, H, W) array (bool, or uint8 > 127).
        settings: ``CoarseSettings`` for :func:`skeleton_2d`.
        progress: show a tqdm bar.

    Returns:
        (index of the chosen frame (the first on ties), (T,) float64 ratios).

    Raises:
        InputError: no masks, or every mask is empty.
    """
    s = settings or CoarseSettings()
    if len(masks) == 0:
        raise InputError("canonical_frame(): got no masks; pass the sequence's masks (T >= 1)")
    ratios = np.zeros(len(masks), np.float64)
    skels: list[Skeleton2D | None] = [None] * len(masks)
    for t in tqdm(range(len(masks)), desc="canonical frame", disable=not progress, leave=False):
        m = np.asarray(masks[t])
        if not np.any(m):
            log.warning("canonical_frame: mask %d is empty; its ratio is 0", t)
            continue
        skels[t] = skeleton_2d(_shrink(m, s.canonical_size), s)
        ratios[t] = skels[t].extent_ratio()
    if not np.any(ratios > 0):
        raise InputError("canonical_frame(): every mask is empty; check the masks folder (foreground = value > 127)")
    top = int(np.argmax(ratios))
    cands = np.flatnonzero(ratios >= s.canonical_tolerance * ratios[top])
    legs = {int(t): leg_pairs(skels[t], s) for t in cands}
    most = max(legs.values())
    stride = {t: leg_stride(skels[t], s) for t in legs if legs[t] == most}
    wide = max(stride.values())
    best = max((t for t in stride if stride[t] >= s.canonical_stride_tolerance * wide),
               key=lambda t: (ratios[t], -t))  # the first frame on ties
    log.info("canonical frame %d (horizontal/vertical skeleton extent %.3f, %d leg pairs, feet apart %.3f; the most "
             "horizontal: frame %d, %.3f, %d leg pairs)", best, ratios[best], legs[best], stride[best], top,
             ratios[top], legs[top])
    return best, ratios


def _shrink(mask: np.ndarray, size: int) -> np.ndarray:
    """The mask resized (area average > 0.5) so its longer side is at most size pixels (0 = unchanged)."""
    m = _check_mask(mask)
    scale = size / max(m.shape) if size > 0 else 1.0
    if scale >= 1.0:
        return m
    w, h = max(1, round(m.shape[1] * scale)), max(1, round(m.shape[0] * scale))
    small = cv2.resize(m.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA) > 0.5
    return small if small.any() else m


def part_masks(mask, skel: Skeleton2D) -> np.ndarray:
    """Foreground pixels split among the skeleton edges: each goes to the edge whose path is nearest.

    These stand in for Hi-LASSIE's DINO part silhouettes. Distances are Euclidean in pixels to the
    nearest pixel of an edge's path (``scipy.ndimage.distance_transform_edt`` with indices); a pixel
    shared by several paths (a junction) belongs to the lowest edge index.

    Args:
        mask: (H, W) silhouette, the one ``skel`` was computed from.
        skel: its Skeleton2D (E >= 1 edges; an edgeless skeleton gives one part = the whole mask).

    Returns:
        (P, H, W) bool with P = max(E, 1). Concretely, ``parts[e, y, x]`` is True iff pixel (x, y) is
        foreground and edge e's path is the nearest; every foreground pixel is in exactly one part.

    Raises:
        InputError: the mask is empty or its shape differs from the skeleton's.
    """
    m = _check_mask(mask)
    if m.shape != tuple(skel.shape):
        raise InputError(f"part_masks(): mask shape {m.shape} differs from the skeleton's {tuple(skel.shape)}; "
                         "pass the mask the skeleton was made from")
    if len(skel.paths) == 0:
        return m[None].copy()
    label = np.full(m.shape, -1, np.int64)
    for e in range(len(skel.paths) - 1, -1, -1):  # lower index painted last wins shared pixels
        p = skel.paths[e]
        label[p[:, 1], p[:, 0]] = e
    _, (ri, ci) = ndimage.distance_transform_edt(label < 0, return_indices=True)
    nearest = label[ri, ci]
    return (nearest[None] == np.arange(len(skel.paths))[:, None, None]) & m[None]
