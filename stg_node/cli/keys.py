"""stg-keys: make and manage the CURVE keys that secure tcp bus endpoints.

stg-keys init keys/                 broker key pair + empty authorized/ list
stg-keys add keys/ robot            a client key pair, authorised; copy keys/server.key and
                                    keys/clients/robot.key_secret to the robot
stg-keys revoke keys/ robot         take it off authorized/ (restart the broker)
stg-keys authorize keys/ FILE.key   admit a public key made elsewhere
stg-keys list keys/

Exit 1 when the work fails (no key directory there, a client that exists or was not
authorised), 2 for bad usage (e.g. a key name that cannot be a file name).
"""

from __future__ import annotations

import argparse
import sys

from stg_node.bus import security
from stg_node.cli.runner import UsageError, add_log_level_option, run_main


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="stg-keys",
        description=__doc__.split("\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__,
    )
    add_log_level_option(parser)
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("init", help="create a key directory with the broker's key pair")
    p.add_argument("dir")
    p.add_argument("--force", action="store_true", help="replace existing broker keys")
    p = sub.add_parser("add", help="make and authorise a client key pair")
    p.add_argument("dir")
    p.add_argument("name")
    p = sub.add_parser("revoke", help="remove a client from authorized/")
    p.add_argument("dir")
    p.add_argument("name")
    p = sub.add_parser("authorize", help="authorise a public key file made elsewhere")
    p.add_argument("dir")
    p.add_argument("public_key")
    p = sub.add_parser("list", help="list authorised clients")
    p.add_argument("dir")
    return parser


def run(args: argparse.Namespace) -> int:
    if getattr(args, "name", None) is not None:
        try:
            security.check_key_name(args.name)
        except ValueError as exc:
            raise UsageError(str(exc)) from exc
    if args.command == "init":
        root = security.init_keys(args.dir, force=args.force)
        print(
            f"broker keys in {root}: server.key (public, give to clients), "
            f"server.key_secret (keep on the broker)"
        )
    elif args.command == "add":
        secret = security.add_client(args.dir, args.name)
        print(
            f"client {args.name!r}: {secret} (copy it and {args.dir}/server.key to the client; "
            f"use --keys DIR --key-name {args.name})"
        )
    elif args.command == "revoke":
        if not security.revoke(args.dir, args.name):
            print(f"stg-keys: error: {args.name!r} was not authorised", file=sys.stderr)
            return 1
        print(f"revoked {args.name!r}; restart the broker to drop its connections")
    elif args.command == "authorize":
        print(f"authorised {security.authorize(args.dir, args.public_key)}")
    else:
        for name in security.authorized_names(args.dir):
            print(name)
    return 0


def main(argv=None) -> int:
    return run_main(build_parser(), run, argv)


if __name__ == "__main__":
    sys.exit(main())
