"""stg-broker: run the bus broker (XSUB/XPUB proxies per lane, last-value cache for latched topics).

stg-broker                                   ipc at $STG_BUS or the default path
stg-broker --bus ipc:///tmp/stg/bus --bus tcp://0.0.0.0:7400 --keys keys/
                                             local nodes on ipc, a robot over CURVE tcp

Runs until Ctrl-C or SIGTERM (exit 0). URLs given without --bus still work but are
deprecated.
"""

from __future__ import annotations

import argparse
import logging
import sys

from stg_node.bus.broker import Broker, BrokerRunning
from stg_node.cli.bus_options import add_bus_options, served_configs
from stg_node.cli.runner import add_log_level_option, run_main

log = logging.getLogger("stg_node.cli.broker")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="stg-broker",
        description=__doc__.split("\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__,
    )
    add_bus_options(parser, serve=True)
    parser.add_argument("urls", nargs="*", metavar="URL", help=argparse.SUPPRESS)  # deprecated: use --bus
    parser.add_argument("--curve-on-ipc", action="store_true", help="require CURVE on ipc too")
    parser.add_argument(
        "--status-period",
        type=float,
        default=1.0,
        metavar="S",
        help="seconds between the broker's NodeStatus messages (0: none)",
    )
    add_log_level_option(parser)
    return parser


def run(args: argparse.Namespace) -> int:
    if args.urls:
        log.warning("stg-broker URL ... is deprecated; use --bus URL (once per URL)")
    configs = served_configs(args, [*(args.bus or []), *args.urls])
    urls = [config.url for config in configs]
    broker = Broker(
        urls,
        keys=configs[0].keys,
        curve_on_ipc=args.curve_on_ipc,
        namespace=configs[0].namespace,
        status_period_s=args.status_period,
    )
    try:
        print(f"stg-broker: serving {' '.join(urls)} (Ctrl-C to stop)", flush=True)
        broker.run()  # returns on Ctrl-C / SIGTERM with every socket closed
    finally:
        broker.close()
    return 0


def main(argv=None) -> int:
    return run_main(build_parser(), run, argv, stop_is_success=True, expected=(BrokerRunning,))


if __name__ == "__main__":
    sys.exit(main())
