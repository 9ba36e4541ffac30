"""Shared fixtures: one DEVICES list (CPU, plus CUDA when Warp and torch both see it), shared data."""

from __future__ import annotations

import os
import signal
from pathlib import Path
from unittest import mock

import pytest
import torch

from s3o_warp.coarse.model import coarse_model
from s3o_warp.data import flow as video_flow
from s3o_warp.data.store import prepare_data
from s3o_warp.fit import Fitter
from s3o_warp.run.checkpoint import latest_checkpoint

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("S3O_SHARED_DATA", REPO.parent / "shared" / "data"))


def _devices() -> list[str]:
    devs = ["cpu"]
    if torch.cuda.is_available():
        try:
            import warp as wp

            wp.config.quiet = True
            wp.init()
            if wp.get_cuda_device_count() > 0:
                devs.append("cuda:0")
        except Exception:  # pragma: no cover - a broken CUDA driver still lets the CPU tests run
            pass
    return devs


DEVICES = _devices()


@pytest.fixture(params=DEVICES)
def device(request) -> str:
    """Every op test runs once per device in DEVICES."""
    return request.param


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """../shared/data (or $S3O_SHARED_DATA); tests that need it skip with a message when absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared evaluation data not found at {SHARED_DATA} (set S3O_SHARED_DATA)")
    return SHARED_DATA


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)
    yield


@pytest.fixture
def sigint_raises():
    """SIGINT raises KeyboardInterrupt in the test (Python's default), however the suite was started (``nohup pytest
    &`` starts it ignored: SIG_IGN); the handler found is restored after. For tests that send themselves SIGINT."""
    found = signal.getsignal(signal.SIGINT)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        yield found
    finally:
        signal.signal(signal.SIGINT, found)


def smoke_config(**over):
    """The smoke preset at 64 px crops, 4-frame windows, no videos, plus ``over`` (dotted keys)."""
    from s3o_warp.config import make_config

    base = {"data.crop_size": 64, "motion.batch_frames": 4, "output.render_video": False}
    base.update(over)
    return make_config("smoke", overrides=[f"{k}={v}" for k, v in base.items()])


@pytest.fixture(scope="session")
def tiny_sequence(tmp_path_factory):
    """An 8-frame 96x72 clip of the built-in quadruped (rendered once per test session)."""
    from s3o_warp.synth import make_sequence

    out = tmp_path_factory.mktemp("seq") / "quad"
    make_sequence(out, frames=8, size=(96, 72), azim=(-15.0, 15.0), seed=0, progress=False)
    return out


@pytest.fixture(scope="session")
def small_sequence(tmp_path_factory):
    """A 16-frame 128x96 clip of the built-in quadruped: the smallest on which the fit keeps its tail (at
    ``tiny_sequence``'s size the tail is 1-2 px thick and the coarse mesh loses it)."""
    from s3o_warp.synth import make_sequence

    out = tmp_path_factory.mktemp("seq") / "quad16"
    make_sequence(out, frames=16, size=(128, 96), azim=(-15.0, 15.0), seed=0, progress=False)
    return out


# ---------------------------------------------------------------------------------------------------
# Helpers shared by the tests of the loop, the M-step and the resampling on a fit's state
# ---------------------------------------------------------------------------------------------------


def final_params(run):
    """The model parameters of a run's newest checkpoint."""
    st = torch.load(latest_checkpoint(run), weights_only=False)
    return st["model"]


def joint_fitter(tiny_sequence, tmp_path):
    """A Fitter in its joint phase after 3 steps on frames 0-3 (the bones have some motion). The M-step tests'
    cases (a far leg never seen moving, the shortest inner bone) were picked on this state, made with the medium
    preset's own finest flow level (1), which is pinned so the state stays."""
    cfg = smoke_config(**{"coarse.steps": 5, "motion.warmup_steps": 5})
    with mock.patch.object(video_flow, "FLOW_FINEST_SCALE", 1):
        data = prepare_data(tiny_sequence, cfg, tmp_path, torch.device("cpu"))
    f = Fitter(data, coarse_model(data, cfg), cfg, tmp_path, torch.device("cpu"))
    f.phase = "joint"
    f.opt = f.make_optimizer()
    frames = torch.arange(0, 4)
    for _ in range(3):
        f.opt.zero_grad()
        terms, _, _ = f.motion_losses(frames)
        sum(w * v for w, v in terms.values()).backward()
        f.step_window(frames)
    return cfg, data, f, frames


def posed_and_loss(f, frames):
    """The posed mesh and the motion loss of a Fitter on ``frames`` (no gradients)."""
    with torch.no_grad():
        return f.model(frames).clone(), float(sum(w * v for w, v in f.motion_losses(frames)[0].values()))


def assert_no_jump(before, after, loss0, loss1):
    """A skeleton edit moved the posed mesh by < 1 % of its diagonal (mean) and the loss by < 5 %."""
    diag = float((before.amax((0, 1)) - before.amin((0, 1))).norm())
    assert float((after - before).norm(dim=-1).mean()) < 0.01 * diag
    assert abs(loss1 - loss0) < 0.05 * loss0, (loss0, loss1)


def stop_in_joint_phase(monkeypatch, sequence, run, cfg, step: int = 2, match: str | None = None):
    """Fit ``sequence`` into ``run`` and stop it (as Ctrl-C does) at joint ``step``; its checkpoint is the next step's."""
    from s3o_warp.fit import FitInterrupted, Fitter, fit

    orig = Fitter.motion_losses

    def stopping(self, frames):
        if self.phase == "joint" and self.step == step:
            self.request_stop()
        return orig(self, frames)

    monkeypatch.setattr(Fitter, "motion_losses", stopping)
    with pytest.raises(FitInterrupted, match=match):
        fit(sequence, run, cfg, torch.device("cpu"))
    monkeypatch.setattr(Fitter, "motion_losses", orig)
