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
from s3o_warp.geometry import axis_angle_to_matrix

log = logging.getLogger(__name__)

HYPOTHESIS_REFINE = 3
"""The best this many hypotheses go on for HYPOTHESIS_REFINE_STEPS more steps and are ranked again (0 or 1 = no
second round): after ``motion.hypothesis_steps`` the scores of neighbouring turn rates are often within a few
per cent (DAVIS dog: within 1.5 %; after the second round the rate the other seeds pick leads by 5-10 %)."""
HYPOTHESIS_REFINE_STEPS = 60
"""Further steps of each refined hypothesis."""


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

    def state_dict(self) -> dict:
        """What a checkpoint keeps (the optimiser in training is the checkpoint's own)."""
        return {k: v for k, v in asdict(self).items() if k != "opt_state"}

    @classmethod
    def from_state(cls, state: dict, opt_state: dict) -> Search:
        return cls(**state, opt_state=opt_state)

    def where(self) -> str:
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


def select_hypothesis(fit, search: Search | None = None) -> float:
    """Score root-rotation hypotheses (constant turn rates about the object's vertical axis) by a short
    warm-up each and keep the best (LASR/S3O's camera hypotheses); returns the chosen rate (deg/frame).

    ``fit`` is the loop (:class:`s3o_warp.fit.Fitter`): its model, optimiser, generator and step are used and
    left as the warm-up starts from them (the chosen turn applied, a fresh optimiser, the generator as before).
    After each step ``fit.stop_point(search)`` writes a checkpoint holding the search and stops when a stop was
    requested; ``search`` (read from such a checkpoint) goes on from there.
    """
    mc, m = fit.cfg.motion, fit.model
    T, c = m.num_frames, fit.coarse.canonical
    if search is None:
        rates = np.linspace(-mc.hypothesis_max_rate, mc.hypothesis_max_rate, mc.hypotheses)
        if 0.0 not in rates:
            rates = np.append(rates, 0.0)
        rates = [float(mc.turn_rate)] if mc.turn_rate is not None else [float(r) for r in rates]
        search = Search(rates=rates, base=copy.deepcopy(m.state_dict()), gen_state=fit.gen.get_state())

    def apply(rate: float) -> None:
        m.load_state_dict(search.base)
        ang = torch.deg2rad(torch.tensor(rate * (np.arange(T) - c), dtype=torch.float32, device=fit.device))
        aa = torch.zeros(T, 3, device=fit.device)
        aa[:, 1] = ang
        with torch.no_grad():
            m.root_R0.copy_(search.base["root_R0"] @ axis_angle_to_matrix(aa))

    def optimiser(state: dict | None = None) -> torch.optim.Optimizer:
        """Only the root and the camera are free: with the bones free too, they absorb a wrong turn."""
        opt = torch.optim.Adam([
            {"params": [m.root_aa, m.root_t], "lr": mc.lr_motion, "name": "motion"},
            {"params": [m.log_focal, m.pp], "lr": mc.lr_camera, "name": "camera"}])
        if state is not None:
            opt.load_state_dict(state)
        return opt

    def train(steps: int, bar: tqdm) -> float:
        """The rest of ``steps`` warm-up steps on random windows from the current state, then this hypothesis'
        score: its flow error over every pair of frames 1-32 apart, the mean over the gaps
        (:func:`~s3o_warp.motion.objective.flow_by_gap`: texture motion tells a turn from a deformation, and a wrong
        turn rate grows with the gap), or the whole loss when the sequence has no flow term."""
        fit.step = search.steps_done
        while fit.step < steps:
            frames = fit.windows.random()
            fit.opt.zero_grad(set_to_none=True)
            terms, _, _ = fit.motion_losses(frames)
            total = sum(w * v for w, v in terms.values())
            if not torch.isfinite(total):
                bar.update(steps - fit.step)
                fit.step = 0
                return float("inf")
            total.backward()
            fit.step_window(frames)
            fit.step += 1
            search.steps_done = fit.step
            bar.update(1)
            fit.stop_point(search)
        fit.step = 0
        try:
            if mc.w_flow > 0:
                by_gap = fit.flow_by_gap()
                log.debug("camera hypothesis: flow error by gap %s",
                          ", ".join(f"{g}: {v:.3f}" for g, v in by_gap.items()))
                return float(np.mean(list(by_gap.values())))
            return sum(fit.mean_terms().values())
        except interrupt.Interrupted:  # stopped while scoring: the checkpoint has every step, the score is redone
            fit.stop_point(search)
            raise

    def start(rate: float | None, snap=None) -> None:
        """The hypothesis to train: a fresh one (``rate``, or a first-round ``snap`` going on), or the one the
        checkpoint holds (the fit's model and generator are already its own)."""
        if search.steps_done:
            fit.opt = optimiser(search.opt_state)
        elif snap is None:
            apply(rate)
            fit.gen.set_state(search.gen_state)
            fit.opt = optimiser()
        else:
            m.load_state_dict(snap[0])
            fit.opt = optimiser(snap[1])
            fit.gen.set_state(search.snaps[0][2])  # the same windows for every finalist
        search.opt_state = None

    if mc.turn_rate is None:
        steps = len(search.rates) * mc.hypothesis_steps
        steps += min(HYPOTHESIS_REFINE, len(search.rates)) * HYPOTHESIS_REFINE_STEPS if _refining() else 0
        done = (len(search.scores) * mc.hypothesis_steps + len(search.refined) * HYPOTHESIS_REFINE_STEPS
                + search.steps_done)
        with tqdm(total=steps, initial=done, desc="hypotheses", unit="step", dynamic_ncols=True, leave=True) as bar:
            while len(search.scores) < len(search.rates):
                rate = search.rates[len(search.scores)]
                bar.set_postfix(rate=f"{rate:+.2f}")
                start(rate)
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
    apply(best)
    m.visited.zero_()
    fit.gen.set_state(search.gen_state)
    fit.opt = fit.make_optimizer()
    fit.record({"phase": "eval", "step": 0, "seconds": round(time.perf_counter() - fit.t0, 3), "what": "hypotheses",
               "rates_deg_per_frame": search.rates, "scores": scores,
               "refined": {f"{r:g}": v for r, v in refined.items()}, "chosen": best})
    log.info("camera hypotheses: turn rate %.2f deg/frame chosen (scores %s%s)", best,
             ", ".join(f"{x:.4f}" for x in scores),
             "; refined " + ", ".join(f"{r:g}: {v:.4f}" for r, v in refined.items()) if refined else "")
    return best
