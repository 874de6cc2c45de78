import os
import subprocess
import sys

import pytest

from stg_node.threads import DEFAULT_THREADS, parse_threads, resolve_threads


def _threads_in_fresh_process(env_value: str | None, explicit: str = "None") -> tuple[int, int]:
    """torch's and OpenCV's thread counts after configure_threads, in a clean interpreter."""
    env = dict(os.environ)
    env.pop("STG_THREADS", None)
    if env_value is not None:
        env["STG_THREADS"] = env_value
    code = (
        "import torch, cv2\n"
        "from stg_node.threads import configure_threads\n"
        f"configure_threads({explicit})\n"
        "print(torch.get_num_threads(), cv2.getNumThreads())\n"
    )
    out = subprocess.run([sys.executable, "-c", code], env=env, check=True, capture_output=True, text=True)
    torch_n, cv_n = out.stdout.split()
    return int(torch_n), int(cv_n)


def test_default_applies_to_torch_and_opencv():
    assert _threads_in_fresh_process(None) == (DEFAULT_THREADS, DEFAULT_THREADS)


def test_environment_sets_count():
    assert _threads_in_fresh_process("2") == (2, 2)


def test_explicit_count_beats_environment():
    assert _threads_in_fresh_process("2", explicit="1") == (1, 1)


def test_zero_and_all_mean_every_core():
    cores = os.cpu_count() or 1
    assert parse_threads("0") == cores
    assert parse_threads("all") == cores


def test_resolve_prefers_explicit(monkeypatch):
    monkeypatch.setenv("STG_THREADS", "3")
    assert resolve_threads() == 3
    assert resolve_threads(1) == 1


@pytest.mark.parametrize("bad", ["-1", "two", "1.5"])
def test_bad_count_is_a_clear_error(bad):
    with pytest.raises(ValueError, match="STG_THREADS"):
        parse_threads(bad)
