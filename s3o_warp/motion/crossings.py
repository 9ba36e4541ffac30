"""Paired legs through their crossings: undo the bounce the warm-up leaves behind.

Seen from the side, a silhouette and its optical flow do not say which of two paired legs is which:
where the legs cross in the image, fitting the next frames from the last one lets each fitted leg turn
back to its own side (the front fitted foot is always the front foot) instead of swinging through. The
silhouette is as good either way, but keypoints transferred through the surface land on the other leg
for half of every stride (the feet's ~50 % PCK-T).

The two labellings differ in one thing the images do not measure: a bounce reverses both feet's
velocity at the crossing, a swing-through does not. So for every symmetric limb pair of the coarse
lift, the frames are labelled "as fitted" or "exchanged" where going on along the other foot's path (in the
image, where the feet cross whatever depth the fit gave them) keeps both feet's velocities and staying does
not, and the exchanged frames get the mirrored motion of the partner leg (each leg keeps its own side of the
symmetry plane and its attachment). Pure functions; the fit calls :func:`resolve_crossings` after the
warm-up and again after the first epoch of the joint phase (``motion.resolve_crossings``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import torch

from s3o_warp.geometry import axis_angle_to_matrix, matrix_to_axis_angle, project

log = logging.getLogger(__name__)


MAX_GAP = 0.8
"""Two limbs' paths may be exchanged only where their ends are at most this x the limbs' mean projected length
apart."""
WINDOW = 2
"""Frames over which the feet's velocities before and after a crossing are measured."""
RATIO = 0.75
"""Exchange two limbs' paths where that changes their velocities by less than this x keeping them does."""


@dataclass(frozen=True)
class LimbPair:
    """Two symmetric limbs, one bone each: bone indices and their rest axes (top at the shared junction,
    then the far end), object frame, the first on the negative side of the lift's symmetry plane, whose unit
    ``normal`` it keeps (the plane goes through the origin: z = 0 in a side view, x = 0 in a front view)."""

    a: int
    b: int
    top_a: np.ndarray
    end_a: np.ndarray
    top_b: np.ndarray
    end_b: np.ndarray
    normal: tuple = (0.0, 0.0, 1.0)

    @property
    def mirror(self) -> np.ndarray:
        """(3, 3) the reflection through the symmetry plane, I - 2 n n^T."""
        n = np.asarray(self.normal, np.float64)
        return np.eye(3) - 2.0 * np.outer(n, n) / float(n @ n)


def exchange_costs(pa: np.ndarray, pb: np.ndarray, window: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Change of velocity of both limbs at each frame boundary t -> t+1, kept or exchanged.

    ``pa``, ``pb`` ``(T, D)``: the two limbs' end points (in the image: ``D`` = 2). The
    velocity before the boundary is taken over ``window`` frames ending at t, the one after over
    ``window`` frames starting at t+1, each along one path, so the frame pair straddling the crossing
    (and any gap between the paths) does not count. Returns ``(stay, swap)`` ``(T-1,)``: the summed
    squared change when each limb stays on its path, and when each goes on along the other's (inf where
    a window runs off the ends).
    """
    pa, pb = np.asarray(pa, np.float64), np.asarray(pb, np.float64)
    T, k = len(pa), int(window)
    stay = np.full(max(T - 1, 0), np.inf)
    swap = np.full(max(T - 1, 0), np.inf)
    if T - 1 - k > k:
        t = np.arange(k, T - 1 - k)
        va_in, vb_in = (pa[t] - pa[t - k]) / k, (pb[t] - pb[t - k]) / k
        va_out, vb_out = (pa[t + 1 + k] - pa[t + 1]) / k, (pb[t + 1 + k] - pb[t + 1]) / k
        stay[t] = ((va_out - va_in) ** 2).sum(1) + ((vb_out - vb_in) ** 2).sum(1)
        swap[t] = ((vb_out - va_in) ** 2).sum(1) + ((va_out - vb_in) ** 2).sum(1)
    return stay, swap


def crossing_labels(pa: np.ndarray, pb: np.ndarray, anchor: int, max_gap: float = np.inf, window: int = 2,
                    ratio: float = 0.5) -> np.ndarray:
    """Which frames exchange the two limbs' paths, so that neither bounces back at a crossing.

    A labelling ``s`` (T,) gives limb a the path ``pa`` where ``s = 0`` and ``pb`` where ``s = 1``. The
    paths are exchanged after frame t when going on along the other path changes both limbs' velocity
    (:func:`exchange_costs`) by less than ``ratio`` x what staying does, where the paths come closest
    (within ``window`` frames) and at most ``max_gap`` apart: where the limbs cross in the image.
    Exchanges are taken best first, more than ``window`` frames apart. ``s[anchor] = 0``.
    """
    T = len(pa)
    s = np.zeros(T, bool)
    if T < 2:
        return s
    stay, swap = exchange_costs(pa, pb, window)
    gap = np.linalg.norm(np.asarray(pa, np.float64) - np.asarray(pb, np.float64), axis=1)
    near = np.minimum(gap[:-1], gap[1:])
    closest = np.array([near[t] <= gap[max(t - window, 0):t + 2 + window].min() for t in range(T - 1)])
    ok = np.isfinite(stay) & (swap < ratio * stay) & (near <= max_gap) & closest
    taken: list[int] = []
    for t in sorted(np.nonzero(ok)[0], key=lambda i: swap[i] - stay[i]):
        if all(abs(int(t) - u) > window for u in taken):
            taken.append(int(t))
    for t in taken:
        s[t + 1:] ^= True
    if s[anchor]:
        s ^= True
    return s


def _rot_between(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The smallest rotation taking direction u to direction v (3, 3)."""
    from scipy.spatial.transform import Rotation

    u, v = u / np.linalg.norm(u), v / np.linalg.norm(v)
    return Rotation.align_vectors(v[None], u[None])[0].as_matrix()  # one pair: the shortest arc (scipy >= 1.11)


