"""Camera hypotheses at the start of the warm-up (paper 3.3; LASR's and S3O's): the root's rotation is tried at
several constant turn rates about the object's vertical axis, each scored by a short warm-up, and the best kept.

The search shows a progress bar and stops at any step when a stop is requested: :class:`Search` is where it
stands, and a checkpoint taken inside it holds that, so a resumed fit goes on from the same step and chooses what
an uninterrupted one chooses.
"""

from __future__ import annotations

import copy
import logging
import time
from dataclasses import asdict, dataclass, field

import numpy as np
import torch
from tqdm import tqdm

from s3o_warp import interrupt
from s3o_warp.errors import InputError
from s3o_warp.geometry import axis_angle_to_matrix
from s3o_warp.motion.losses import soft_iou

log = logging.getLogger(__name__)

HYPOTHESIS_REFINE = 3
"""The best this many hypotheses go on for HYPOTHESIS_REFINE_STEPS more steps and are ranked again (0 or 1 = no
second round): after ``motion.hypothesis_steps`` the scores of neighbouring turn rates are often within a few
per cent (DAVIS dog: within 1.5 %; after the second round the rate the other seeds pick leads by 5-10 %)."""
HYPOTHESIS_REFINE_STEPS = 60
"""Further steps of each refined hypothesis."""
ORIENTATIONS = 8
"""Root orientations about the object's vertical axis tried for each video after the first (several videos of one
object, unknown cameras): evenly spaced, 0 included (360 / 8 = 45 degrees apart)."""
ORIENTATION_STEPS = 30
"""Steps (root and camera free, on the video's anchor window) each orientation is fitted for before it is scored."""
ORIENTATION_TILTS = (-30.0, -15.0, 15.0, 30.0)
"""After the orientations, the best one is tried again with the turn's axis tipped by each of these (degrees) about
the reference camera's horizontal axis: the body's vertical is the reference camera's vertical tipped by the
camera's elevation, so two videos filmed from a little above on opposite sides are a half turn about that tipped
axis (about the camera's own vertical, the second body comes out rolled by twice the elevation)."""
MIN_ORIENTATION_IOU = 0.3
"""A video whose best orientation's mask IoU on its anchor window stays under this fits no orientation of the body
(another object, or masks of something else): refused with one line naming it."""


@dataclass
class Search:
    """Where a hypothesis search stands. The hypothesis in training (``steps_done`` > 0) is the fit's model,
    optimiser and generator; everything else is here.

    Attributes:
        rates: the turn rates tried, degrees per frame.
        base: the model's state before the search (each hypothesis starts from it).
        gen_state: the fit's generator before the search (each hypothesis draws the same windows).
        scores: the first round's score of each finished rate, in order.
        snaps: (model state, optimiser state, generator state) of each finished rate, for the second round.
        top: indices of the second round's rates, once the first round is over.
        refined: the second round's score of each finished finalist, by rate.
        steps_done: steps already taken by the hypothesis in training.
        opt_state: its optimiser's state, when the search was read from a checkpoint.
        video: the video searched (several videos), -1 for the whole sequence (one video).
        yaws: the video's orientations about the vertical to try first (degrees; empty: the reference video), then
            the best of them again for each of :data:`ORIENTATION_TILTS`.
        tilts: each orientation's tip of the turn's axis (degrees; 0 for the first :data:`ORIENTATIONS`).
        yaw_scores, yaw_ious: each finished orientation's score (silhouette and flow terms on the anchor window) and
            mask IoU there.
        chosen: each video already searched: its orientation, turn rate and scores.
    """

    rates: list[float]
    base: dict
    gen_state: torch.Tensor
    scores: list[float] = field(default_factory=list)
    snaps: list = field(default_factory=list)
    top: list[int] | None = None
    refined: dict[float, float] = field(default_factory=dict)
    steps_done: int = 0
    opt_state: dict | None = None
    video: int = -1
    yaws: list[float] = field(default_factory=list)
    tilts: list[float] = field(default_factory=list)
    yaw_scores: list[float] = field(default_factory=list)
    yaw_ious: list[float] = field(default_factory=list)
    chosen: list[dict] = field(default_factory=list)

    def state_dict(self) -> dict:
        """What a checkpoint keeps (the optimiser in training is the checkpoint's own)."""
        return {k: v for k, v in asdict(self).items() if k != "opt_state"}

    @classmethod
    def from_state(cls, state: dict, opt_state: dict) -> Search:
        state = {"tilts": [0.0] * len(state.get("yaws", [])), **state}  # a checkpoint written before tilts
        return cls(**state, opt_state=opt_state)

    def where(self) -> str:
        if len(self.yaw_scores) < len(self.yaws):
            return (f"video {self.video}, orientation {len(self.yaw_scores) + 1} of {len(self.yaws)}, step "
                    f"{self.steps_done}")
        if len(self.scores) < len(self.rates):
            return f"turn rate {len(self.scores) + 1} of {len(self.rates)}, step {self.steps_done}"
        return f"finalist {len(self.refined) + 1} of {len(self.top or [])}, step {self.steps_done}"


