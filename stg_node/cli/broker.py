"""stg-broker: run the bus broker (XSUB/XPUB proxies per lane, last-value cache for latched topics).

stg-broker                                   ipc at $STG_BUS or the default path
stg-broker ipc:///tmp/stg/bus tcp://0.0.0.0:7400 --keys keys/
                                             local nodes on ipc, a robot over CURVE tcp
stg-broker --bus tcp://0.0.0.0:7400          the same --bus option as every bus command
"""

from __future__ import annotations

import argparse
import logging
import sys

from stg_node.bus.broker import Broker, BrokerRunning
from stg_node.bus.config import BusConfig
from stg_node.cli.bus_options import sigterm_as_interrupt
from stg_node.logs import configure_logging

log = logging.getLogger("stg_node.cli.broker")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="stg-broker",
        description=__doc__.split("\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__,
    )
    parser.add_argument("urls", nargs="*", metavar="URL", help="bus URLs to serve (default $STG_BUS or ipc)")
    parser.add_argument(
        "--bus",
        action="append",
        default=[],
        metavar="URL",
        help="a bus URL to serve, as every bus command takes it (repeatable; same as a positional URL)",
    )
    parser.add_argument(
        "--keys",
        metavar="DIR",
        help="CURVE key directory (stg-keys init): tcp admits only authorised clients",
    )
    parser.add_argument("--curve-on-ipc", action="store_true", help="require CURVE on ipc too")
    parser.add_argument("--namespace", default="", help="namespace of the broker's own node/status topic")
    parser.add_argument(
        "--status-period",
        type=float,
        default=1.0,
        metavar="S",
        help="seconds between the broker's NodeStatus messages (0: none)",
    )
    parser.add_argument("--log-level", help="DEBUG, INFO, ... (default $STG_LOG_LEVEL or INFO)")
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    configure_logging(args.log_level)
    urls = [*args.urls, *args.bus] or [BusConfig.from_env().url]
    with sigterm_as_interrupt():
        try:
            broker = Broker(
                urls,
                keys=args.keys,
                curve_on_ipc=args.curve_on_ipc,
                namespace=args.namespace,
                status_period_s=args.status_period,
            )
        except (BrokerRunning, OSError, ValueError) as exc:
            print(f"stg-broker: {exc}", file=sys.stderr)
            return 1
        try:
            print(f"stg-broker: serving {' '.join(urls)} (Ctrl-C to stop)", flush=True)
            broker.run()  # returns on Ctrl-C / SIGTERM with every socket closed
        except KeyboardInterrupt:  # one that arrived outside the loop
            pass
        finally:
            broker.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
