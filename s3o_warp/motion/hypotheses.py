"""Camera hypotheses at the start of the warm-up (paper 3.3; LASR's and S3O's): the root's rotation is tried at
several constant turn rates about the object's vertical axis, each scored by a short warm-up, and the best kept.
"""

from __future__ import annotations

import copy
import logging
import time

import numpy as np
import torch

from s3o_warp.geometry import axis_angle_to_matrix

log = logging.getLogger(__name__)

HYPOTHESIS_REFINE = 3
"""The best this many hypotheses go on for HYPOTHESIS_REFINE_STEPS more steps and are ranked again (0 or 1 = no
second round): after ``motion.hypothesis_steps`` the scores of neighbouring turn rates are often within a few
per cent (DAVIS dog: within 1.5 %; after the second round the rate the other seeds pick leads by 5-10 %)."""
HYPOTHESIS_REFINE_STEPS = 60
"""Further steps of each refined hypothesis."""


def select_hypothesis(fit) -> float:
    """Score root-rotation hypotheses (constant turn rates about the object's vertical axis) by a short
    warm-up each and keep the best (LASR/S3O's camera hypotheses); returns the chosen rate (deg/frame).

    ``fit`` is the loop (:class:`s3o_warp.fit.Fitter`): its model, optimiser, generator and step are used and
    left as the warm-up starts from them (the chosen turn applied, a fresh optimiser, the generator as before).
    """
    mc, m = fit.cfg.motion, fit.model
    base = copy.deepcopy(m.state_dict())
    T, c = m.num_frames, fit.coarse.canonical
    rates = np.linspace(-mc.hypothesis_max_rate, mc.hypothesis_max_rate, mc.hypotheses)
    if 0.0 not in rates:
        rates = np.append(rates, 0.0)
    gen_state = fit.gen.get_state()

    def apply(rate: float) -> None:
        m.load_state_dict(base)
        ang = torch.deg2rad(torch.tensor(rate * (np.arange(T) - c), dtype=torch.float32, device=fit.device))
        aa = torch.zeros(T, 3, device=fit.device)
        aa[:, 1] = ang
        with torch.no_grad():
            m.root_R0.copy_(base["root_R0"] @ axis_angle_to_matrix(aa))

    def optimiser() -> torch.optim.Optimizer:
        """Only the root and the camera are free: with the bones free too, they absorb a wrong turn."""
        return torch.optim.Adam([
            {"params": [m.root_aa, m.root_t], "lr": mc.lr_motion, "name": "motion"},
            {"params": [m.log_focal, m.pp], "lr": mc.lr_camera, "name": "camera"}])

    def train(steps: int) -> float:
        """``steps`` warm-up steps on random windows from the current state, then this hypothesis' score: its
        optical-flow term over every frame (texture motion tells a turn from a deformation), or the whole loss
        when the sequence has no flow term."""
        for _ in range(steps):
            frames = fit.windows.random()
            fit.opt.zero_grad(set_to_none=True)
            terms, _, _ = fit.motion_losses(frames)
            total = sum(w * v for w, v in terms.values())
            if not torch.isfinite(total):
                fit.step = 0
                return float("inf")
            total.backward()
            fit.step_window(frames)
            fit.step += 1
        fit.step = 0
        terms = fit.mean_terms()
        return terms["flow"] if "flow" in terms else sum(terms.values())

    refined: dict[float, float] = {}
    if mc.turn_rate is not None:
        rates, scores = np.array([float(mc.turn_rate)]), [float("nan")]
    else:
        scores, snaps = [], []
        keep = HYPOTHESIS_REFINE > 1 and HYPOTHESIS_REFINE_STEPS > 0
        for rate in rates:
            apply(float(rate))
            fit.gen.set_state(gen_state)
            fit.opt = optimiser()
            scores.append(train(mc.hypothesis_steps))
            snaps.append((copy.deepcopy(m.state_dict()), copy.deepcopy(fit.opt.state_dict()),
                          fit.gen.get_state()) if keep else None)
        if keep:  # the best few go on from where they stopped and are ranked again
            top = [int(i) for i in np.argsort(scores)[:HYPOTHESIS_REFINE] if np.isfinite(scores[i])]
            for i in top:
                m.load_state_dict(snaps[i][0])
                fit.opt = optimiser()
                fit.opt.load_state_dict(snaps[i][1])
                fit.gen.set_state(snaps[0][2])  # the same windows for every finalist
                refined[float(rates[i])] = train(HYPOTHESIS_REFINE_STEPS)
            del snaps
    if refined:
        best = min(refined, key=refined.get)
    else:
        best = float(rates[int(np.argmin(scores))] if mc.turn_rate is None else rates[0])
    apply(best)
    m.visited.zero_()
    fit.gen.set_state(gen_state)
    fit.opt = fit.make_optimizer()
    fit.record({"phase": "eval", "step": 0, "seconds": round(time.perf_counter() - fit.t0, 3), "what": "hypotheses",
               "rates_deg_per_frame": [float(r) for r in rates], "scores": scores,
               "refined": {f"{r:g}": v for r, v in refined.items()}, "chosen": best})
    log.info("camera hypotheses: turn rate %.2f deg/frame chosen (scores %s%s)", best,
             ", ".join(f"{x:.4f}" for x in scores),
             "; refined " + ", ".join(f"{r:g}: {v:.4f}" for r, v in refined.items()) if refined else "")
    return best
