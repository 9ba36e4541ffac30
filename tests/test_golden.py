"""The fit's behaviour pinned at a fixed seed on the CPU: a change that should not change the fit must pass this.

Two fits are recorded in ``tests/golden/fit.json``:

- ``tiny``: the smoke preset on ``tiny_sequence`` (30 coarse, 40 warm-up, 60 joint steps), every step's loss and
  loss terms (``motion.log_every=1``), and the hard-render IoU before and after;
- ``quadruped``: the CI skeleton fit of ``small_sequence`` (``test_fit.py``), its final metrics and skeleton.

Values are compared at a relative tolerance of 1e-5. A fit is repeatable bit for bit only on the same CPU, torch
and Warp (``repeatable``; it is chaotic across machines), so on another environment the test skips and names the
one it was recorded on. To record it again, from a commit whose behaviour is the reference::

    python tests/test_golden.py --write
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import pytest
import torch

GOLDEN = Path(__file__).parent / "golden" / "fit.json"
RTOL, ATOL = 1e-5, 1e-7


def environment() -> dict:
    """What a fit's last bits depend on: the CPU model, torch and Warp."""
    import warp

    from s3o_warp.provenance import cpu_name

    return {"cpu": cpu_name(), "torch": torch.__version__, "warp": warp.__version__}


def tiny_record(sequence: Path, run: Path) -> dict:
    from conftest import smoke_config

    from s3o_warp.fit import fit

    cfg = smoke_config(**{"coarse.steps": 30, "motion.warmup_steps": 40, "motion.steps": 60, "motion.log_every": 1})
    fit(sequence, run, cfg, torch.device("cpu"))
    steps, evals = [], []
    for line in (run / "log.jsonl").read_text().splitlines():
        r = json.loads(line)
        if r["phase"] == "eval":
            if "iou_all_frames" in r:
                evals.append({"what": r["what"], "iou_all_frames": r["iou_all_frames"]})
            continue
        steps.append({"phase": r["phase"], "step": r["step"], "loss": r["loss"], "terms": r["terms"]})
    return {"steps": steps, "evals": evals}


def quadruped_record(sequence: Path, run: Path) -> dict:
    from conftest import smoke_config

    from s3o_warp.fit import fit

    cfg = smoke_config(**{"data.crop_size": 96, "coarse.target_vertices": 1200, "coarse.steps": 30,
                          "motion.warmup_steps": 40, "motion.steps": 60})
    metrics = fit(sequence, run, cfg, torch.device("cpu"))
    skel = json.loads((run / "skeleton.json").read_text())
    return {"metrics": _numbers(metrics), "skeleton": _numbers(skel)}


def _numbers(obj):
    """The numbers, strings and booleans of a JSON-like object (seconds and paths dropped: they vary by run)."""
    if isinstance(obj, dict):
        return {k: _numbers(v) for k, v in obj.items()
                if k not in ("run", "sequence")
                and not any(s in k for s in ("seconds", "time", "path", "commit", "peak_rss", "version"))}
    if isinstance(obj, (list, tuple)):
        return [_numbers(v) for v in obj]
    return obj


def compare(got, want, where: str = "") -> list[str]:
    """Every place where ``got`` differs from ``want`` (numbers at RTOL/ATOL, the rest exactly)."""
    if isinstance(want, dict):
        if not isinstance(got, dict) or set(got) != set(want):
            return [f"{where}: keys {sorted(got) if isinstance(got, dict) else type(got).__name__} != {sorted(want)}"]
        return [d for k in want for d in compare(got[k], want[k], f"{where}.{k}")]
    if isinstance(want, list):
        if not isinstance(got, list) or len(got) != len(want):
            return [f"{where}: length {len(got) if isinstance(got, list) else type(got).__name__} != {len(want)}"]
        return [d for i, (g, w) in enumerate(zip(got, want)) for d in compare(g, w, f"{where}[{i}]")]
    if isinstance(want, float) or (isinstance(want, int) and not isinstance(want, bool) and isinstance(got, float)):
        if not isinstance(got, (int, float)) or isinstance(got, bool):
            return [f"{where}: {got!r} != {want!r}"]
        if math.isnan(want) and math.isnan(got):
            return []
        return [] if math.isclose(got, want, rel_tol=RTOL, abs_tol=ATOL) else [f"{where}: {got!r} != {want!r}"]
    return [] if got == want else [f"{where}: {got!r} != {want!r}"]


@pytest.fixture(scope="module")
def golden() -> dict:
    if not GOLDEN.is_file():
        pytest.fail(f"{GOLDEN} is missing; record it with: python tests/test_golden.py --write")
    g = json.loads(GOLDEN.read_text())
    env = environment()
    if g["environment"] != env:
        pytest.skip(f"golden fit recorded on {g['environment']}, this is {env}: the fit repeats bit for bit only on "
                    f"the same CPU, torch and Warp; record it here from a reference commit "
                    f"(python tests/test_golden.py --write)")
    return g


def _check(got: dict, want: dict, name: str) -> None:
    diffs = compare(got, want, name)
    assert not diffs, f"{len(diffs)} values moved, first: " + "; ".join(diffs[:8])


def test_tiny_fit_repeats_its_recorded_losses(golden, tiny_sequence, tmp_path):
    _check(tiny_record(tiny_sequence, tmp_path / "run"), golden["tiny"], "tiny")


def test_quadruped_fit_repeats_its_recorded_metrics_and_skeleton(golden, small_sequence, tmp_path):
    _check(quadruped_record(small_sequence, tmp_path / "run"), golden["quadruped"], "quadruped")


def _write() -> None:
    import tempfile

    sys.path.insert(0, str(Path(__file__).parent))
    from s3o_warp.synth import make_sequence

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        # the same clips as conftest.py's tiny_sequence and small_sequence
        make_sequence(tmp / "quad", frames=8, size=(96, 72), azim=(-15.0, 15.0), seed=0, progress=False)
        make_sequence(tmp / "quad16", frames=16, size=(128, 96), azim=(-15.0, 15.0), seed=0, progress=False)
        torch.manual_seed(0)
        tiny = tiny_record(tmp / "quad", tmp / "run-tiny")
        torch.manual_seed(0)
        quad = quadruped_record(tmp / "quad16", tmp / "run-quad")
    GOLDEN.parent.mkdir(exist_ok=True)
    out = {"environment": environment(), "tiny": tiny, "quadruped": quad}
    tmp_file = GOLDEN.with_name(GOLDEN.name + ".tmp")
    tmp_file.write_text(json.dumps(out, indent=1) + "\n")
    tmp_file.replace(GOLDEN)
    print(f"wrote {GOLDEN} ({len(tiny['steps'])} steps, {len(quad['skeleton'].get('bones', []))} bones)")


if __name__ == "__main__":
    if sys.argv[1:] != ["--write"]:
        sys.exit("usage: python tests/test_golden.py --write")
    _write()
