"""stg-launch at run time: order and readiness, respawn with backoff, required nodes, escalation,
node-prefixed output, exit codes, and no orphans after Ctrl-C."""

from __future__ import annotations

import io
import os
import re
import signal
import sys
import threading
from pathlib import Path

from nodehelpers import LineReader, describe_pids, ignore_sigint, launch_file, pid_alive, spawn, wait_until

from stg_node.launch import LaunchFileError, read_launch
from stg_node.launch.process import OutputSink
from stg_node.launch.supervisor import Launcher

PY = sys.executable
ECHO = "tests.nodes.sample_nodes:Echo"


def launch(tmp_path: Path, body: str, **overrides) -> tuple[int, str, Launcher]:
    """Run a launch file in this process; (exit code, node output, launcher)."""
    path = launch_file(tmp_path, body)
    out = io.StringIO()
    launcher = Launcher(read_launch(path, overrides), sink=OutputSink(out, color=False))
    code = launcher.run()
    return code, out.getvalue(), launcher


def test_a_required_node_ends_the_launch_and_output_is_prefixed(tmp_path):
    code, out, launcher = launch(
        tmp_path,
        f"""
        nodes:
          - {{name: quick, cmd: [{PY}, -c, "print('hello'); print('world')"], required: true, after: [slow]}}
          - {{name: slow, cmd: [sleep, "60"], ready: "delay:0.3"}}
        """,
    )
    assert code == 0
    assert "[quick] hello\n[quick] world\n" in out
    quick, slow = launcher.states
    assert slow.proc.runs[0].returncode == -signal.SIGINT  # stopped by the launch, a clean end
    assert quick.proc.runs[0].started - slow.proc.runs[0].started >= 0.3  # waited for readiness


def test_readiness_by_heartbeat_orders_the_start(tmp_path):
    code, out, launcher = launch(
        tmp_path,
        f"""
        nodes:
          - {{name: second, cmd: [echo, go], after: [first], required: true}}
          - {{name: first, kind: {ECHO}, params: {{setup_s: 1.0}}}}
        """,
    )
    assert code == 0, out
    second, first = launcher.states
    # the heartbeat only comes once setup (1 s) is over
    assert second.proc.runs[0].started - first.proc.runs[0].started > 1.0
    assert "[second] go" in out


def test_respawn_backs_off_and_a_node_out_of_respawns_fails_the_launch(tmp_path, caplog):
    code, out, launcher = launch(
        tmp_path,
        f"""
        nodes:
          - name: crashy
            cmd: [{PY}, -c, "import sys; print('run'); sys.exit(3)"]
            respawn: true
            respawn_delay: 0.2
            max_respawns: 3
        """,
    )
    assert code == 1
    runs = launcher.states[0].proc.runs
    assert [r.returncode for r in runs] == [3, 3, 3, 3]
    delays = [float(d) for d in re.findall(r"respawning in ([\d.]+) s", caplog.text)]
    assert delays == [0.2, 0.4, 0.8], caplog.text  # doubling delays ...
    gaps = [b.started - a.ended for a, b in zip(runs, runs[1:], strict=False)]
    for gap, want in zip(gaps, delays, strict=True):  # ... each waited out
        assert gap >= want - 0.02, gaps
    assert "no respawns left" in " ".join(launcher.states[0].problems)


def test_a_node_that_fails_before_others_can_start_ends_the_launch(tmp_path):
    code, out, launcher = launch(
        tmp_path,
        """
        nodes:
          - {name: setup, cmd: ["false"], ready: exit}
          - {name: main, cmd: [sleep, "60"], after: [setup]}
        """,
    )
    assert code == 1
    assert launcher.states[1].proc is None  # never started
    assert "setup failed before it was ready" in (launcher._ending or "")


def test_a_one_shot_step_gates_the_next_and_everything_ending_ends_the_launch(tmp_path):
    marker = tmp_path / "made"
    code, out, launcher = launch(
        tmp_path,
        f"""
        nodes:
          - {{name: make, cmd: [touch, {marker}], ready: exit}}
          - {{name: use, cmd: [ls, {marker}], after: [make]}}
        """,
    )
    assert code == 0 and f"[use] {marker}" in out


def test_escalation_sigint_then_sigterm_then_sigkill(tmp_path):
    stubborn = (
        "import signal, time; signal.signal(signal.SIGINT, signal.SIG_IGN); "
        "signal.signal(signal.SIGTERM, signal.SIG_IGN); print('up', flush=True); time.sleep(60)"
    )
    polite = (
        "import time\ntry:\n    print('up', flush=True)\n    time.sleep(60)\n"
        "except KeyboardInterrupt:\n    print('bye', flush=True)"
    )
    path = launch_file(
        tmp_path,
        f"""
            nodes:
              - {{name: stubborn, cmd: [{PY}, -c, "{stubborn}"], sigint_timeout: 0.3, sigterm_timeout: 0.3}}
              - name: polite
                cmd: [{PY}, -c, {polite!r}]
        """,
    )
    out = io.StringIO()
    launcher = Launcher(read_launch(path), sink=OutputSink(out, color=False))

    def stop_once_up():  # a stop asked for while both run (each has said so)
        if wait_until(lambda: "[stubborn] up" in out.getvalue() and "[polite] up" in out.getvalue(), 60):
            launcher.request_stop()

    threading.Thread(target=stop_once_up, daemon=True).start()
    code = launcher.run()
    assert code == 1  # a node that had to be killed is a failure
    stubborn_state, polite_state = launcher.states
    assert stubborn_state.proc.runs[0].returncode == -signal.SIGKILL
    assert "had to be killed" in " ".join(stubborn_state.problems)
    assert polite_state.proc.runs[0].returncode == 0 and "[polite] bye" in out.getvalue()


