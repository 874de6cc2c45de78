"""Command-line options of every command that talks to the bus: ``--bus URL`` and its companions.

One spelling everywhere: ``--bus URL`` (default ``$STG_BUS``, else ipc in the user's
runtime dir), ``--namespace NS``, ``--keys DIR``; clients also take ``--key-name NAME``.
A URL or namespace that is not valid is bad usage (exit 2, stg_node.cli.runner).

The bus tools deliberately skip stg_node.threads.configure_threads(): they run no torch or
OpenCV work, and must start fast on a robot that has no torch at all.
"""

from __future__ import annotations

import argparse
import logging

from stg_node.bus.config import ENV_BUS, ENV_KEY_NAME, ENV_KEYS, ENV_NAMESPACE, BusConfig
from stg_node.cli.runner import UsageError
from stg_node.signals import interrupt_on_signals

log = logging.getLogger(__name__)


def add_bus_options(
    parser: argparse.ArgumentParser, *, in_subcommand: bool = False, serve: bool = False
) -> None:
    """--bus/--namespace/--keys, and --key-name for clients.

    ``in_subcommand``: added to a subcommand too, they may follow it as well
    (``stg-topic echo x --bus URL``). ``serve``: for the broker, which serves every
    ``--bus`` given (repeat it: ipc for local nodes and tcp for a robot) and, as the CURVE
    server, has no key name of its own.
    """
    extra = {"default": argparse.SUPPRESS} if in_subcommand else {}
    where = f"default ${ENV_BUS} or ipc in the user's runtime dir"
    group = parser.add_argument_group("bus")
    if serve:
        group.add_argument(
            "--bus",
            metavar="URL",
            action="append",
            help=f"bus URL to serve (ipc://PATH, tcp://HOST:PORT); repeat for several; {where}",
        )
    else:
        group.add_argument(
            "--bus",
            metavar="URL",
            **extra,
            help=f"bus URL (ipc://PATH, tcp://HOST:PORT); {where}",
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
    if not serve:
        group.add_argument(
            "--key-name",
            metavar="NAME",
            **extra,
            help=f"this client's key name in DIR/clients (default ${ENV_KEY_NAME})",
        )


def bus_config(args: argparse.Namespace) -> BusConfig:
    """The client's BusConfig from the options and the environment; UsageError when invalid."""
    try:
        return BusConfig.from_env(
            url=args.bus, namespace=args.namespace, keys=args.keys, key_name=getattr(args, "key_name", None)
        )
    except ValueError as exc:
        raise UsageError(str(exc)) from exc


def served_configs(args: argparse.Namespace, urls: list[str] | None = None) -> list[BusConfig]:
    """One BusConfig per URL the broker serves: ``urls`` (else every --bus, else $STG_BUS or the
    default), with the namespace and keys of the options and the environment; UsageError
    when a URL or the namespace is not valid."""
    urls = urls or args.bus or [None]
    try:
        return [BusConfig.from_env(url=url, namespace=args.namespace, keys=args.keys) for url in urls]
    except ValueError as exc:
        raise UsageError(str(exc)) from exc


# Its former name here, kept for code that imports it: SIGINT and SIGTERM both raise KeyboardInterrupt.
sigterm_as_interrupt = interrupt_on_signals
