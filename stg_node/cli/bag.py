"""stg-bag: record the bus to MCAP, play it back, inspect and export recordings (like `ros2 bag`).

    stg-bag record -o session.mcap [--topics REGEX ...] [--split-size MB] [--split-duration S]
                   [--compression none|zstd|lz4] [--duration S] [--launch FILE]
    stg-bag play session.mcap [--rate R] [--loop] [--topics REGEX] [--start-offset S] [--paused]
                 [--lockstep [--ack-topic T] [--acks N] [--ack-timeout S]]
    stg-bag info session.mcap [--json]
    stg-bag export session.mcap --topic avatar/image -o out.mp4      (or -o frames/ for PNGs)
    stg-bag export session.mcap --foxglove -o session.view.mcap

record and play take the bus options (--bus URL, --namespace, --keys, --key-name). Ctrl-C
or SIGTERM stops them cleanly and they exit 0 (a recording is finished, never left
half-written); info and export exit 1 when interrupted (their output is incomplete). --rate 0
plays as fast as possible. While playing on a terminal: space pauses/resumes, s steps one
message, q quits; SIGUSR1 toggles pause and SIGUSR2 steps (for scripts).
Exit codes: 0 done, 1 the work failed, 2 bad usage. Guide: docs/RECORDING.md.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import json
import logging
import os
import select
import signal
import sys
import threading
import time

from stg_node.bus.recording import (
    COMPRESSIONS,
    BagReader,
    Lockstep,
    PlaybackError,
    Player,
    Recorder,
    RecordingError,
    bag_info,
    format_info,
)
from stg_node.bus.recording.info import info_dict
from stg_node.bus.stats import format_bytes
from stg_node.cli.bus_options import add_bus_options, bus_config
from stg_node.cli.runner import EXIT_INTERRUPTED, EXIT_OK, UsageError, add_log_level_option, run_main
from stg_node.signals import StopSignals

log = logging.getLogger("stg_node.cli.bag")

MB = 1_000_000


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="stg-bag",
        description=__doc__.split("\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__,
    )
    add_log_level_option(parser)
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("record", help="record the bus to an MCAP file")
    add_bus_options(p)
    p.add_argument("-o", "--output", required=True, metavar="FILE.mcap", help="the recording to write")
    p.add_argument(
        "--topics",
        nargs="+",
        metavar="REGEX",
        help="record only topics matching one of these regexes (searched in the full topic, namespace "
        "included, e.g. 'camera/|body/pose'); default: every topic",
    )
    p.add_argument("--split-size", type=float, metavar="MB", help="start a new file after MB megabytes")
    p.add_argument("--split-duration", type=float, metavar="S", help="start a new file every S seconds")
    p.add_argument("--compression", choices=COMPRESSIONS, default="none", help="(default none)")
    p.add_argument("--chunk-size", type=float, default=4.0, metavar="MB", help="chunk size (default 4 MB)")
    p.add_argument(
        "--flush-interval",
        type=float,
        default=1.0,
        metavar="S",
        help="write the chunk in progress at least every S s (what a kill -9 can lose; default 1)",
    )
    p.add_argument(
        "--max-queue", type=float, default=512, metavar="MB", help="memory for messages not yet on disk (512)"
    )
    p.add_argument("--duration", type=float, metavar="S", help="stop after S seconds")
    p.add_argument("--launch", metavar="FILE", help="launch file to store in the recording")

    p = sub.add_parser("play", help="publish a recording on the bus")
    add_bus_options(p)
    p.add_argument(
        "files", nargs="+", metavar="FILE", help="recording(s): a file, a split set's name, a folder"
    )
    p.add_argument("--rate", type=float, default=1.0, help="speed factor; 0 = as fast as possible")
    p.add_argument("--loop", action="store_true", help="start over at the end")
    p.add_argument(
        "--topics", nargs="+", metavar="REGEX", help="play only topics matching these regexes (full topics)"
    )
    p.add_argument("--start-offset", type=float, default=0.0, metavar="S", help="skip the first S seconds")
    p.add_argument("--paused", action="store_true", help="start paused (space / SIGUSR1 resumes)")
    p.add_argument(
        "--wait",
        type=float,
        default=1.0,
        metavar="S",
        help="wait up to S s for subscribers first (default 1)",
    )
    p.add_argument(
        "--lockstep",
        action="store_true",
        help="send each message only after the previous one was acknowledged (regression tests)",
    )
    p.add_argument("--ack-topic", default="node/ack", help="where acknowledgements arrive (default node/ack)")
    p.add_argument("--acks", type=int, default=1, metavar="N", help="acknowledgements needed per message")
    p.add_argument("--ack-timeout", type=float, default=30.0, metavar="S", help="fail after S s without one")
    p.add_argument("--ack-for", metavar="REGEX", help="only messages on matching topics need acknowledgement")

    p = sub.add_parser("info", help="what a recording holds")
    p.add_argument("files", nargs="+", metavar="FILE")
    p.add_argument("--json", action="store_true", help="machine-readable output")

    p = sub.add_parser("export", help="images to a video or PNGs; or a Foxglove view file")
    p.add_argument("files", nargs="+", metavar="FILE")
    p.add_argument("-o", "--output", required=True, help="out.mp4 / out.avi, a folder for PNGs, or view.mcap")
    p.add_argument("--topic", help="the image topic to export (e.g. avatar/image)")
    p.add_argument("--array", default="image", help="which array: image (default), mask, alpha")
    p.add_argument("--fps", type=float, help="video frame rate (default: the topic's recorded rate)")
    p.add_argument("--png", action="store_true", help="PNG files into the output folder")
    p.add_argument("--foxglove", action="store_true", help="write an MCAP with Foxglove view channels")
    p.add_argument("--topics", nargs="+", metavar="REGEX", help="with --foxglove: only these topics")
    p.add_argument("--image-format", choices=("jpeg", "png", "raw"), default="jpeg", help="with --foxglove")
    p.add_argument(
        "--no-original", action="store_true", help="with --foxglove: leave out the stg-bus channels"
    )
    return parser


# --- signals ---------------------------------------------------------------------------------------


@contextlib.contextmanager
def player_controls(player: Player, stop: StopSignals):
    """SIGUSR1 toggles pause, SIGUSR2 steps; on a terminal, keys: space, s, q."""
    previous = {
        signal.SIGUSR1: signal.signal(signal.SIGUSR1, lambda *_: player.toggle_pause()),
        signal.SIGUSR2: signal.signal(signal.SIGUSR2, lambda *_: player.step()),
    }
    keys = None
    done = threading.Event()
    if sys.stdin is not None and sys.stdin.isatty():
        keys = threading.Thread(target=_read_keys, args=(player, stop, done), daemon=True)
        keys.start()
    try:
        yield
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)
        if keys is not None:
            done.set()
            keys.join(1.0)  # it restores the terminal's mode


def _read_keys(player: Player, stop: StopSignals, done: threading.Event) -> None:
    import termios  # noqa: PLC0415 (POSIX terminals only)
    import tty  # noqa: PLC0415

    fd = sys.stdin.fileno()
    saved = termios.tcgetattr(fd)
    try:
        tty.setcbreak(fd)
        print("keys: space pause/resume, s step, q quit", file=sys.stderr)
        while not done.is_set():
            if not select.select([fd], [], [], 0.1)[0]:
                continue
            key = os.read(fd, 1)
            if key == b" ":
                print("paused" if player.toggle_pause() else "playing", file=sys.stderr)
            elif key == b"s":
                player.step()
            elif key in (b"q", b"\x03"):
                stop.request("q")  # stops the player (on_stop)
    finally:
        termios.tcsetattr(fd, termios.TCSADRAIN, saved)


# --- commands ----------------------------------------------------------------------------------------


def _positive(value: float | None, what: str) -> None:
    if value is not None and value <= 0:
        raise UsageError(f"{what} must be > 0, got {value:g}")


def cmd_record(args, out) -> int:
    for value, what in (
        (args.split_size, "--split-size"),
        (args.split_duration, "--split-duration"),
        (args.chunk_size, "--chunk-size"),
        (args.flush_interval, "--flush-interval"),
        (args.max_queue, "--max-queue"),
        (args.duration, "--duration"),
    ):
        _positive(value, what)
    config = bus_config(args)
    try:
        recorder = Recorder(
            args.output,
            config=config,
            topics=args.topics,
            compression=args.compression,
            split_size=None if args.split_size is None else int(args.split_size * MB),
            split_duration_s=args.split_duration,
            chunk_size=int(args.chunk_size * MB),
            flush_interval_s=args.flush_interval,
            max_queue_bytes=int(args.max_queue * MB),
            launch_file=args.launch,
            metadata={"command": " ".join(["stg-bag", *sys.argv[1:]])},
        )
    except RecordingError as exc:
        raise UsageError(str(exc)) from None
    with StopSignals() as stop:  # the first Ctrl-C/SIGTERM stops cleanly; a second one interrupts
        recorder.start()
        print(f"stg-bag: recording {config.url} to {args.output} (Ctrl-C to stop)", file=out, flush=True)
        deadline = None if args.duration is None else time.monotonic() + args.duration
        next_report = time.monotonic() + 10.0
        try:
            while not stop.requested and (deadline is None or time.monotonic() < deadline):
                recorder.poll(0.1)
                if time.monotonic() >= next_report:
                    s = recorder.stats()
                    log.info(
                        "%d messages, %s written, %d queued, drops %s",
                        s.written,
                        format_bytes(s.bytes_written),
                        s.queued,
                        s.drops or 0,
                    )
                    next_report += 10.0
        finally:
            stats = recorder.stop()
    files = ", ".join(stats.files)
    print(
        f"stg-bag: recorded {stats.written} messages ({format_bytes(stats.bytes_written)}) to {files}",
        file=out,
    )
    if stats.drops:
        detail = ", ".join(f"{n} {reason}" for reason, n in sorted(stats.drops.items()))
        print(f"stg-bag: dropped {stats.dropped} message(s): {detail}", file=out)
    else:
        print("stg-bag: no drops", file=out)
    return EXIT_OK


def cmd_play(args, out) -> int:
    if args.rate < 0:
        raise UsageError(f"--rate must be >= 0 (0 = as fast as possible), got {args.rate:g}")
    if args.start_offset < 0:
        raise UsageError(f"--start-offset must be >= 0, got {args.start_offset:g}")
    lockstep = None
    if args.lockstep:
        try:
            lockstep = Lockstep(
                ack_topic=args.ack_topic, acks=args.acks, timeout_s=args.ack_timeout, topics=args.ack_for
            )
        except ValueError as exc:
            raise UsageError(str(exc)) from None
    config = bus_config(args)
    reader = BagReader(args.files)
    for bag in reader.files:
        if bag.truncated:
            print(f"stg-bag: {bag.path} is truncated ({bag.problem}); playing what was recovered", file=out)
    player = Player(
        reader,
        config=config,
        rate=args.rate,
        loop=args.loop,
        topics=args.topics,
        start_offset_s=args.start_offset,
        paused=args.paused,
        lockstep=lockstep,
        wait_for_subscribers_s=args.wait,
    )
    with StopSignals(on_stop=player.stop) as stop, player_controls(player, stop):
        if args.paused:
            print("stg-bag: paused (space or SIGUSR1 resumes, s or SIGUSR2 steps)", file=out, flush=True)
        stats = player.run()
    print(
        f"stg-bag: published {stats.published} messages ({format_bytes(stats.bytes)})"
        + (f", {stats.loops} loops" if args.loop else "")
        + (f", {stats.acks} acknowledgements" if lockstep else "")
        + (f"; skipped {stats.skipped} invalid recorded message(s)" if stats.skipped else ""),
        file=out,
    )
    if stop.requested and stop.signal_name != "q" and not args.loop:
        print("stg-bag: interrupted before the end of the recording", file=sys.stderr)
        return EXIT_INTERRUPTED
    return EXIT_OK


def cmd_info(args, out) -> int:
    info = bag_info(BagReader(args.files))
    if args.json:
        print(json.dumps(info_dict(info), indent=2), file=out)
    else:
        print(format_info(info), file=out)
    return EXIT_OK


def cmd_export(args, out) -> int:
    if args.foxglove == bool(args.topic):
        raise UsageError("export needs either --topic TOPIC (images) or --foxglove (a view file)")
    reader = BagReader(args.files)
    if args.foxglove:
        from stg_node.bus.recording.foxglove import export_foxglove  # noqa: PLC0415

        stats = export_foxglove(
            reader,
            args.output,
            topics=args.topics,
            image_format=args.image_format,
            keep_original=not args.no_original,
        )
        views = ", ".join(f"{topic} ({n})" for topic, n in sorted(stats.views.items()))
        print(f"stg-bag: wrote {args.output}: {stats.messages} original messages; views: {views}", file=out)
        return EXIT_OK
    from stg_node.bus.recording.export import export_images  # noqa: PLC0415

    _positive(args.fps, "--fps")
    stats = export_images(
        reader, args.topic, args.output, array=args.array, fps=args.fps, png=True if args.png else None
    )
    what = "PNG files" if args.png or not args.output.lower().endswith((".mp4", ".avi", ".mkv")) else "frames"
    print(f"stg-bag: wrote {stats.images} {what} to {stats.out} ({stats.fps:.2f} fps)", file=out)
    return EXIT_OK


COMMANDS = {"record": cmd_record, "play": cmd_play, "info": cmd_info, "export": cmd_export}


def run(args: argparse.Namespace, out=None) -> int:
    return COMMANDS[args.command](args, out or sys.stdout)


def main(argv=None, out=None) -> int:
    """Exit codes (docs/CLI.md): 0 done, and for record (and play --loop) also a stop by Ctrl-C or
    SIGTERM; 1 the work failed; 2 bad usage; 130 play, info or export interrupted."""
    return run_main(build_parser(), functools.partial(run, out=out), argv, expected=(PlaybackError,))


if __name__ == "__main__":
    sys.exit(main())
