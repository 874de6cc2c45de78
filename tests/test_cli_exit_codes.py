"""One exit-code convention for every command (docs/CLI.md): 0 ok, 1 the work failed, 2 bad usage,
130 for an interrupted job (Ctrl-C or SIGTERM). The shared runner and the non-bus commands here;
the bus commands in tests/bus/test_bus_cli_exit_codes.py."""

from __future__ import annotations

import argparse
import importlib
import os
import signal
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import pytest

from stg_node.cli.runner import (
    EXIT_FAILED,
    EXIT_INTERRUPTED,
    EXIT_OK,
    EXIT_USAGE,
    CommandFailed,
    UsageError,
    add_log_level_option,
    run_main,
)

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]


def _main_of(script: str):
    module_name, _, attr = SCRIPTS[script].partition(":")
    return getattr(importlib.import_module(module_name), attr)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="stg-test")
    parser.add_argument("--n", type=int, default=1)
    add_log_level_option(parser)
    return parser


def _run(command, argv=(), **options) -> int:
    return run_main(_parser(), command, list(argv), **options)


# --- the runner ------------------------------------------------------------------------------------


def _raises(exc: BaseException):
    def command(args):
        raise exc

    return command


@pytest.mark.parametrize(
    "exc, code",
    [
        (FileNotFoundError("no such file: x.pkl"), EXIT_FAILED),
        (ValueError("bad data in x.npy"), EXIT_FAILED),
        (CommandFailed("the job failed"), EXIT_FAILED),
        (UsageError("--n must be >= 1"), EXIT_USAGE),
    ],
)
def test_expected_errors_map_to_their_code_with_one_line_and_no_traceback(exc, code, capsys):
    assert _run(_raises(exc)) == code
    err = capsys.readouterr().err
    assert f"stg-test: error: {exc}" in err and "Traceback" not in err
    assert ("usage: stg-test" in err) == (code == EXIT_USAGE)


def test_an_unexpected_error_is_a_failure_with_its_traceback(capsys):
    assert _run(_raises(KeyError("bug"))) == EXIT_FAILED
    err = capsys.readouterr().err
    assert "unexpected error" in err and "Traceback" in err and "KeyError" in err


def test_argparse_errors_are_usage_and_help_is_success(capsys):
    assert _run(lambda args: 0, ["--n", "many"]) == EXIT_USAGE
    assert "invalid int value" in capsys.readouterr().err
    assert _run(lambda args: 0, ["--help"]) == EXIT_OK
    assert "usage: stg-test" in capsys.readouterr().out


def test_return_values_and_sys_exit_pass_through():
    assert _run(lambda args: None) == EXIT_OK
    assert _run(lambda args: 3) == 3
    assert _run(_raises(SystemExit(4))) == 4


def test_a_bad_log_level_is_usage_from_the_option_or_the_environment(monkeypatch, capsys):
    assert _run(lambda args: 0, ["--log-level", "loud"]) == EXIT_USAGE
    monkeypatch.setenv("STG_LOG_LEVEL", "shouty")
    assert _run(lambda args: 0) == EXIT_USAGE
    assert "STG_LOG_LEVEL" in capsys.readouterr().err


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_stop_signal_interrupts_a_job_with_130(sig, capsys):
    def job(args):
        os.kill(os.getpid(), sig)
        time.sleep(5)  # the handler raises before this ends
        return 0

    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    assert _run(job) == EXIT_INTERRUPTED == 130  # (a job that slept on would have returned 0)
    assert "stg-test: interrupted" in capsys.readouterr().err
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before  # restored


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_commands_that_run_until_stopped_end_with_0_on_a_stop_signal(sig):
    def service(args):
        os.kill(os.getpid(), sig)
        time.sleep(5)
        return 0

    assert _run(service, stop_is_success=True) == EXIT_OK


def test_sigint_works_even_when_inherited_ignored():
    """A process started in the background inherits SIGINT ignored; the runner handles it anyway."""
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:

        def job(args):
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(5)
            return 0

        assert _run(job) == EXIT_INTERRUPTED
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN  # put back as it was
    finally:
        signal.signal(signal.SIGINT, previous)


# --- every console script ------------------------------------------------------------------------------


@pytest.mark.parametrize("script", sorted(SCRIPTS))
def test_every_command_returns_2_for_bad_usage_and_0_for_help(script, capsys):
    """Holds for future commands too: each must go through run_main (no SystemExit escapes)."""
    main = _main_of(script)
    assert main(["--no-such-option"]) == EXIT_USAGE
    assert "usage:" in capsys.readouterr().err
    assert main(["--help"]) == EXIT_OK
    assert main(["--log-level", "loud", "--help"]) == EXIT_OK  # --help wins, as argparse has it


# --- stg-synth -------------------------------------------------------------------------------------------


def test_stg_synth_codes(tmp_path, monkeypatch, capsys):
    main = _main_of("stg-synth")
    tiny = ["--frames", "1", "--size", "16", "--views", "0", "--no-progress"]
    assert main(["--out", str(tmp_path / "a"), "--frames", "0", "--no-progress"]) == EXIT_USAGE
    assert main(["--out", str(tmp_path / "a"), "--threads", "lots", *tiny]) == EXIT_USAGE
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "mine.txt").write_text("x")
    assert main(["--out", str(tmp_path / "full"), *tiny]) == EXIT_USAGE  # would overwrite: usage
    assert "--overwrite" in capsys.readouterr().err
    assert main(["--out", str(tmp_path / "b"), "--body", str(tmp_path / "missing.pkl"), *tiny]) == EXIT_FAILED
    err = capsys.readouterr().err
    assert "stg-synth: error: SMPL model not found" in err and "Traceback" not in err

    generate_module = importlib.import_module("stg_node.data.synth.generate")  # the module, not the function

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(generate_module, "generate", interrupted)
    assert main(["--out", str(tmp_path / "c"), *tiny]) == EXIT_INTERRUPTED


def test_stg_synth_process_exits_130_on_ctrl_c_without_a_traceback(tmp_path):
    out = tmp_path / "synth"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "STG_THREADS": "1"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "stg_node.cli.synth", "--out", str(out), "--frames", "500", "--no-progress"],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    try:
        deadline = time.monotonic() + 60
        while not (out / "annots.npy").exists() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.1)  # annots.npy: the job is under way
        assert proc.poll() is None, proc.communicate()
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == EXIT_INTERRUPTED, err
    assert b"stg-synth: interrupted" in err and b"Traceback" not in err


# --- stg-keys --------------------------------------------------------------------------------------------


def test_stg_keys_codes(tmp_path, capsys):
    main = _main_of("stg-keys")
    keys = str(tmp_path / "keys")
    assert main(["add", keys, "robot"]) == EXIT_FAILED  # no key directory yet
    assert "broker public key not found" in capsys.readouterr().err
    assert main(["init", keys]) == EXIT_OK
    assert main(["init", keys]) == EXIT_FAILED  # exists; --force replaces
    assert main(["add", keys, "robot"]) == EXIT_OK
    assert main(["add", keys, "robot"]) == EXIT_FAILED  # already has keys
    assert main(["add", keys, "../escape"]) == EXIT_USAGE  # not a key name
    assert main(["revoke", keys, "nobody"]) == EXIT_FAILED
    assert main(["revoke", keys, "robot"]) == EXIT_OK
    assert main(["list"]) == EXIT_USAGE  # DIR missing
    assert main([]) == EXIT_USAGE  # no subcommand
    assert not (tmp_path / "escape.key").exists()
