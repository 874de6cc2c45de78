"""Shared pytest wiring: the `gpu` marker skips cleanly where CUDA (or gsplat) is missing; slow
tests get a longer per-test timeout than the default suite's."""

from __future__ import annotations

import pytest


def _cuda_reason() -> str | None:
    try:
        import torch
    except ImportError:
        return "torch is not installed"
    if not torch.cuda.is_available():
        return "no CUDA device"
    return None


SLOW_TEST_TIMEOUT_S = 3600  # a slow test trains at full size: pyproject's per-test bound is for the rest


def pytest_collection_modifyitems(config, items):
    for item in items:
        if item.get_closest_marker("slow") and not item.get_closest_marker("timeout"):
            item.add_marker(pytest.mark.timeout(SLOW_TEST_TIMEOUT_S))
    gpu_items = [item for item in items if item.get_closest_marker("gpu")]
    if not gpu_items:
        return
    reason = _cuda_reason()
    if reason is None:
        return
    skip = pytest.mark.skip(reason=f"gpu test: {reason}")
    for item in gpu_items:
        item.add_marker(skip)


@pytest.fixture(scope="session", autouse=True)
def _project_thread_default():
    """Run every test with the thread count the project applies by default (STG_THREADS, else 1;
    docs/BENCHMARKS.md#thread-count): on a busy 2-core machine two torch threads make the torch
    reference many times slower. Tests that need another count set and restore it themselves."""
    from stg_node.threads import configure_threads

    configure_threads()


@pytest.fixture
def cpu_kernels():
    """The C++ CPU kernels, built (or found cached); skips where this machine cannot build them."""
    from stg_node.splat import build

    try:
        return build.load_kernels()
    except build.ExtensionUnavailable as exc:  # pragma: no cover - machines without a compiler
        pytest.skip(f"CPU kernels unavailable: {exc}")
