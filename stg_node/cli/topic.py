"""stg-topic: look at a running bus, like `ros2 topic`.

    stg-topic list                      topics seen (for --duration s), type, lane, rate, size, sources
    stg-topic echo avatar/image -n 1    print messages: header, fields, array summaries
    stg-topic hz camera/frame           message rate over a sliding window, every second
    stg-topic bw camera/frame           bandwidth and message sizes, every second

Topics are relative to --namespace unless they start with '/'. Every command stops on
Ctrl-C or SIGTERM (exit 0), after -n messages or after --duration seconds. The numbers
come from stg_node.bus.stats, the code a node's heartbeat reports its rates with.
"""

from __future__ import annotations

import argparse
import datetime
import functools
import sys
import time

import numpy as np

from stg_node.bus.codec import Envelope
from stg_node.bus.pubsub import Subscriber
from stg_node.bus.stats import ArrivalWindow, TopicCensus, WindowStats, format_bytes
from stg_node.cli.bus_options import add_bus_options, bus_config
from stg_node.cli.runner import UsageError, add_log_level_option, run_main


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="stg-topic",
        description=__doc__.split("\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__,
    )
    add_bus_options(parser)
    add_log_level_option(parser)
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("list", help="topics seen on the bus")
    add_bus_options(p, in_subcommand=True)
    p.add_argument(
        "--duration", type=float, default=2.0, metavar="S", help="how long to listen (default 2 s)"
    )

    p = sub.add_parser("echo", help="print messages of a topic")
    add_bus_options(p, in_subcommand=True)
    p.add_argument("topic")
    p.add_argument("-n", "--count", type=int, help="stop after this many messages")
    p.add_argument("--duration", type=float, metavar="S", help="stop after this many seconds")
    p.add_argument("--full", action="store_true", help="print array values (numpy's summarised form)")

    for name, what in (("hz", "message rate"), ("bw", "bandwidth")):
        p = sub.add_parser(name, help=f"{what} of a topic")
        add_bus_options(p, in_subcommand=True)
        p.add_argument("topic")
        p.add_argument("--window", type=int, default=100, help="messages in the sliding window (default 100)")
        p.add_argument("-n", "--count", type=int, help="stop after this many messages")
        p.add_argument("--duration", type=float, metavar="S", help="stop after this many seconds")
    return parser


# --- formatting --------------------------------------------------------------------------------


def _stamp(stamp_ns: int) -> str:
    when = datetime.datetime.fromtimestamp(stamp_ns / 1e9)
    age_ms = (time.time_ns() - stamp_ns) / 1e6
    return f"{when:%H:%M:%S}.{stamp_ns % 1_000_000_000:09d} (age {age_ms:.1f} ms)"


def _array_line(name: str, arr: np.ndarray, full: bool) -> str:
    text = f"{name}: {arr.dtype}{list(arr.shape)}"
    if arr.size and arr.dtype.kind in "uif":
        finite = arr[np.isfinite(arr)] if arr.dtype.kind == "f" else arr
        if finite.size:
            text += f"  min {finite.min():.4g}  max {finite.max():.4g}  mean {finite.mean():.4g}"
        if arr.dtype.kind == "f" and finite.size != arr.size:
            text += f"  ({arr.size - finite.size} non-finite)"
    if full:
        text += "\n  " + np.array2string(arr, threshold=64, edgeitems=3).replace("\n", "\n  ")
    return text


def format_envelope(env: Envelope, full: bool = False) -> str:
    h = env.header
    lines = [
        f"--- {env.topic}  {h['type']} v{h['v']}  seq {h['seq']}  src {h['src']}  {_stamp(h['stamp_ns'])}"
    ]
    for key, value in h.items():
        if key not in ("type", "v", "seq", "stamp_ns", "src", "arrays"):
            lines.append(f"{key}: {value!r}")
    lines.extend(_array_line(name, arr, full) for name, arr in env.arrays.items())
    return "\n".join(lines)


# --- commands ------------------------------------------------------------------------------------


def _deadline(duration: float | None) -> float | None:
    return None if duration is None else time.monotonic() + duration


def _remaining(deadline: float | None, tick: float = 1.0) -> float:
    if deadline is None:
        return tick
    return max(0.0, min(tick, deadline - time.monotonic()))


