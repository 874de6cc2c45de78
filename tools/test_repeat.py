#!/usr/bin/env python3
"""Run the default test suite N times and count, per test, how often it failed: a suite that is
green once may still fail by chance; this shows whether it does.

    python tools/test_repeat.py 5 --busy-runs 2 --background-runs 1   # make test-repeat 5 BUSY=2 BACKGROUND=1
    python tools/test_repeat.py 3 -- tests/nodes -x                   # pytest arguments after --

Each run is ``python -m pytest`` (the default suite: slow tests excluded) with a JUnit XML
report, read afterwards for the tests that failed or errored. ``--busy-runs K``: the first K runs
have a busy loop beside them (a process spinning on a core, as another job would on a small
machine). ``--background-runs K``: the last K runs are started as a non-interactive shell starts
a background job (``bash -c 'pytest ... & wait'``: SIGINT ignored, no terminal input), the way a
CI script or ``make test &`` runs it. The report: each run's outcome and time, then every test
that failed at least once with its count and the first line of its first failure. Exit code 0
when no run failed, 1 otherwise (2: bad usage).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import signal
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


@dataclass
class Run:
    index: int
    busy: bool
    background: bool
    exit_code: int
    seconds: float
    tests: int = 0
    failed: list[str] = field(default_factory=list)  # test ids that failed or errored
    messages: dict[str, str] = field(default_factory=dict)  # test id -> first line of the failure


def read_junit(path: Path) -> tuple[int, list[str], dict[str, str]]:
    """(tests run, failed test ids, first failure line per id) from a pytest JUnit XML report."""
    if not path.is_file():
        return 0, [], {}
    root = ET.parse(path).getroot()
    tests, failed, messages = 0, [], {}
    for case in root.iter("testcase"):
        tests += 1
        problem = case.find("failure")
        if problem is None:
            problem = case.find("error")
        if problem is None:
            continue
        test_id = f"{case.get('classname', '')}::{case.get('name', '')}"
        failed.append(test_id)
        text = (problem.get("message") or problem.text or "").strip().splitlines()
        messages[test_id] = text[0][:200] if text else ""
    return tests, failed, messages


def busy_loop() -> subprocess.Popen:
    """A process that keeps one core busy until killed."""
    return subprocess.Popen([sys.executable, "-c", "while True: pass"], stdin=subprocess.DEVNULL)


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def run_suite(
    index: int, pytest_args: list[str], *, busy: bool, background: bool, work: Path, python: str
) -> Run:
    report = work / f"run{index}.xml"
    log = work / f"run{index}.log"
    command = [python, "-m", "pytest", "-q", "-p", "no:cacheprovider", f"--junitxml={report}", *pytest_args]
    spinner = busy_loop() if busy else None
    start = time.monotonic()
    try:
        with open(log, "w") as out:
            if background:
                # exactly what a non-interactive shell does with `cmd &`: SIGINT and SIGQUIT ignored,
                # stdin from /dev/null
                # (the command itself must be the job: `cd X && cmd &` forks a subshell that does
                # not ignore SIGINT)
                shell = f"{shlex.join(command)} & wait $!"
                code = subprocess.call(["bash", "-c", shell], cwd=ROOT, stdout=out, stderr=subprocess.STDOUT)
            else:  # as from a terminal: SIGINT at its default, however this tool itself was started
                code = subprocess.call(
                    command, cwd=ROOT, stdout=out, stderr=subprocess.STDOUT, preexec_fn=_default_sigint
                )
    finally:
        if spinner is not None:
            spinner.kill()
            spinner.wait()
    seconds = time.monotonic() - start
    tests, failed, messages = read_junit(report)
    return Run(index, busy, background, code, seconds, tests, failed, messages)


def summary(runs: list[Run]) -> tuple[list[str], Counter]:
    counts: Counter = Counter()
    first: dict[str, str] = {}
    lines = []
    for r in runs:
        how = (
            ", ".join(w for w, on in (("busy loop", r.busy), ("background job", r.background)) if on)
            or "plain"
        )
        lines.append(
            f"run {r.index}: exit {r.exit_code}, {r.tests} tests, {len(r.failed)} failed, "
            f"{r.seconds / 60:.1f} min ({how})"
        )
        counts.update(r.failed)
        for test_id in r.failed:
            first.setdefault(test_id, r.messages.get(test_id, ""))
    if counts:
        lines.append(f"failures per test (of {len(runs)} runs):")
        for test_id, n in counts.most_common():
            lines.append(f"  {n}/{len(runs)}  {test_id}: {first[test_id]}")
    else:
        lines.append(f"no test failed in {len(runs)} run(s)")
    return lines, counts


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    pytest_args: list[str] = []
    if "--" in argv:
        cut = argv.index("--")
        argv, pytest_args = argv[:cut], argv[cut + 1 :]
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("runs", type=int, help="how many times to run the suite")
    parser.add_argument(
        "--busy-runs", type=int, default=0, metavar="K", help="the first K runs beside a busy loop"
    )
    parser.add_argument(
        "--background-runs", type=int, default=0, metavar="K", help="the last K runs as a background job"
    )
    parser.add_argument(
        "--work", type=Path, help="folder for the runs' logs and reports (default: a temp folder)"
    )
    parser.add_argument("--json", type=Path, help="also write the results here")
    parser.add_argument("--python", default=sys.executable, help="the interpreter (default: this one)")
    args = parser.parse_args(argv)
    if args.runs < 1 or not 0 <= args.busy_runs <= args.runs or not 0 <= args.background_runs <= args.runs:
        parser.error("runs must be >= 1; --busy-runs and --background-runs between 0 and runs")
    work = args.work or Path(tempfile.mkdtemp(prefix="stg-test-repeat-"))
    work.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("STG_THREADS", "1")
    print(f"test-repeat: {args.runs} run(s) of the suite; logs and reports in {work}", flush=True)
    runs = []
    for i in range(1, args.runs + 1):
        busy = i <= args.busy_runs
        background = i > args.runs - args.background_runs
        run = run_suite(i, pytest_args, busy=busy, background=background, work=work, python=args.python)
        runs.append(run)
        print(summary([run])[0][0], flush=True)
    lines, counts = summary(runs)
    print("\n".join(lines[len(runs) :]))
    if args.json:
        args.json.write_text(
            json.dumps({"runs": [asdict(r) for r in runs], "failures": dict(counts)}, indent=2) + "\n"
        )
    return 0 if all(r.exit_code == 0 and not r.failed for r in runs) else 1


if __name__ == "__main__":
    sys.exit(main())