def v_minimum(rates, scores, fallback: float) -> float:
    """The turn rate between the scored ones where ``c + k |rate - r0|`` (k > 0) fits ``scores`` best (least
    squares over r0 on a 0.01-degree grid spanning the rates): the flow error over a gap grows with the size of the
    rate's error, so the scores of rates either side of the truth form a V, and its vertex lies between the grid's
    rates. ``fallback`` when the scores do not fall towards a vertex (k <= 0)."""
    x, y = np.asarray(rates, np.float64), np.asarray(scores, np.float64)
    if len(x) < 3 or not np.all(np.isfinite(y)):
        return fallback
    best, best_err = fallback, np.inf
    for r0 in np.arange(x.min(), x.max() + 0.005, 0.01):
        A = np.stack([np.ones_like(x), np.abs(x - r0)], 1)
        (c, k), *_ = np.linalg.lstsq(A, y, rcond=None)
        err = float(((A @ [c, k] - y) ** 2).sum())
        if k > 1e-9 * max(float(np.abs(y).max()), 1.0) and err < best_err - 1e-12:
            best, best_err = float(np.round(r0, 2)), err
    return best


def _refining() -> bool:
    return HYPOTHESIS_REFINE > 1 and HYPOTHESIS_REFINE_STEPS > 0


def _new_search(fit, video: int, chosen: list[dict]) -> Search:
    mc, m = fit.cfg.motion, fit.model
    rates = np.linspace(-mc.hypothesis_max_rate, mc.hypothesis_max_rate, mc.hypotheses)
    if 0.0 not in rates:
        rates = np.append(rates, 0.0)
    rates = [float(mc.turn_rate)] if mc.turn_rate is not None else [0.0] if mc.hypotheses == 1 else \
        [float(r) for r in rates]
    yaws = [] if video < 0 or video == fit.reference_video else [360.0 * k / ORIENTATIONS for k in range(ORIENTATIONS)]
    return Search(rates=rates, base=copy.deepcopy(m.state_dict()), gen_state=fit.gen.get_state(), video=video,
                  yaws=yaws, tilts=[0.0] * len(yaws), chosen=list(chosen))


def select_hypotheses(fit, search: Search | None = None) -> list[dict]:
    """:func:`select_hypothesis` for every video of the fit, the reference video (the canonical frame's) first, then
    each other video's orientation and turn rate against the shape fitted so far; returns each video's choice."""
    if fit.data.num_videos == 1:
        return [{"video": 0, "yaw_deg": 0.0, "turn_rate": select_hypothesis(fit, search)}]
    order = [fit.reference_video] + [v for v in range(fit.data.num_videos) if v != fit.reference_video]
    if search is None:
        search = _new_search(fit, order[0], [])
    for v in order[order.index(search.video):]:
        if search is None:
            search = _new_search(fit, v, chosen)
        select_hypothesis(fit, search)
        chosen, search = search.chosen, None
    return chosen