def test_sigint_on_the_launch_leaves_no_process_behind(tmp_path):
    """stg-launch in the background (SIGINT inherited ignored), with nodes that start children
    of their own; Ctrl-C ends it with exit 0, and no pid it started survives."""
    path = launch_file(
        tmp_path,
        f"""
            nodes:
              - {{name: node, kind: {ECHO}, params: {{child: true}}}}
              - {{name: shell, cmd: [sh, -c, "sleep 300 & echo grandchild $!; wait"]}}
        """,
    )
    proc = spawn(["-m", "stg_node.cli.launch", str(path), "--no-color"], preexec_fn=ignore_sigint)
    out = LineReader(proc.stdout)

    def ready(text: str) -> bool:
        return text.count("grandchild") == 2 and "node is ready" in text

    assert out.wait_for(ready), out.text()
    pids = [int(p) for p in re.findall(r"(?:pid |grandchild )(\d+)", out.text())]
    assert len(pids) >= 4  # two nodes, two grandchildren
    proc.send_signal(signal.SIGINT)
    text = out.rest(proc, timeout=30)
    assert proc.returncode == 0, text
    assert wait_until(lambda: not any(pid_alive(p) for p in pids), timeout=30), describe_pids(pids)


def test_a_launcher_killed_outright_takes_its_nodes_with_it(tmp_path):
    """SIGKILL leaves the launcher no chance to clean up: its children, and what they started
    themselves (which no parent-death signal reaches), are stopped by the launch guard."""
    path = launch_file(
        tmp_path,
        f"""
            nodes:
              - {{name: node, kind: {ECHO}, params: {{child: true}}}}
              - {{name: sleeper, cmd: [sleep, '300']}}
              - {{name: shell, cmd: [sh, -c, "sleep 300 & echo grandchild $!; wait"]}}
        """,
    )
    proc = spawn(["-m", "stg_node.cli.launch", str(path), "--no-color"])
    out = LineReader(proc.stdout)
    assert out.wait_for(lambda text: text.count("grandchild") == 2 and "node is ready" in text), out.text()
    pids = [int(p) for p in re.findall(r"(?:started \w+: pid |grandchild )(\d+)", out.text())]
    assert len(pids) == 5, out.text()  # three children, two grandchildren
    proc.kill()  # SIGKILL: no chance to clean up
    out.rest(proc)
    assert wait_until(lambda: not any(pid_alive(p) for p in pids), timeout=60), describe_pids(pids)


def test_a_standby_copy_takes_over_when_the_node_dies(tmp_path):
    """standby: a second copy waits, prepared; when the node is killed the launcher hands over to
    it (that very process becomes the node, as respawn 1), and a fresh copy is prepared again."""
    path = launch_file(
        tmp_path,
        f"nodes:\n  - {{name: node, kind: {ECHO}, respawn: true, respawn_delay: 0.1, standby: true}}\n",
    )
    proc = spawn(["-m", "stg_node.cli.launch", str(path), "--no-color"], preexec_fn=ignore_sigint)
    out = LineReader(proc.stdout)

    def seen(pattern: str) -> list[str]:
        return re.findall(pattern, out.text())

    def until(pattern: str, count: int = 1) -> bool:
        return out.wait_for(lambda text: len(re.findall(pattern, text)) >= count, timeout=120)

    try:
        assert until(r"\[node\*\] .*standing by \(pid (\d+)\)"), out.text()
        first = int(seen(r"started node: pid (\d+)")[0])
        spare = int(seen(r"standing by \(pid (\d+)\)")[0])
        assert spare != first
        os.kill(first, signal.SIGKILL)
        assert until(r"handed over to its standby copy node \(respawn 1\): pid (\d+)"), out.text()
        assert int(seen(r"handed over to its standby copy node \(respawn 1\): pid (\d+)")[0]) == spare
        assert until(r"\[node\] .*taking over \(respawn 1\)"), out.text()  # its own words, the node's prefix
        assert until(r"node is ready", 2), out.text()
        assert until(r"standing by \(pid (\d+)\)", 2), out.text()  # and a new copy waits
        pids = [first, spare, *map(int, seen(r"standing by \(pid (\d+)\)"))]
    finally:
        proc.send_signal(signal.SIGINT)
        text = out.rest(proc)
    assert proc.returncode == 0, text
    assert wait_until(lambda: not any(pid_alive(p) for p in pids), timeout=30), describe_pids(pids)


