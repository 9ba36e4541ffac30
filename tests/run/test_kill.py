"""A fit killed with SIGKILL while it writes a checkpoint resumes and ends where an uninterrupted fit ends.

The fit runs in a child process that kills itself (SIGKILL: no handler, no clean-up) at a seeded checkpoint write, at
one of three points: half way through writing the temporary file, after writing it and before the rename, after the
rename and before the older checkpoints are deleted. The parent then resumes the run and compares its final model with
an uninterrupted fit's, bit for bit.
"""

from __future__ import annotations

import random
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from conftest import final_params, smoke_config

from s3o_warp.fit import fit

OVERRIDES = {"coarse.steps": 4, "motion.warmup_steps": 4, "motion.steps": 6, "output.checkpoint_every": 2}
"""A tiny fit with a checkpoint every 2 steps: 7 checkpoint writes (phase starts, every 2 steps, the end)."""

CHILD = r"""
import os, signal, sys
from pathlib import Path
import torch
sys.path.insert(0, sys.argv[1])
from conftest import smoke_config
import s3o_warp.run.checkpoint as C
from s3o_warp.fit import fit

seq, run, k, point = sys.argv[2], sys.argv[3], int(sys.argv[4]), sys.argv[5]
overrides = eval(sys.argv[6])
calls = {"n": 0}
real_save, real_torch_save = C.torch_save, torch.save

def die():
    os.kill(os.getpid(), signal.SIGKILL)

def torch_save(obj, path):
    calls["n"] += 1
    if calls["n"] != k:
        return real_save(obj, path)
    if point == "after_rename":
        real_save(obj, path)
        die()
    def partial(o, f):  # the temporary file, cut short or whole, never renamed
        real_torch_save(o, f)
        if point == "mid_write":
            size = os.path.getsize(f)
            with open(f, "r+b") as fh:
                fh.truncate(size // 2)
        die()
    torch.save = partial
    real_save(obj, path)

C.torch_save = torch_save
fit(seq, run, smoke_config(**overrides), torch.device("cpu"))
"""


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_fit_killed_while_writing_a_checkpoint_resumes_to_the_same_end(tiny_sequence, tmp_path, seed):
    rng = random.Random(seed)
    k = rng.randint(2, 6)  # which checkpoint write (of 7: every 2 steps, each phase start, the end)
    point = rng.choice(["mid_write", "before_rename", "after_rename"])
    ref, run = tmp_path / "ref", tmp_path / "run"
    fit(tiny_sequence, ref, smoke_config(**OVERRIDES), torch.device("cpu"))
    tests = str(Path(__file__).resolve().parents[1])
    child = subprocess.run([sys.executable, "-c", CHILD, tests, str(tiny_sequence), str(run), str(k), point,
                            repr(OVERRIDES)], capture_output=True, text=True, timeout=600)
    assert child.returncode == -signal.SIGKILL, (k, point, child.returncode, child.stderr[-2000:])
    fit(tiny_sequence, run, smoke_config(**OVERRIDES), torch.device("cpu"), resume=True)
    a, b = final_params(ref), final_params(run)
    assert a.keys() == b.keys()
    for name in a:
        torch.testing.assert_close(b[name], a[name], rtol=0, atol=0, msg=f"{k}, {point}: the resumed fit differs in {name}")
