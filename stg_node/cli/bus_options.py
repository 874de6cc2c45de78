"""Command-line options shared by the bus tools (stg-topic, stg-broker) and Ctrl-C/SIGTERM handling.

The bus tools deliberately skip stg_node.threads.configure_threads(): they run no torch or
OpenCV work, and must start fast on a robot that has no torch at all.
"""

from __future__ import annotations

import argparse

from stg_node.bus.config import ENV_BUS, ENV_KEY_NAME, ENV_KEYS, ENV_NAMESPACE, BusConfig
from stg_node.signals import interrupt_on_signals


def add_bus_options(parser: argparse.ArgumentParser, *, in_subcommand: bool = False) -> None:
    """--bus/--namespace/--keys/--key-name. Added to the subcommands too (``in_subcommand``),
    they may follow the subcommand as well (``stg-topic echo x --bus URL``)."""
    extra = {"default": argparse.SUPPRESS} if in_subcommand else {}
    group = parser.add_argument_group("bus")
    group.add_argument(
        "--bus",
        metavar="URL",
        **extra,
        help=f"bus URL (ipc://PATH, tcp://HOST:PORT); default ${ENV_BUS} or ipc in the user's runtime dir",
    )
    group.add_argument(
        "--namespace", metavar="NS", **extra, help=f"topic namespace, e.g. rig1 (default ${ENV_NAMESPACE})"
    )
    group.add_argument(
        "--keys",
        metavar="DIR",
        **extra,
        help=f"CURVE key directory for tcp (default ${ENV_KEYS}); see stg-keys",
    )
    group.add_argument(
        "--key-name",
        metavar="NAME",
        **extra,
        help=f"this client's key name in DIR/clients (default ${ENV_KEY_NAME})",
    )


def bus_config(args: argparse.Namespace) -> BusConfig:
    return BusConfig.from_env(url=args.bus, namespace=args.namespace, keys=args.keys, key_name=args.key_name)


# SIGTERM (from a launcher) and SIGINT both end a bus tool like Ctrl-C, installed explicitly so that
# a tool started in the background (SIGINT inherited as ignored) still stops on Ctrl-C.
sigterm_as_interrupt = interrupt_on_signals
