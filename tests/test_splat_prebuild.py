"""``stg-splat-prebuild``: builds (or finds cached) kernels, says where, and exits 0 / 1 / 2."""

from __future__ import annotations

import pytest
import torch

from stg_node.cli.splat_prebuild import main
from stg_node.splat import prebuild as prebuild_mod
from stg_node.splat.api import cpu_backend_status
from stg_node.splat.build import load_kernels


@pytest.mark.skipif(cpu_backend_status() is not None, reason="C++ splat kernels unavailable")
def test_cpu_prebuild_reports_the_cached_library(capsys):
    assert main(["--backend", "cpu"]) == 0
    assert f"cpu: ok: C++ kernels ready: {load_kernels().library}" in capsys.readouterr().out


def test_cuda_prebuild_without_cuda_torch_fails_only_when_asked_for(monkeypatch, capsys):
    monkeypatch.setattr(torch.version, "cuda", None)
    monkeypatch.setattr(
        prebuild_mod, "prebuild_cpu", lambda: prebuild_mod.KernelBuild("cpu", True, False, "ok")
    )
    assert main(["--backend", "cuda"]) == 1
    assert "cuda: FAILED: torch is built without CUDA" in capsys.readouterr().err
    assert main([]) == 0  # all: cuda is skipped, not failed
    assert "cuda: skipped" in capsys.readouterr().out


def test_a_failed_build_is_exit_status_1_and_bad_usage_2(monkeypatch, capsys):
    def broken():
        return prebuild_mod.KernelBuild("cpu", ok=False, skipped=False, detail="no C++ compiler found (test)")

    monkeypatch.setattr(prebuild_mod, "prebuild_cpu", broken)
    assert main(["--backend", "cpu"]) == 1
    assert "cpu: FAILED: no C++ compiler found (test)" in capsys.readouterr().err
    assert main(["--backend", "gpu"]) == 2  # run_main turns argparse's exit into the status
