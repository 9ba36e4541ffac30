"""Warp's initialisation (kernels/_warp.py): its missing-driver line is held back, everything else still shows."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
import torch

from s3o_warp.kernels import _warp


def test_holding_back_returns_the_marked_line_and_writes_the_others_to_stderr(capfd):
    def native_init():
        os.write(2, b"Warp CUDA warning: Could not find or load the NVIDIA CUDA driver. GPU execution will not be "
                    b"available.\nsome other native line\n")

    held = _warp.holding_back(native_init, _warp.NO_DRIVER)
    assert held == ("Warp CUDA warning: Could not find or load the NVIDIA CUDA driver. GPU execution will not be "
                    "available.")
    err = capfd.readouterr().err
    assert "some other native line" in err and _warp.NO_DRIVER not in err


@pytest.mark.parametrize("device", ["None", "'cpu'"])
def test_no_driver_warning_unless_cuda_is_asked_for(device):
    code = f"from s3o_warp.fit import resolve_device; print(resolve_device({device}))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() in ("cpu", "cuda:0") and _warp.NO_DRIVER not in out.stderr, out.stderr


def test_asking_for_cuda_without_it_names_the_missing_driver():
    if torch.cuda.is_available():
        pytest.skip("CUDA present")
    out = subprocess.run([sys.executable, "-m", "s3o_warp.cli", "--device", "cuda"], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("s3o-fit: error: --device cuda: no CUDA device"), out.stderr
    _warp.init()
    if _warp.driver_warning:  # this machine has no driver at all (not only no GPU): the line says so
        assert _warp.NO_DRIVER in lines[0]