def test_a_copys_first_words_after_the_hand_over_carry_the_nodes_own_prefix():
    """The copy answers "go" at once; its prefix must already be the node's when the word is sent
    (renamed only afterwards, its "taking over" line raced the rename and sometimes came out as
    [node*], which hung a test that read the launcher's output for [node])."""
    from stg_node.launch.process import ChildProcess

    out = io.StringIO()
    script = "import sys; sys.stdin.readline(); print('took over', flush=True); sys.stdin.read()"
    spare = ChildProcess(
        "node*", [sys.executable, "-c", script], dict(os.environ), None, OutputSink(out), standby=True
    )
    spare.start()
    try:
        assert spare.hand_over(1, "node")
        assert wait_until(lambda: "took over" in out.getvalue(), timeout=60), out.getvalue()
        assert out.getvalue() == "[node] took over\n"
    finally:
        spare.dismiss()
        spare.popen.wait(timeout=60)


def test_standby_is_for_kind_nodes_that_respawn(tmp_path):
    for body, why in (
        ("nodes:\n  - {name: n, cmd: [sleep, '1'], respawn: true, standby: true}\n", "cmd"),
        (f"nodes:\n  - {{name: n, kind: {ECHO}, standby: true}}\n", "no respawn"),
    ):
        try:
            read_launch(launch_file(tmp_path, body))
        except LaunchFileError as exc:
            assert "standby is for kind nodes with respawn: true" in str(exc), why
        else:
            raise AssertionError(f"standby accepted for a node with {why}")


def _thread_nices(pid: int) -> dict[int, int]:
    """The niceness of every thread of ``pid``, as the kernel reports it (/proc/PID/task/TID/stat)."""
    nices = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        fields = (task / "stat").read_text().rsplit(")", 1)[1].split()
        nices[int(task.name)] = int(fields[16])  # field 19 of stat; fields[0] is field 3 (state)
    return nices


def test_nice_reaches_the_process_and_the_threads_it_starts(tmp_path):
    """A node's ``nice:`` is the niceness the kernel reports for its process and for threads the
    program starts later (a kind node and a program); a node without it runs as the launcher."""
    base = os.nice(0)
    expected = min(base + 7, 19)
    program = (
        "import threading, time; threading.Thread(target=time.sleep, args=(300,)).start(); "
        "print('up', flush=True); time.sleep(300)"
    )
    path = launch_file(
        tmp_path,
        f"""
        nodes:
          - {{name: background, cmd: [{PY}, -c, "{program}"], nice: 7}}
          - {{name: kindnode, kind: {ECHO}, nice: 7}}
          - {{name: plain, cmd: [sleep, "300"]}}
        """,
    )
    out = io.StringIO()
    launcher = Launcher(read_launch(path), sink=OutputSink(out, color=False))
    runner = threading.Thread(target=launcher.run, daemon=True)
    runner.start()
    try:
        states = {s.name: s for s in launcher.states}

        def started() -> bool:
            return "[background] up" in out.getvalue() and all(s.ready for s in states.values())

        assert wait_until(started, timeout=60), out.getvalue()
        background = states["background"].proc.popen.pid
        assert wait_until(lambda: len(_thread_nices(background)) >= 2, timeout=30)
        assert set(_thread_nices(background).values()) == {expected}
        kind_pid = states["kindnode"].proc.popen.pid
        assert os.getpriority(os.PRIO_PROCESS, kind_pid) == expected
        assert set(_thread_nices(kind_pid).values()) == {expected}  # the bus's threads too
        assert os.getpriority(os.PRIO_PROCESS, states["plain"].proc.popen.pid) == base
    finally:
        launcher.request_stop("test done")
        runner.join(timeout=60)
    assert not runner.is_alive()


def test_nice_outside_0_to_19_is_refused_with_the_line(tmp_path):
    for value in (-5, 20):
        try:
            read_launch(launch_file(tmp_path, f"nodes:\n  - {{name: n, cmd: [sleep, '1'], nice: {value}}}\n"))
        except LaunchFileError as exc:
            assert re.search(r"\.yaml:\d+: node 'n': nice: must be [<>]= (0|19)", str(exc)), str(exc)
        else:
            raise AssertionError(f"nice: {value} accepted")


def test_the_live_launch_files_run_the_trainer_below_the_live_path():
    root = Path(__file__).resolve().parents[2]
    rig = {"calibration": "rig.json", "videos": "a.mp4"}
    for name, extra in (("live_v4l2", {}), ("live_oak", {}), ("rig_v4l2", rig)):
        path = root / "launch" / f"{name}.yaml"
        nodes = {n.name: n for n in read_launch(path, extra).nodes}
        assert nodes["trainer"].nice == 10, name
        assert all(n.nice == 0 for k, n in nodes.items() if k != "trainer"), name
        nodes = {n.name: n for n in read_launch(path, {**extra, "trainer_nice": "0"}).nodes}
        assert nodes["trainer"].nice == 0, name