def exchanged_motion(A_o: np.ndarray, b_o: np.ndarray, top_self, end_self, top_other, end_other, centre_self,
                     mirror: np.ndarray | None = None):
    """The motion of one limb that mirrors its partner's: ``(R, t)`` per frame of the rotation-about-centre
    parametrisation (``x -> R (x - c) + c + t``) so that the limb's rest axis lands where the partner's
    posed axis is, reflected through the symmetry plane.

    ``A_o`` ``(T, 3, 3)``, ``b_o`` ``(T, 3)``: the partner's posed map ``y -> A_o y + b_o``. Corresponding
    points: the partner's rest axis is matched to this limb's by its top and direction (one rigid map),
    so the limb keeps its own rest shape and side.
    ``mirror`` ``(3, 3)``: the reflection through the symmetry plane (:attr:`LimbPair.mirror`; the side view's
    z = 0 when None).
    """
    S = np.diag([1.0, 1.0, -1.0]) if mirror is None else np.asarray(mirror, np.float64)
    u_self = np.asarray(end_self, np.float64) - np.asarray(top_self, np.float64)
    u_oth = S @ (np.asarray(end_other, np.float64) - np.asarray(top_other, np.float64))
    H = _rot_between(u_self, u_oth)  # rest: this limb's axis onto the mirrored partner's
    # psi(x) = S (H (x - top_self) + S top_other) maps this limb's rest points onto the partner's
    # new map: x -> S (A_o psi(x) + b_o) = (S A_o S H) x + S A_o (top_other - S H top_self) + S b_o
    R = np.einsum("ij,tjk,kl,lm->tim", S, A_o, S, H)
    off = np.asarray(top_other, np.float64) - S @ H @ np.asarray(top_self, np.float64)
    bvec = np.einsum("ij,tjk,k->ti", S, A_o, off) + b_o @ S.T
    c = np.asarray(centre_self, np.float64)
    t = bvec - c + np.einsum("tij,j->ti", R, c)
    return R, t


