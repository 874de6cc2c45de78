"""stg-launch: run a YAML launch file (a broker and supervised node processes); docs/LAUNCH.md.

    stg-launch launch/demo.yaml                       run it; Ctrl-C stops every node in order
    stg-launch launch/demo.yaml out:=/tmp/d iters:=500    arguments as name:=value
    stg-launch --validate launch/replay_zju.yaml data_root:=/data/zju/CoreView_377
    stg-launch --show-args launch/demo.yaml           the file's arguments, defaults and docs
    stg-launch --schema                               the launch-file JSON schema

Exit codes: 0 every node ended well, 1 a node failed, 2 bad usage or a bad launch file (the
message names the file and line).
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from stg_node.cli.runner import UsageError, add_log_level_option, run_main
from stg_node.launch.process import OutputSink
from stg_node.launch.spec import LaunchSpec, parse_overrides, read_launch
from stg_node.launch.yamlfile import LaunchFileError
from stg_node.nodes.runtime import name_process

log = logging.getLogger("stg_node.launch")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="stg-launch",
        description=__doc__.split("\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__,
    )
    parser.add_argument("file", nargs="?", type=Path, help="launch file (YAML)")
    parser.add_argument("overrides", nargs="*", metavar="name:=value", help="launch arguments")
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument(
        "--validate", action="store_true", help="check the file (and node parameters); start nothing"
    )
    mode.add_argument("--show-args", action="store_true", help="list the file's arguments")
    mode.add_argument("--print", action="store_true", help="print the processes it would start")
    mode.add_argument("--schema", action="store_true", help="print the launch-file JSON schema")
    parser.add_argument("--no-broker", action="store_true", help="do not start a broker (one runs already)")
    parser.add_argument("--log-dir", type=Path, help="also write each process's output to DIR/NAME.log")
    parser.add_argument("--no-color", action="store_true", help="no colored [name] prefixes")
    add_log_level_option(parser)
    return parser


def _show_args(spec: LaunchSpec) -> str:
    lines = [f"{spec.path}: {spec.description}".rstrip(": ")]
    for arg in spec.args:
        default = "(required)" if arg.default is None else f"default {arg.default!r}"
        lines.append(f"  {arg.name}:={spec.arg_values.get(arg.name, '')!s:20s} {default}  {arg.doc}".rstrip())
    return "\n".join(lines)


def _print_plan(spec: LaunchSpec) -> str:
    import shlex

    lines = [f"bus {spec.bus.url}  broker {'yes' if spec.bus.broker else 'no (external)'}"]
    for node in spec.nodes:
        flags = [f for f in ("required" if node.required else "", "respawn" if node.respawn else "") if f]
        after = f" after {','.join(node.after)}" if node.after else ""
        lines.append(f"{node.name} [{node.source}] ready={node.ready}{after} {' '.join(flags)}".rstrip())
        lines.append("    " + shlex.join(node.command(spec.bus)))
    for name in spec.skipped:
        lines.append(f"{name}: skipped (if/unless)")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    if args.schema:
        from stg_node.launch.schema import schema_text

        sys.stdout.write(schema_text())
        return 0
    if args.file is None:
        raise UsageError("a launch file is required")
    try:
        spec = read_launch(args.file, parse_overrides(args.overrides))
    except (LaunchFileError, ValueError) as exc:  # a bad file is bad usage: it names file and line
        raise UsageError(str(exc)) from exc
    if args.validate:
        skipped = f", skipped {', '.join(spec.skipped)}" if spec.skipped else ""
        print(f"{args.file}: ok ({len(spec.nodes)} node(s){skipped})")
        return 0
    if args.show_args:
        print(_show_args(spec))
        return 0
    if args.print:
        print(_print_plan(spec))
        return 0

    from stg_node.launch.supervisor import Launcher

    name_process("launch")
    sink = OutputSink(log_dir=args.log_dir, color=False if args.no_color else None)
    try:  # the launcher installs its own SIGINT/SIGTERM handlers: a stop is its normal end
        return Launcher(spec, sink=sink, broker=False if args.no_broker else None).run()
    finally:
        sink.close()


def main(argv=None) -> int:
    return run_main(build_parser(), run, argv, stop_is_success=True)


if __name__ == "__main__":
    sys.exit(main())
