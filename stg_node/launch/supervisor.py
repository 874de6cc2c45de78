"""The launcher: a broker, then the nodes in order of readiness, kept alive, stopped in escalation.

:class:`Launcher` runs a :class:`~stg_node.launch.spec.LaunchSpec`:

- starts the broker (in a thread of this process) unless the launch file says one runs already;
- starts each node when the nodes it comes ``after`` are ready; a node is ready at its first
  NodeStatus heartbeat (kind nodes, matched by name and pid), when started, when it exited 0
  (``ready: exit``, one-shot steps), when a file exists, or after a delay;
- restarts a failed node with ``respawn`` (delay doubling from ``respawn_delay`` up to
  ``respawn_max_delay``; back to the first delay after a run longer than that); with ``standby``
  it keeps a second copy of the node started and prepared (its imports done), waiting on a pipe,
  and a respawn hands over to it at once instead of starting a process from nothing;
- ends the launch when a ``required`` node ends, when a node fails that others wait for, or
  when nothing is left running;
- on SIGINT/SIGTERM (or the end) stops every node: SIGINT to its process group, SIGTERM after
  ``sigint_timeout``, SIGKILL after ``sigterm_timeout``; a second Ctrl-C skips to SIGTERM, a
  third to SIGKILL; finally every process group is killed so no grandchild survives;
- keeps a guard process (:mod:`.guard`) that stops every group if the launcher itself is killed.

The exit code: 0 when every node ended well, 1 when a node failed (exited non-zero and was not
respawned, never became ready, or had to be killed), 2 is the CLI's for bad usage or files.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import stg_node
from stg_node.bus import Broker, BrokerRunning, Subscriber
from stg_node.bus.messages import NodeStatus
from stg_node.launch.guard import Guard
from stg_node.launch.process import ChildProcess, OutputSink
from stg_node.launch.spec import LaunchSpec, NodeSpec
from stg_node.nodes.runtime import ENV_LAUNCH_FILE, ENV_PARENT_PID, ENV_RESPAWN, ENV_STANDBY

log = logging.getLogger("stg_node.launch")

LOOP_S = 0.05
PACKAGE_ROOT = str(Path(stg_node.__file__).resolve().parents[1])


@dataclass
class NodeState:
    """What the launcher knows about one node."""

    spec: NodeSpec
    proc: ChildProcess | None = None
    phase: str = "waiting"  # waiting, running, backoff, done, failed
    ready: bool = False
    respawns: int = 0
    failures_in_row: int = 0
    next_start: float = 0.0
    started_at: float = 0.0
    problems: list[str] = field(default_factory=list)
    spare: ChildProcess | None = None  # the standby copy (``standby: true``), prepared and waiting
    spare_due: float = float("inf")  # when to start the next standby copy

    @property
    def name(self) -> str:
        return self.spec.name


class Launcher:
    """Runs one launch; :meth:`run` returns the exit code (0 ok, 1 a node failed)."""

    def __init__(self, spec: LaunchSpec, *, sink: OutputSink | None = None, broker: bool | None = None):
        self.spec = spec
        self.sink = sink or OutputSink()
        self.start_broker = spec.bus.broker if broker is None else broker
        self.states = [NodeState(n) for n in spec.nodes]
        self._by_name = {s.name: s for s in self.states}
        self._signals = 0
        self._signal_lock = threading.RLock()  # taken in a signal handler: must be re-entrant
        self._ending: str | None = None
        self._failed = False
        self._broker: Broker | None = None
        self._status: Subscriber | None = None
        self._guard: Guard | None = None

    # -- signals ------------------------------------------------------------------------------------

    def _on_signal(self, signum, frame) -> None:
        with self._signal_lock:
            self._signals += 1
        if self._ending is None:
            self._ending = f"{signal.Signals(signum).name} received"

    def request_stop(self, reason: str = "stop requested") -> None:
        """End the launch from code (what SIGINT does)."""
        with self._signal_lock:
            self._signals += 1
        if self._ending is None:
            self._ending = reason

    # -- running ------------------------------------------------------------------------------------

    def run(self) -> int:
        previous = {}
        if threading.current_thread() is threading.main_thread():
            previous = {s: signal.signal(s, self._on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
        started = time.monotonic()
        try:
            self._guard = Guard()
            self._open_bus()
            self._loop()
        except BrokerRunning as exc:
            log.error("%s (set bus: {broker: false} in the launch file to use the running one)", exc)
            self._failed = True
        except Exception as exc:
            log.exception("launcher failed: %s", exc)
            self._failed = True
        finally:
            try:
                self._shutdown()
            finally:
                self._close_bus()
                if self._guard is not None:
                    self._guard.close()
                    self._guard = None
                for sig, handler in previous.items():
                    signal.signal(sig, handler)
        self._summary(time.monotonic() - started)
        return 1 if self._failed else 0

    def _open_bus(self) -> None:
        bus = self.spec.bus
        if self.start_broker:
            self._broker = Broker([bus.url, *bus.broker_urls], keys=bus.keys, lanes=bus.lanes).start()
        namespaces = sorted({s.spec.namespace for s in self.states if s.spec.entry.kind is not None})
        topics = [f"/{ns}/node/status" if ns else "/node/status" for ns in namespaces]
        if topics:
            self._status = Subscriber(bus.config(namespace=""), topics)

    def _close_bus(self) -> None:
        if self._status is not None:
            self._status.close()
        if self._broker is not None:
            self._broker.stop()

    def _loop(self) -> None:
        log.info(
            "launch %s: %d node(s) on %s%s",
            self.spec.path.name,
            len(self.states),
            self.spec.bus.url,
            f" (skipped: {', '.join(self.spec.skipped)})" if self.spec.skipped else "",
        )
        while self._ending is None:
            self._read_status()
            now = time.monotonic()
            for state in self.states:
                self._check_exit(state, now)
            for state in self.states:
                self._check_ready(state, now)
            for state in self.states:
                self._maybe_start(state, now)
            for state in self.states:
                self._keep_spare(state, now)
            if self._ending is None and all(s.phase in ("done", "failed") for s in self.states):
                self._ending = "every node has ended"
            time.sleep(LOOP_S)
        log.info("shutting down: %s", self._ending)

    def _read_status(self) -> None:
        if self._status is None:
            return
        while (msg := self._status.recv(timeout=0)) is not None:
            if not isinstance(msg, NodeStatus):
                continue
            state = self._by_name.get(msg.node)
            if state is None or state.proc is None or state.proc.pid != msg.pid:
                continue
            if state.spec.ready == "heartbeat" and not state.ready and msg.state in ("running", "degraded"):
                self._mark_ready(state)

    def _mark_ready(self, state: NodeState) -> None:
        state.ready = True
        log.info("%s is ready (%.1f s)", state.name, time.monotonic() - state.started_at)
        if state.spec.standby and state.spare is None:
            state.spare_due = min(state.spare_due, time.monotonic())  # prepared while the node runs

    # -- standby copies -------------------------------------------------------------------------------

    def _keep_spare(self, state: NodeState, now: float) -> None:
        """Start a node's standby copy when due; notice one that died (and start another later)."""
        if not state.spec.standby or self._ending is not None:
            return
        spare = state.spare
        if spare is not None and spare.poll() is not None:
            log.warning(
                "%s: its standby copy (pid %d) ended (exit %s)", state.name, spare.pid, spare.popen.returncode
            )
            state.spare = None
            state.spare_due = now + max(state.spec.respawn_delay, 5.0)
        if state.spare is None and now >= state.spare_due and state.phase == "running" and state.ready:
            spec = state.spec
            env = {**self._env(spec), ENV_STANDBY: "1"}
            spare = ChildProcess(
                f"{spec.name}*",
                spec.command(self.spec.bus),
                env,
                spec.cwd,
                self.sink,
                guard=self._guard,
                grace_s=spec.sigint_timeout + spec.sigterm_timeout,
                standby=True,
                nice=spec.nice,
            )
            try:
                pid = spare.start()
            except OSError as exc:
                log.warning("%s: cannot start a standby copy: %s", spec.name, exc)
                state.spare_due = now + 30.0
                return
            state.spare, state.spare_due = spare, float("inf")
            log.info("started %s's standby copy: pid %d", spec.name, pid)

    def _take_over(self, state: NodeState) -> int | None:
        """Hand the node over to its standby copy; its pid, or None if there is none to take it."""
        spare, state.spare = state.spare, None
        if spare is None or not spare.hand_over(state.respawns, state.proc.name):
            if spare is not None:
                spare.dismiss()
                spare.signal_group(signal.SIGKILL)
                spare.poll()
            return None
        state.spare_due = float("inf")  # the next copy once this one is ready
        return state.proc.adopt(spare)

    def _deps_ready(self, state: NodeState) -> bool:
        for dep in state.spec.after:
            other = self._by_name.get(dep)
            if other is not None and not other.ready:  # a skipped node counts as ready
                return False
        return True

    def _maybe_start(self, state: NodeState, now: float) -> None:
        if self._ending is not None:
            return
        if state.phase == "waiting" and self._deps_ready(state):
            self._start(state, now)
        elif state.phase == "backoff" and now >= state.next_start:
            self._start(state, now)

    def _env(self, spec: NodeSpec) -> dict[str, str]:
        env = {**os.environ, **spec.env}
        env["PYTHONUNBUFFERED"] = "1"
        env["PYTHONPATH"] = os.pathsep.join(p for p in (PACKAGE_ROOT, env.get("PYTHONPATH", "")) if p)
        env["STG_BUS"] = self.spec.bus.url
        env["STG_NAMESPACE"] = spec.namespace
        env[ENV_PARENT_PID] = str(os.getpid())
        env[ENV_LAUNCH_FILE] = str(Path(self.spec.path).resolve())
        if self.spec.bus.keys:
            env["STG_BUS_KEYS"] = self.spec.bus.keys
        return env

    def _start(self, state: NodeState, now: float) -> None:
        spec = state.spec
        argv = spec.command(self.spec.bus)
        if state.proc is None:
            state.proc = ChildProcess(
                spec.name,
                argv,
                self._env(spec),
                spec.cwd,
                self.sink,
                guard=self._guard,
                grace_s=spec.sigint_timeout + spec.sigterm_timeout,
                nice=spec.nice,
            )
        state.proc.env[ENV_RESPAWN] = str(state.respawns)
        pid = self._take_over(state) if state.respawns else None
        took_over = pid is not None
        if not took_over:
            try:
                pid = state.proc.start()
            except OSError as exc:
                self._fail(state, f"cannot start {argv[0]!r}: {exc}")
                return
        state.phase = "running"
        state.ready = spec.ready == "started"
        state.started_at = state.proc.runs[-1].started  # the process's own start: delays count from it
        again = f" (respawn {state.respawns})" if state.respawns else ""
        how = "handed over to its standby copy" if took_over else "started"
        log.info("%s %s%s: pid %d", how, spec.name, again, pid)

    def _check_ready(self, state: NodeState, now: float) -> None:
        if state.phase != "running" or state.ready:
            return
        how, _, value = state.spec.ready.partition(":")
        if how == "file" and Path(value).expanduser().exists():
            self._mark_ready(state)
        elif how == "delay" and now - state.started_at >= float(value):
            self._mark_ready(state)
        elif (
            how != "exit"
            and state.spec.ready_timeout > 0
            and now - state.started_at > state.spec.ready_timeout
        ):
            self._fail(state, f"not ready within {state.spec.ready_timeout:g} s ({state.spec.ready})")
            state.proc.signal_group(signal.SIGTERM)

    def _check_exit(self, state: NodeState, now: float) -> None:
        if state.phase != "running" or state.proc is None:
            return
        code = state.proc.poll()
        if code is None:
            return
        spec = state.spec
        ran = now - state.started_at
        if code == 0:
            state.phase = "done"
            if spec.ready == "exit":
                self._mark_ready(state)
            log.info("%s finished (exit 0 after %.1f s)", spec.name, ran)
            if spec.required:
                self._end(f"required node {spec.name} finished")
            return
        how = f"killed by {signal.Signals(-code).name}" if code < 0 else f"exit code {code}"
        can_respawn = spec.respawn and (spec.max_respawns < 0 or state.respawns < spec.max_respawns)
        if can_respawn:
            if ran > spec.respawn_max_delay:
                state.failures_in_row = 0
            state.failures_in_row += 1
            delay = min(spec.respawn_delay * 2 ** (state.failures_in_row - 1), spec.respawn_max_delay)
            state.respawns += 1
            state.phase = "backoff"
            state.ready = False
            state.next_start = now + delay
            log.warning("%s died (%s after %.1f s); respawning in %.1f s", spec.name, how, ran, delay)
            return
        self._fail(state, f"{how} after {ran:.1f} s" + (" (no respawns left)" if spec.respawn else ""))

    def _fail(self, state: NodeState, problem: str) -> None:
        spec = state.spec
        state.phase = "failed"
        state.problems.append(problem)
        self._failed = True
        log.error("%s failed: %s", spec.name, problem)
        if spec.required:
            self._end(f"required node {spec.name} failed")
        elif not state.ready:
            waiting = [s.name for s in self.states if spec.name in s.spec.after and s.phase == "waiting"]
            if waiting:
                self._end(f"{spec.name} failed before it was ready; {', '.join(waiting)} wait(s) on it")

    def _end(self, reason: str) -> None:
        if self._ending is None:
            self._ending = reason

    # -- shutdown -----------------------------------------------------------------------------------

    def _running(self) -> list[NodeState]:
        return [s for s in self.states if s.proc is not None and s.proc.running]

    def _shutdown(self) -> None:
        """SIGINT to every running node; each one that outlives its own sigint_timeout gets SIGTERM,
        then SIGKILL after its sigterm_timeout. Another Ctrl-C moves everyone one step on."""
        for state in self.states:  # standby copies first: nothing will take over any more
            if state.spare is not None:
                state.spare.dismiss()
                state.spare.signal_group(signal.SIGTERM)
        running = self._running()
        if running:
            log.info("stopping %s", ", ".join(s.name for s in running))
        now = time.monotonic()
        stage: dict[str, tuple[int, float]] = {}
        for state in reversed(running):
            state.proc.signal_group(signal.SIGINT)
            stage[state.name] = (signal.SIGINT, now + state.spec.sigint_timeout)
        seen = self._signals
        while running := self._running():
            now = time.monotonic()
            hurry = self._signals > seen
            seen = self._signals
            for state in running:
                sent, deadline = stage.get(state.name, (signal.SIGINT, now))
                if now < deadline and not hurry:
                    continue
                if sent == signal.SIGINT:
                    log.warning("%s still running after SIGINT: SIGTERM", state.name)
                    state.proc.signal_group(signal.SIGTERM)
                    stage[state.name] = (signal.SIGTERM, now + state.spec.sigterm_timeout)
                elif sent == signal.SIGTERM:
                    log.error("%s still running after SIGTERM: SIGKILL", state.name)
                    state.problems.append("had to be killed (SIGKILL)")
                    self._failed = True
                    state.proc.signal_group(signal.SIGKILL)
                    stage[state.name] = (signal.SIGKILL, now + 5.0)
                elif deadline != float("inf"):
                    log.error("%s (pid %s) survives SIGKILL; giving up on it", state.name, state.proc.pid)
                    stage[state.name] = (signal.SIGKILL, float("inf"))
            if all(stage.get(s.name, (0, 0.0))[1] == float("inf") for s in running):
                break
            time.sleep(LOOP_S)
        for state in self.states:  # whatever the nodes left behind in their groups
            if state.spare is not None:
                state.spare.signal_group(signal.SIGKILL)
                state.spare.poll()
                state.spare = None
            if state.proc is not None:
                state.proc.signal_group(signal.SIGKILL)
                code = state.proc.poll()
                if state.phase == "running":
                    state.phase = "done"
                    if code not in (0, -signal.SIGINT, -signal.SIGTERM, None):
                        if not state.problems:
                            state.problems.append(f"exit code {code} on shutdown")
                        self._failed = True

    def _summary(self, elapsed: float) -> None:
        lines = [f"launch ended after {elapsed:.1f} s: {self._ending or 'stopped'}"]
        for state in self.states:
            runs = state.proc.runs if state.proc is not None else []
            codes = ",".join(str(r.returncode) for r in runs) or "-"
            extra = f"; {'; '.join(state.problems)}" if state.problems else ""
            lines.append(f"  {state.name:20s} runs {len(runs)}  exit {codes}{extra}")
        for name in self.spec.skipped:
            lines.append(f"  {name:20s} skipped (if/unless)")
        for line in lines:
            log.info("%s", line)