def select_hypothesis(fit, search: Search | None = None) -> float:
    """Score root-rotation hypotheses (constant turn rates about the object's vertical axis) by a short
    warm-up each and keep the best (LASR/S3O's camera hypotheses); returns the chosen rate (deg/frame).

    With several videos ``search.video`` is the one searched (its frames only; the others keep their roots), and a
    video other than the reference first tries :data:`ORIENTATIONS` turns of the body about the vertical on its
    anchor window, each fitted for :data:`ORIENTATION_STEPS` steps (root and camera) and scored by the silhouette
    and flow terms there; the rates then turn the video from its best orientation.

    ``fit`` is the loop (:class:`s3o_warp.fit.Fitter`): its model, optimiser, generator and step are used and
    left as the warm-up starts from them (the chosen turn applied, a fresh optimiser, the generator as before).
    After each step ``fit.stop_point(search)`` writes a checkpoint holding the search and stops when a stop was
    requested; ``search`` (read from such a checkpoint) goes on from there.
    """
    mc, m = fit.cfg.motion, fit.model
    if search is None:
        search = _new_search(fit, -1, [])
    v = search.video
    if v < 0:
        a, b, c = 0, m.num_frames, fit.coarse.canonical
        name = None
    else:
        a, b = fit.windows.videos[v]
        c, name = fit.windows.anchors[v], fit.data.videos[v].name
    n = min(mc.batch_frames, b - a)
    first = min(max(c - n // 2, a), b - n)
    anchor_window = torch.arange(first, first + n, device=fit.device)

    def apply(rate: float, yaw: float = 0.0, tilt: float = 0.0) -> None:
        m.load_state_dict(search.base)
        ang = torch.deg2rad(torch.tensor(yaw + rate * (np.arange(a, b) - c), dtype=torch.float32, device=fit.device))
        aa = torch.zeros(b - a, 3, device=fit.device)
        aa[:, 1] = ang * float(np.cos(np.radians(tilt)))  # about the vertical, tipped about the camera's horizontal
        if tilt:
            aa[:, 2] = ang * float(np.sin(np.radians(tilt)))
        with torch.no_grad():
            Ry = axis_angle_to_matrix(aa)
            m.root_R0[a:b].copy_(search.base["root_R0"][a:b] @ Ry)
            if v >= 0:  # several videos: turned about the body's centre, not the lift's origin (off to one side)
                verts = search.base["verts"]
                p = 0.5 * (verts.min(0).values + verts.max(0).values)
                R = axis_angle_to_matrix(search.base["root_aa"][a:b]) @ search.base["root_R0"][a:b]
                m.root_t[a:b] = search.base["root_t"][a:b] + R @ p - (R @ Ry) @ p

    def best_yaw() -> tuple[float, float]:
        """The best orientation so far: (yaw, tilt) in degrees."""
        if not search.yaws:
            return 0.0, 0.0
        k = int(np.argmin(search.yaw_scores))
        return search.yaws[k], search.tilts[k]

    def optimiser(state: dict | None = None) -> torch.optim.Optimizer:
        """Only the root and the camera are free: with the bones free too, they absorb a wrong turn."""
        opt = torch.optim.Adam([
            {"params": [m.root_aa, m.root_t], "lr": mc.lr_motion, "name": "motion"},
            {"params": [m.log_focal, m.pp], "lr": mc.lr_camera, "name": "camera"}])
        if state is not None:
            opt.load_state_dict(state)
        return opt

    def steps_to(steps: int, bar: tqdm, window=None) -> bool:
        """The rest of ``steps`` warm-up steps on random windows (of the video; or ``window`` always) from the
        current state; False when the loss went NaN/Inf."""
        fit.step = search.steps_done
        while fit.step < steps:
            frames = fit.windows.random(None if v < 0 else v) if window is None else window
            fit.opt.zero_grad(set_to_none=True)
            terms, _, _ = fit.motion_losses(frames)
            total = sum(w * v_ for w, v_ in terms.values())
            if not torch.isfinite(total):
                bar.update(steps - fit.step)
                fit.step = 0
                return False
            total.backward()
            fit.step_window(frames)
            fit.step += 1
            search.steps_done = fit.step
            bar.update(1)
            fit.stop_point(search)
        fit.step = 0
        return True

    def train(steps: int, bar: tqdm) -> float:
        """:func:`steps_to`, then this hypothesis' score: its flow error over every pair of frames 1-32 apart, the
        mean over the gaps (:func:`~s3o_warp.motion.objective.flow_by_gap`: texture motion tells a turn from a
        deformation, and a wrong turn rate grows with the gap), or the whole loss when the sequence has no flow
        term."""
        if not steps_to(steps, bar):
            return float("inf")
        try:
            if mc.w_flow > 0:
                by_gap = fit.flow_by_gap() if v < 0 else fit.flow_by_gap((a, b))
                log.debug("camera hypothesis: flow error by gap %s",
                          ", ".join(f"{g}: {v_:.3f}" for g, v_ in by_gap.items()))
                return float(np.mean(list(by_gap.values())))
            return sum((fit.mean_terms() if v < 0 else fit.mean_terms((a, b))).values())
        except interrupt.Interrupted:  # stopped while scoring: the checkpoint has every step, the score is redone
            fit.stop_point(search)
            raise

    def start(rate: float | None, snap=None, yaw: float = 0.0, tilt: float = 0.0) -> None:
        """The hypothesis to train: a fresh one (``rate``, or a first-round ``snap`` going on), or the one the
        checkpoint holds (the fit's model and generator are already its own)."""
        if search.steps_done:
            fit.opt = optimiser(search.opt_state)
        elif snap is None:
            apply(rate, yaw, tilt)
            fit.gen.set_state(search.gen_state)
            fit.opt = optimiser()
        else:
            m.load_state_dict(snap[0])
            fit.opt = optimiser(snap[1])
            fit.gen.set_state(search.snaps[0][2])  # the same windows for every finalist
        search.opt_state = None

    if search.yaws:
        with tqdm(total=(ORIENTATIONS + len(ORIENTATION_TILTS)) * ORIENTATION_STEPS,
                  initial=len(search.yaw_scores) * ORIENTATION_STEPS + search.steps_done, desc=f"orient {name}",
                  unit="step", dynamic_ncols=True, leave=True) as bar:
            while True:
                if len(search.yaw_scores) == ORIENTATIONS and len(search.yaws) == ORIENTATIONS:
                    grid_yaw = best_yaw()[0]  # the grid done: its best again, the turn's axis tipped
                    search.yaws += [grid_yaw] * len(ORIENTATION_TILTS)
                    search.tilts += list(ORIENTATION_TILTS)
                if len(search.yaw_scores) >= len(search.yaws):
                    break
                yaw, tilt = search.yaws[len(search.yaw_scores)], search.tilts[len(search.yaw_scores)]
                bar.set_postfix(yaw=f"{yaw:.0f}", tilt=f"{tilt:.0f}")
                start(0.0, yaw=yaw, tilt=tilt)
                ok = steps_to(ORIENTATION_STEPS, bar, anchor_window)
                with torch.no_grad():
                    terms, sil, mask = fit.motion_losses(anchor_window)
                score = sum(float(w * t) for k, (w, t) in terms.items() if k in ("sil", "flow")) if ok else float("inf")
                search.yaw_scores.append(score)
                search.yaw_ious.append(float(soft_iou((sil > 0.5).float(), mask).mean()) if ok else 0.0)
                search.steps_done = 0
                fit.stop_point(search)
        k = int(np.argmin(search.yaw_scores))
        if search.yaw_ious[k] < MIN_ORIENTATION_IOU:
            raise InputError(
                f"video '{name}' fits no orientation of the body seen in the other videos (best mask IoU "
                f"{search.yaw_ious[k]:.2f} at {search.yaws[k]:.0f} degrees on frames {int(anchor_window[0]) - a}-"
                f"{int(anchor_window[-1]) - a}); is it the same object? leave it out or check its masks")

    if len(search.rates) > 1:
        steps = len(search.rates) * mc.hypothesis_steps
        steps += min(HYPOTHESIS_REFINE, len(search.rates)) * HYPOTHESIS_REFINE_STEPS if _refining() else 0
        done = (len(search.scores) * mc.hypothesis_steps + len(search.refined) * HYPOTHESIS_REFINE_STEPS
                + search.steps_done)
        with tqdm(total=steps, initial=done, desc="hypotheses" + (f" {name}" if name else ""), unit="step",
                  dynamic_ncols=True, leave=True) as bar:
            while len(search.scores) < len(search.rates):
                rate = search.rates[len(search.scores)]
                bar.set_postfix(rate=f"{rate:+.2f}")
                yaw, tilt = best_yaw()
                start(rate, yaw=yaw, tilt=tilt)
                score = train(mc.hypothesis_steps, bar)
                search.scores.append(score)
                search.snaps.append((copy.deepcopy(m.state_dict()), copy.deepcopy(fit.opt.state_dict()),
                                     fit.gen.get_state()) if _refining() else None)
                search.steps_done = 0
                fit.stop_point(search)
            if _refining():  # the best few go on from where they stopped and are ranked again
                if search.top is None:
                    order = np.argsort(search.scores)[:HYPOTHESIS_REFINE]
                    search.top = [int(i) for i in order if np.isfinite(search.scores[i])]
                    bar.total = bar.n + len(search.top) * HYPOTHESIS_REFINE_STEPS  # fewer when a rate failed
                    bar.refresh()
                while len(search.refined) < len(search.top):
                    i = search.top[len(search.refined)]
                    bar.set_postfix(rate=f"{search.rates[i]:+.2f}", round=2)
                    start(None, search.snaps[i])
                    search.refined[search.rates[i]] = train(HYPOTHESIS_REFINE_STEPS, bar)
                    search.steps_done = 0
                    fit.stop_point(search)
        scores, refined = search.scores, search.refined
        best = min(refined, key=refined.get) if refined else search.rates[int(np.argmin(scores))]
        if len(refined) >= 3:
            best = v_minimum(list(refined), list(refined.values()), best)
    else:
        scores, refined, best = [float("nan")], {}, search.rates[0]
    yaw, tilt = best_yaw()
    apply(best, yaw, tilt)
    m.visited.zero_()
    fit.gen.set_state(search.gen_state)
    fit.opt = fit.make_optimizer()
    rec = {"phase": "eval", "step": 0, "seconds": round(time.perf_counter() - fit.t0, 3), "what": "hypotheses",
           "rates_deg_per_frame": search.rates, "scores": scores,
           "refined": {f"{r:g}": v_ for r, v_ in refined.items()}, "chosen": best}
    if v >= 0:
        choice = {"video": v, "name": name, "anchor_frame": c - a, "yaw_deg": yaw, "tilt_deg": tilt, "turn_rate": best,
                  "yaws_deg": search.yaws, "tilts_deg": search.tilts, "yaw_scores": search.yaw_scores,
                  "yaw_ious": search.yaw_ious}
        others = [i for i in range(len(search.yaws)) if search.yaws[i] != yaw]  # the runner-up: another yaw
        if others:
            k = int(np.argmin(search.yaw_scores))
            r = min(others, key=lambda i: search.yaw_scores[i])
            s0, s1 = search.yaw_scores[k], search.yaw_scores[r]
            choice.update(runner_up_yaw_deg=search.yaws[r], margin=float((s1 - s0) / max(abs(s1), 1e-12)),
                          iou=search.yaw_ious[k])
        search.chosen.append(choice)
        rec.update(video=name, orientation=choice)
        if search.yaws:
            log.info("video '%s': orientation %.0f degrees about the vertical (tipped %.0f degrees) from the first "
                     "video's (score %.4f, %.0f %% below the next, %.0f degrees; mask IoU %.3f on its frames %d-%d)",
                     name, yaw, tilt, min(search.yaw_scores), 100 * choice["margin"], choice["runner_up_yaw_deg"],
                     choice["iou"], int(anchor_window[0]) - a, int(anchor_window[-1]) - a)
    fit.record(rec)
    log.info("camera hypotheses%s: turn rate %.2f deg/frame chosen (scores %s%s)", f" of '{name}'" if name else "",
             best, ", ".join(f"{x:.4f}" for x in scores),
             "; refined " + ", ".join(f"{r:g}: {v_:.4f}" for r, v_ in refined.items()) if refined else "")
    return best
