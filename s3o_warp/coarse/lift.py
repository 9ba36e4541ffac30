"""Phase 1, 3D part: lift the canonical frame's 2D skeleton to ellipsoids, a mesh and initial bones.

Object frame (all outputs here): the canonical camera's axes (OpenCV: x right, y down, z forward),
origin at the body centre back-projected at the given depth, units of the depth (metres by
convention). The root transform of the canonical frame is therefore ``[I | C]`` with C the body
centre in camera coordinates. The symmetry plane goes through the origin: z = 0 (normal (0, 0, 1)) for a
side view, x = 0 (normal (1, 0, 0)) for a front view (:func:`s3o_warp.coarse.skeleton2d.front_view`).
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass, field, replace

import numpy as np
import trimesh
from skimage.measure import marching_cubes

from s3o_warp.coarse.skeleton2d import (
    ENDPOINT,
    CoarseSettings,
    Skeleton2D,
    front_view,
    mirror_pairs,
    symmetric_pairs,
)
from s3o_warp.errors import InputError
from s3o_warp.geometry import project_np

log = logging.getLogger(__name__)


@dataclass
class Coarse3D:
    """The lifted coarse model: 3D skeleton nodes and one ellipsoid per 2D skeleton edge.

    Attributes:
        nodes: (N, 3) float64 node positions in the object frame (same order as ``Skeleton2D.nodes``).
        edges: (E, 2) int64 node indices (same as ``Skeleton2D.edges``).
        centres: (E, 3) float64 ellipsoid centres = midpoints of their 3D edges (paired limbs: shifted by
            ``edge_dz`` along z at their junction end, so the whole limb sits off the plane).
        rotations: (E, 3, 3) float64 proper rotations whose columns are the ellipsoid axes in the object
            frame; column 0 is the long axis (along the edge). Concretely, a point p is inside
            ellipsoid e iff ``|| (rotations[e].T @ (p - centres[e])) / radii[e] || <= 1``.
        radii: (E, 3) float64 semi-axes along those columns (long, short, short).
        sym_pairs: (S, 2) int64 edge indices of symmetric limb pairs, the first on the negative side of the
            symmetry plane: in a side view the end node of ``sym_pairs[s, 0]`` sits at z = -dz (nearer the
            camera), that of ``sym_pairs[s, 1]`` at +dz; in a front view the first is the image's left one.
        symmetry_plane: (normal (3,) float64, offset float): points p with normal . p = offset; offset 0.
        root_transform: (4, 4) float64 object-to-camera transform of the canonical frame, [I | C].
        root: root node index (the torso junction; -1 when the skeleton has no junction).
        root_edge: index of the edge that becomes the root bone (the widest edge at the root node).
        K: (3, 3) float64 intrinsics of the canonical frame (pixels).
        depth: the depth of the body centre along the camera's z axis.
        dz: the symmetric limbs' z offset (object-frame units; 0 in a front view, whose pairs are apart in x).
        edge_dz: (E,) float64 z shift of each edge's ellipsoid at its junction end (0 off the pairs; dz with
            girdles, else at most dz and ``junction_dz_fraction`` x the junction's radius, so the limb stays
            attached).
        girdle_centres: (G, 3) float64 centres of the girdle ellipsoids (one per symmetric pair with
            ``girdles``, at the pair's junction node; none otherwise). They shape the mesh only (no bone).
        girdle_radii: (G, 3) float64 their axis-aligned semi-axes (x, y, z): the junction's radius in x and
            y, dz + the larger limb radius in z, so both limbs join the body.
    """

    nodes: np.ndarray
    edges: np.ndarray
    centres: np.ndarray
    rotations: np.ndarray
    radii: np.ndarray
    sym_pairs: np.ndarray
    symmetry_plane: tuple[np.ndarray, float]
    root_transform: np.ndarray
    root: int
    root_edge: int
    K: np.ndarray
    depth: float
    dz: float
    edge_dz: np.ndarray | None = None
    girdle_centres: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    girdle_radii: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

    def all_ellipsoids(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(centres, rotations, radii) of the edge ellipsoids followed by the girdles (identity rotations)."""
        G = len(self.girdle_centres)
        rot = np.broadcast_to(np.eye(3), (G, 3, 3))
        return (np.concatenate([self.centres, self.girdle_centres]), np.concatenate([self.rotations, rot]),
                np.concatenate([self.radii, self.girdle_radii]))

    def project(self, points: np.ndarray) -> np.ndarray:
        """(M, 3) object-frame points -> (M, 2) float64 pixels (x, y) in the canonical frame."""
        cam = points @ self.root_transform[:3, :3].T + self.root_transform[:3, 3]
        return project_np(cam, self.K)


@dataclass
class Bones:
    """Initial bones and joints (S3O's B in R^{B x 13} and J in R^{J x 5}), object frame.

    Attributes:
        centres: (B, 3) float64 Gaussian centres C_b (= the ellipsoid centres).
        precisions: (B, 3, 3) float64 precision matrices Q_b = V_b^T diag(k / r^2) V_b, V_b's rows the
            ellipsoid axes, r the semi-axes, k = ``precision_sharpness``.
        lengths: (B,) float64 bone lengths = distance between the edge's two 3D nodes.
        parents: (B,) int64 parent bone, -1 for the root bone. Concretely, ``parents[b] = p`` means
            bone b hangs from bone p at the node they share, p being the one nearer the root.
        joints: (J, 2) int64 bone pairs (parent, child), one per non-root bone (J = B - 1 for a tree).
        joint_positions: (J, 3) float64 the shared node's 3D position.
        joint_nodes: (J,) int64 the shared node's index in ``Coarse3D.nodes``.
        edge_of_bone: (B,) int64 the 2D/3D skeleton edge each bone came from (bone b = edge b).
    """

    centres: np.ndarray
    precisions: np.ndarray
    lengths: np.ndarray
    parents: np.ndarray
    joints: np.ndarray
    joint_positions: np.ndarray
    joint_nodes: np.ndarray
    edge_of_bone: np.ndarray

    def packed(self) -> tuple[np.ndarray, np.ndarray]:
        """The paper's packing: (B, 13) [centre 3 | precision 9 (row-major) | length 1], (J, 5) [i, j | xyz]."""
        b = np.concatenate([self.centres, self.precisions.reshape(-1, 9), self.lengths[:, None]], axis=1)
        j = np.concatenate([self.joints.astype(np.float64), self.joint_positions], axis=1)
        return b, j


# --------------------------------------------------------------------------------------------------
# lift


def _check_K(K) -> np.ndarray:
    k = np.asarray(K, np.float64)
    if k.shape != (3, 3):
        raise InputError(f"lift_to_3d(): K must be a (3, 3) intrinsics matrix, got shape {k.shape}")
    if not (k[0, 0] > 0 and k[1, 1] > 0 and np.allclose(k[2], [0, 0, 1])):
        raise InputError("lift_to_3d(): K must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0; "
                         f"got {k.tolist()}")
    return k


def _frame_of_axis(a: np.ndarray) -> np.ndarray:
    """A proper rotation whose first column is the unit vector a."""
    ref = np.array([0.0, 0.0, 1.0]) if abs(a[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
    b = np.cross(ref, a)
    b /= np.linalg.norm(b)
    c = np.cross(a, b)
    return np.stack([a, b, c], axis=1)


def lift_to_3d(skel: Skeleton2D, K, depth: float, settings: CoarseSettings | None = None) -> Coarse3D:
    """Lift the canonical frame's 2D skeleton to 3D nodes and one ellipsoid per edge.

    Every node is back-projected through K at ``depth`` (camera z), except the end nodes of symmetric
    limb pairs, which are back-projected at ``depth -+ dz`` (dz = ``dz_fraction`` x the torso radius)
    so they keep their pixel but sit on either side of the symmetry plane z = 0; the ellipsoid of a
    paired limb is shifted off the plane at its junction end too (by up to dz, at most
    ``junction_dz_fraction`` of the junction's radius), so the two legs do not fuse. The main chain
    (torso, neck, head, tail, non-paired limbs) lies on z = 0. The origin is the body centre: the root
    junction (or, without junction, the arc-length midpoint of the longest edge's path) at ``depth``.
    Symmetric limbs: two leaf edges (ending in endpoints) of the same junction with length ratio <=
    ``sym_length_ratio``, radius ratio <= ``sym_radius_ratio`` and 2D angle <= ``sym_max_angle_deg``.

    A front view (:func:`~s3o_warp.coarse.skeleton2d.front_view`: a mirror pair spread to both sides, a
    person's arms held out) is lifted differently: its pairs are the :func:`~s3o_warp.coarse.skeleton2d.mirror_pairs`,
    already apart in the image, so every node stays at ``depth`` (no dz, no girdle), and the symmetry plane
    is the vertical plane x = 0 through the body centre and the camera, not the image plane.

    Ellipsoid e: centre = midpoint of its 3D edge, long axis along the edge with semi-axis
    half the 3D length + ``end_pad`` x r (Hi-LASSIE's 1 + 2 r / L scale), two short semi-axes
    r = the edge's mean 2D radius x depth / f, f = (fx + fy) / 2.

    Args:
        skel: the canonical frame's Skeleton2D (pixels).
        K: (3, 3) intrinsics [[fx, s, cx], [0, fy, cy], [0, 0, 1]] in pixels of that frame.
        depth: camera-z distance of the body centre (> 0), e.g. metres.
        settings: ``CoarseSettings``.

    Returns:
        Coarse3D in the object frame.

    Raises:
        InputError: bad K or depth, or a skeleton without edges.
    """
    s = settings or CoarseSettings()
    K = _check_K(K)
    if not np.isfinite(depth) or depth <= 0:
        raise InputError(f"lift_to_3d(): depth must be a positive finite number, got {depth}")
    if len(skel.edges) == 0:
        raise InputError("lift_to_3d(): the skeleton has no edge (the mask is a small blob); "
                         "use a larger or less round mask for the canonical frame")
    Kinv = np.linalg.inv(K)
    f = 0.5 * (K[0, 0] + K[1, 1])

    if skel.root >= 0:
        centre_px = skel.nodes[skel.root]
        torso_r_px = skel.node_radius[skel.root]
    else:
        e = int(np.argmax(skel.edge_length))
        p = skel.paths[e].astype(np.float64)
        seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
        acc = np.concatenate([[0.0], np.cumsum(seg)])
        centre_px = np.array([np.interp(acc[-1] / 2, acc, p[:, 0]), np.interp(acc[-1] / 2, acc, p[:, 1])])
        torso_r_px = float(skel.edge_radius.max())
    C = depth * (Kinv @ np.array([centre_px[0], centre_px[1], 1.0]))
    mirrored = mirror_pairs(skel, s)
    front = front_view(skel, s, mirrored)
    if front:  # the pairs are apart in the image already: nothing moves off the plane x = 0
        pairs, dz, normal = mirrored, 0.0, np.array([1.0, 0.0, 0.0])
    else:
        pairs, dz, normal = symmetric_pairs(skel, s), s.dz_fraction * torso_r_px * depth / f, np.array([0.0, 0.0, 1.0])
    node_z = np.zeros(len(skel.nodes))
    for e1, e2 in ([] if front else pairs):
        for e, sign in ((e1, -1.0), (e2, 1.0)):
            u, v = skel.edges[e]
            leaf = v if skel.node_type[v] == ENDPOINT else u
            node_z[leaf] = sign * dz
    homog = np.concatenate([skel.nodes, np.ones((len(skel.nodes), 1))], axis=1)
    nodes = (depth + node_z)[:, None] * (homog @ Kinv.T) - C

    E = len(skel.edges)
    # a paired limb is moved off the plane as a whole (parallel to it), not only at its end node:
    # a leg hanging from the spine at z = 0 would fuse with its partner along the upper half
    # (by dz with a girdle joining it to the body; without, at most ``junction_dz_fraction`` of the
    # junction's own radius, so the limb stays attached)
    edge_dz = np.zeros(E)
    girdle_c, girdle_r = [], []
    for e1, e2 in ([] if front else pairs):
        j = int(np.intersect1d(skel.edges[e1], skel.edges[e2])[0])
        r_j = skel.node_radius[j] * depth / f
        shift = dz if s.girdles else min(dz, s.junction_dz_fraction * r_j)
        edge_dz[e1], edge_dz[e2] = -shift, shift
        if s.girdles:  # hips / shoulders: the two parallel limbs hang from one wide ellipsoid at the junction
            r_limb = max(skel.edge_radius[e1], skel.edge_radius[e2]) * depth / f
            girdle_c.append(nodes[j])
            girdle_r.append((r_j, r_j, dz + r_limb))
    centres = np.empty((E, 3))
    rotations = np.empty((E, 3, 3))
    radii = np.empty((E, 3))
    ends = _shifted_ends(nodes, skel.edges, edge_dz)
    for e in range(E):
        pu, pv = ends[e]
        a = pv - pu
        length = float(np.linalg.norm(a))
        r = skel.edge_radius[e] * depth / f
        axis = a / length if length > 1e-12 else np.array([1.0, 0.0, 0.0])
        centres[e] = 0.5 * (pu + pv)
        rotations[e] = _frame_of_axis(axis)
        radii[e] = (0.5 * length + s.end_pad * r, r, r)

    if skel.root >= 0:
        at_root = [e for e in range(E) if skel.root in skel.edges[e]]
        root_edge = int(max(at_root, key=lambda e: skel.edge_radius[e]))
    else:
        root_edge = int(np.argmax(skel.edge_radius))
    T = np.eye(4)
    T[:3, 3] = C
    log.info("lift_to_3d: %d nodes, %d ellipsoids, %d symmetric pairs, %s", len(nodes), E, len(pairs),
             "front view (pairs mirrored about x = 0)" if front else f"dz {dz:.4g}")
    return Coarse3D(nodes=nodes, edges=skel.edges.copy(), centres=centres, rotations=rotations, radii=radii,
                    sym_pairs=np.array(pairs, np.int64).reshape(-1, 2),
                    symmetry_plane=(normal, 0.0), root_transform=T, root=int(skel.root),
                    root_edge=root_edge, K=K, depth=float(depth), dz=float(dz), edge_dz=edge_dz,
                    girdle_centres=np.array(girdle_c, np.float64).reshape(-1, 3),
                    girdle_radii=np.array(girdle_r, np.float64).reshape(-1, 3))


# --------------------------------------------------------------------------------------------------
# union mesh


def ellipsoid_field(coarse: Coarse3D, points: np.ndarray, smooth: float = 0.0) -> np.ndarray:
    """Implicit field of the ellipsoid union: > 0 inside, 0 on the surface, < 0 outside.

    Per ellipsoid g_e(p) = r_short_e (1 - ||R_e^T (p - c_e) / radii_e||) (about a signed distance near
    the surface, in object units); the union is max_e g_e, or the smooth max
    ``smooth * log(sum_e exp(g_e / smooth))`` when smooth > 0 (>= the max, by at most smooth log E).

    Args:
        coarse: the Coarse3D.
        points: (M, 3) float object-frame points.
        smooth: smooth-max softness in object units (0 = hard max).

    Returns:
        (M,) float64 field values.
    """
    p = np.asarray(points, np.float64)
    centres, rotations, radii = coarse.all_ellipsoids()
    g = np.empty((len(centres), len(p)))
    for e in range(len(centres)):
        local = (p - centres[e]) @ rotations[e] / radii[e]
        r = radii[e, 1:].min() if e < len(coarse.centres) else radii[e].min()  # edges: the short radius
        g[e] = r * (1.0 - np.linalg.norm(local, axis=1))
    if smooth <= 0:
        return g.max(axis=0)
    m = g.max(axis=0)
    return m + smooth * np.log(np.exp((g - m) / smooth).sum(axis=0))


def _march(coarse: Coarse3D, h: float, smooth: float):
    centres, _, radii = coarse.all_ellipsoids()
    reach = radii.max(axis=1, keepdims=True)
    margin = 2.0 * h + smooth * np.log(max(len(centres), 1))
    lo = (centres - reach).min(axis=0) - margin
    hi = (centres + reach).max(axis=0) + margin
    n = np.ceil((hi - lo) / h).astype(int) + 1
    axes = [lo[i] + h * np.arange(n[i]) for i in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    vol = ellipsoid_field(coarse, grid, smooth).reshape(n)
    verts, faces, _, _ = marching_cubes(vol, level=0.0, spacing=(h, h, h))
    return verts + lo, faces


def ellipsoid_union_mesh(coarse: Coarse3D, target_vertices: int | None = None,
                         settings: CoarseSettings | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A watertight mesh of the union of the ellipsoids, near a target vertex count (object frame).

    Marching cubes (``skimage.measure.marching_cubes``, level 0) of :func:`ellipsoid_field` with
    smooth max ``smooth_max`` x the mean short radius, on a cubic grid whose spacing is searched
    (at most ``mesh_trials`` tries, rescaling the spacing by sqrt(V / target)) until the vertex count
    is within ``vertex_tolerance`` of the target; then Taubin smoothing
    (``trimesh.smoothing.filter_taubin``), which moves vertices but keeps the topology. Faces wind
    counter-clockwise seen from outside (trimesh volume > 0).

    Args:
        coarse: the Coarse3D.
        target_vertices: overrides ``settings.target_vertices``.
        settings: ``CoarseSettings``.

    Returns:
        (verts (V, 3) float32 object frame, faces (F, 3) int32).
    """
    s = settings or CoarseSettings()
    if target_vertices is not None:
        s = replace(s, target_vertices=int(target_vertices))
    target = s.target_vertices
    smooth = s.smooth_max * float(coarse.radii[:, 1:].mean())
    # first guess: surface area of the ellipsoids (Knud Thomsen's approximation) / target
    a, b, c = coarse.radii.T
    pp = 1.6075
    area = float((4 * np.pi * (((a * b) ** pp + (a * c) ** pp + (b * c) ** pp) / 3) ** (1 / pp)).sum())
    h = np.sqrt(area / target)
    best = None
    for trial in range(s.mesh_trials):
        verts, faces = _march(coarse, h, smooth)
        err = abs(len(verts) - target) / target
        log.debug("ellipsoid_union_mesh: trial %d spacing %.4g -> %d vertices", trial, h, len(verts))
        if best is None or err < best[0]:
            best = (err, verts, faces)
        if err <= s.vertex_tolerance:
            break
        h *= np.sqrt(len(verts) / target)
    _, verts, faces = best
    mesh = trimesh.Trimesh(verts, faces, process=True)
    if mesh.volume < 0:
        mesh.invert()
    if s.taubin_iterations > 0:
        trimesh.smoothing.filter_taubin(mesh, lamb=s.taubin_lambda, nu=s.taubin_nu, iterations=s.taubin_iterations)
    if not (mesh.is_watertight and mesh.is_winding_consistent):
        log.warning("ellipsoid_union_mesh: mesh is not watertight/consistently wound (%d vertices)", len(mesh.vertices))
    n_bodies = int(mesh.body_count)
    if n_bodies > 1:
        log.warning("ellipsoid_union_mesh: the union has %d separate bodies; raise coarse.end_pad", n_bodies)
    log.info("ellipsoid_union_mesh: %d vertices, %d faces (target %d)", len(mesh.vertices), len(mesh.faces), target)
    return np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int32)


# --------------------------------------------------------------------------------------------------
# bones


def _shifted_ends(nodes: np.ndarray, edges: np.ndarray, edge_dz: np.ndarray | None) -> np.ndarray:
    ends = nodes[edges].copy()
    if edge_dz is not None:
        on_plane = np.isclose(ends[..., 2], 0.0, rtol=0.0, atol=1e-12)
        ends[..., 2] += np.where(on_plane, edge_dz[:, None], 0.0)
    return ends


def edge_ends(coarse: Coarse3D) -> np.ndarray:
    """``(E, 2, 3)`` the 3D ends of each edge's ellipsoid axis: the edge's nodes, except that a paired
    limb's end on the symmetry plane (its junction end) is shifted by ``edge_dz`` like the rest of it."""
    return _shifted_ends(coarse.nodes, coarse.edges, coarse.edge_dz)


def init_bones(coarse: Coarse3D, settings: CoarseSettings | None = None) -> Bones:
    """One bone per 3D edge, a kinematic tree rooted at the torso, joints where bones meet.

    Bone b = edge b: centre = ellipsoid centre, precision Q_b = V_b^T diag(k / r^2) V_b with V_b the
    transposed ellipsoid rotation (rows = axes), length = 3D edge length. The tree is a breadth-first
    walk from ``coarse.root_edge``: a bone's parent is the bone it was reached from through their
    shared node (at the root junction, the root bone is the parent of the others there). A cycle in
    the graph (only possible from a hole in the mask) is cut where the walk meets itself.

    Args:
        coarse: the Coarse3D.
        settings: ``CoarseSettings`` (``precision_sharpness`` = k).

    Returns:
        Bones in the object frame.
    """
    s = settings or CoarseSettings()
    E = len(coarse.edges)
    k = s.precision_sharpness
    lam = k / coarse.radii**2  # (E, 3)
    R = coarse.rotations
    precisions = np.einsum("eij,ej,ekj->eik", R, lam, R)
    axis_ends = edge_ends(coarse)  # (E, 2, 3): paired limbs' ends off the plane
    lengths = np.linalg.norm(axis_ends[:, 1] - axis_ends[:, 0], axis=1)

    at_node: dict[int, list[int]] = {}
    for e, (u, v) in enumerate(coarse.edges):
        at_node.setdefault(int(u), []).append(e)
        at_node.setdefault(int(v), []).append(e)
    parents = np.full(E, -2, np.int64)
    r0 = coarse.root_edge
    parents[r0] = -1
    joints, joint_nodes = [], []
    visited = set(int(n) for n in coarse.edges[r0])
    # frontier: the root bone's end nodes, root junction first so its siblings hang from the root bone
    ends = [int(n) for n in coarse.edges[r0]]
    if coarse.root in ends:
        ends.sort(key=lambda n: n != coarse.root)
    queue = deque((n, r0) for n in ends)
    while queue:
        n, via = queue.popleft()
        for e in at_node.get(n, []):
            if parents[e] != -2:
                continue
            parents[e] = via
            joints.append((via, e))
            joint_nodes.append(n)
            u, v = (int(x) for x in coarse.edges[e])
            far = v if u == n else u
            if far not in visited:
                visited.add(far)
                queue.append((far, e))
    if (parents == -2).any():  # unreachable edges (not possible for one component): make them roots
        log.warning("init_bones: %d edges unreachable from the root", int((parents == -2).sum()))
        parents[parents == -2] = -1
    joint_nodes = np.array(joint_nodes, np.int64)
    joints = np.array(joints, np.int64).reshape(-1, 2)
    # a joint sits at the child's end at the shared node (a paired limb's top is off the plane)
    side = (coarse.edges[joints[:, 1], 1] == joint_nodes).astype(np.int64)
    return Bones(centres=coarse.centres.copy(), precisions=precisions, lengths=lengths, parents=parents,
                 joints=joints, joint_positions=axis_ends[joints[:, 1], side].reshape(-1, 3), joint_nodes=joint_nodes,
                 edge_of_bone=np.arange(E, dtype=np.int64))


__all__ = ["Bones", "Coarse3D", "edge_ends", "ellipsoid_field", "ellipsoid_union_mesh", "init_bones", "lift_to_3d"]