def cmd_list(config, args, out) -> int:
    census = TopicCensus()
    with Subscriber(config, [""], typed=False, keep_last=False) as sub:
        deadline = _deadline(args.duration)
        start = time.monotonic()
        while time.monotonic() < deadline:
            env = sub.recv(timeout=_remaining(deadline, 0.2))
            if env is not None:
                census.add(env.topic, env.type, env.nbytes, env.header["src"])
        elapsed = time.monotonic() - start
        drops = dict(sub.traffic.drops)
    if not census:
        print(f"no messages on {config.url} in {args.duration:g} s", file=out)
        return 0
    rows = [("TOPIC", "TYPE", "LANE", "MSGS", "HZ", "AVG SIZE", "SOURCES")]
    for topic in census.summary(elapsed):
        rows.append(
            (
                topic.topic,
                topic.type,
                config.lane_of(topic.topic).name,
                str(topic.messages),
                f"{topic.rate_hz:.1f}",
                format_bytes(topic.mean_bytes),
                ",".join(topic.sources),
            )
        )
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    for row in rows:
        print("  ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=True)).rstrip(), file=out)
    if drops:
        print(f"dropped: {drops}", file=out)
    return 0


def cmd_echo(config, args, out) -> int:
    printed = 0
    with Subscriber(config, [args.topic], typed=False) as sub:
        deadline = _deadline(args.duration)
        while args.count is None or printed < args.count:
            if deadline is not None and time.monotonic() >= deadline:
                break
            env = sub.recv(timeout=_remaining(deadline))
            if env is None:
                continue
            print(format_envelope(env, args.full), file=out, flush=True)
            printed += 1
    return 0


def cmd_rate(config, args, out, mode: str) -> int:
    """hz and bw: a sliding window of arrival times and sizes (bus.stats.ArrivalWindow), every second."""
    window = ArrivalWindow(args.window)
    next_report = time.monotonic() + 1.0
    with Subscriber(config, [args.topic], typed=False, keep_last=False) as sub:
        deadline = _deadline(args.duration)
        print(f"subscribed to {sub.topics[0]}", file=out, flush=True)
        while (args.count is None or window.received < args.count) and (
            deadline is None or time.monotonic() < deadline
        ):
            env = sub.recv(timeout=_remaining(deadline, max(0.0, next_report - time.monotonic())))
            now = time.monotonic()
            if env is not None:
                window.add(now, env.nbytes)
            if now >= next_report:
                _report(mode, window, out)
                next_report = now + 1.0
        if window.received:
            _report(mode, window, out)
    if not window.received:
        print(f"no messages on {args.topic}", file=out)
    return 0


def _report(mode: str, window: ArrivalWindow, out) -> None:
    stats: WindowStats | None = window.stats()
    if stats is None:
        print("no new messages" if not len(window) else "1 message so far", file=out, flush=True)
    elif mode == "hz":
        print(
            f"average rate: {stats.rate_hz:.3f} Hz\n"
            f"\tmin: {stats.min_gap_s:.4f}s max: {stats.max_gap_s:.4f}s "
            f"std dev: {stats.std_gap_s:.5f}s window: {stats.arrivals - 1}",
            file=out,
            flush=True,
        )
    else:
        print(
            f"average: {format_bytes(stats.bytes_per_s)}/s\n\tmean: {format_bytes(stats.mean_bytes)} "
            f"min: {format_bytes(stats.min_bytes)} max: {format_bytes(stats.max_bytes)} "
            f"window: {stats.sized}",
            file=out,
            flush=True,
        )


def run(args: argparse.Namespace, out=None) -> int:
    out = out or sys.stdout
    config = bus_config(args)
    if args.command in ("hz", "bw") and args.window < 1:
        raise UsageError(f"--window must be >= 1, got {args.window}")
    if args.command == "list":
        return cmd_list(config, args, out)
    if args.command == "echo":
        return cmd_echo(config, args, out)
    return cmd_rate(config, args, out, args.command)


def main(argv=None, out=None) -> int:
    return run_main(build_parser(), functools.partial(run, out=out), argv, stop_is_success=True)


if __name__ == "__main__":
    sys.exit(main())