@torch.no_grad()
def resolve_crossings(bone_aa: torch.Tensor, bone_t: torch.Tensor, centres: torch.Tensor, pairs: list[LimbPair],
                      anchor: int, project, max_gap: float = MAX_GAP, window: int = WINDOW,
                      ratio: float = RATIO) -> list[int]:
    """Relabel every pair's frames (:func:`crossing_labels` on the posed end points' image paths, exchanges
    allowed where they are at most ``max_gap`` x the limbs' mean projected length apart) and write the exchanged
    frames' motion in place (:func:`exchanged_motion`). Returns the number of exchanged frames per pair.

    ``project``: the map of object-frame points ``(T, 3)``, one per frame, to image pixels ``(T, 2)``. The paths
    are compared unmirrored, where the feet cross in the image, whatever depth the fit gave them: a warm-up that
    slides a leg sideways instead of swinging it keeps the 3D ends apart at the crossing."""
    T = bone_aa.shape[0]
    R_all = axis_angle_to_matrix(bone_aa.detach().reshape(-1, 3).double()).reshape(T, -1, 3, 3).cpu().numpy()
    t_all = bone_t.detach().double().cpu().numpy()
    c_all = centres.detach().double().cpu().numpy()
    counts = []
    for pr in pairs:
        maps = {}
        for k in (pr.a, pr.b):
            A = R_all[:, k]
            maps[k] = (A, c_all[k] + t_all[:, k] - A @ c_all[k])

        def posed(k, x, maps=maps):
            return np.einsum("tij,j->ti", maps[k][0], x) + maps[k][1]

        end_a, end_b = project(posed(pr.a, pr.end_a)), project(posed(pr.b, pr.end_b))
        length = 0.5 * float((np.linalg.norm(end_a - project(posed(pr.a, pr.top_a)), axis=1)
                              + np.linalg.norm(end_b - project(posed(pr.b, pr.top_b)), axis=1)).mean())
        s = crossing_labels(end_a, end_b, anchor, max_gap * length, window, ratio)
        counts.append(int(s.sum()))
        if not s.any():
            continue
        idx = np.nonzero(s)[0]
        for me, oth, top_m, end_m, top_o, end_o in ((pr.a, pr.b, pr.top_a, pr.end_a, pr.top_b, pr.end_b),
                                                    (pr.b, pr.a, pr.top_b, pr.end_b, pr.top_a, pr.end_a)):
            A_o, b_o = maps[oth][0][idx], maps[oth][1][idx]
            R, t = exchanged_motion(A_o, b_o, top_m, end_m, top_o, end_o, c_all[me], pr.mirror)
            ii = torch.as_tensor(idx, device=bone_aa.device)
            bone_aa.data[ii, me] = matrix_to_axis_angle(torch.as_tensor(R)).to(bone_aa)
            bone_t.data[ii, me] = torch.as_tensor(t).to(bone_t)
    return counts


__all__ = ["LimbPair", "crossing_labels", "exchange_costs", "exchanged_motion", "resolve_crossings"]


def resolve_model_crossings(model, opt: torch.optim.Optimizer, pairs: list[LimbPair], canonical: int,
                            videos: list[tuple[int, int, int]] | None = None) -> list[int]:
    """:func:`resolve_crossings` on the model's bone motion, the feet compared where the fitted camera shows them
    (full-frame pixels); Adam's moments of every rewritten frame start afresh (they were the partner's). Returns
    the number of exchanged frames per pair.

    ``videos``: ``(start, stop, anchor)`` of each video, each followed on its own from its anchor frame (the rows
    synchronized videos share are followed once, in the first video listed); None: one video, from ``canonical``."""
    m = model
    before = (m.bone_aa.detach().clone(), m.bone_t.detach().clone())
    spans = videos or [(0, m.num_frames, canonical)]
    total = [0] * len(pairs)
    done: set[int] = set()
    for a, b, anchor in spans:
        rows = m.motion_of[a:b]
        if int(rows[0]) in done or not pairs:
            continue
        done.update(rows.tolist())
        with torch.no_grad():
            fr = torch.arange(a, b, device=m.bone_aa.device)
            Rt = m.root_rt(fr).double().cpu()
            Kf = m.intrinsics_frame(fr).double().cpu()

        def image(P: np.ndarray, Rt=Rt, Kf=Kf) -> np.ndarray:
            """Object-frame points (T, 3), one per frame -> full-frame pixels (T, 2)."""
            cam = (Rt[:, :, :3] @ torch.as_tensor(P, dtype=torch.float64)[..., None])[..., 0] + Rt[:, :, 3]
            return project(cam[:, None], Kf)[:, 0].numpy()

        aa, tt = m.bone_aa.detach()[rows].clone(), m.bone_t.detach()[rows].clone()
        counts = resolve_crossings(aa, tt, m.bone_centers, pairs, anchor - a, project=image)
        with torch.no_grad():
            m.bone_aa.data[rows] = aa
            m.bone_t.data[rows] = tt
        total = [x + y for x, y in zip(total, counts)]
    for p, old in zip((m.bone_aa, m.bone_t), before):
        st = opt.state.get(p)
        changed = (p.detach() != old).any(-1)
        if st and changed.any():
            for key in ("exp_avg", "exp_avg_sq"):
                if key in st:
                    st[key][changed] = 0
    return total if pairs else []
