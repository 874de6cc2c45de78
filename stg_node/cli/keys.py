"""stg-keys: make and manage the CURVE keys that secure tcp bus endpoints.

stg-keys init keys/                 broker key pair + empty authorized/ list
stg-keys add keys/ robot            a client key pair, authorised; copy keys/server.key and
                                    keys/clients/robot.key_secret to the robot
stg-keys revoke keys/ robot         take it off authorized/ (restart the broker)
stg-keys authorize keys/ FILE.key   admit a public key made elsewhere
stg-keys list keys/
"""

from __future__ import annotations

import argparse
import sys

from stg_node.bus import security
from stg_node.logs import configure_logging


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="stg-keys",
        description=__doc__.split("\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__,
    )
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


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    configure_logging()
    try:
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
            if security.revoke(args.dir, args.name):
                print(f"revoked {args.name!r}; restart the broker to drop its connections")
            else:
                print(f"{args.name!r} was not authorised", file=sys.stderr)
                return 1
        elif args.command == "authorize":
            print(f"authorised {security.authorize(args.dir, args.public_key)}")
        else:
            for name in security.authorized_names(args.dir):
                print(name)
    except (OSError, ValueError) as exc:
        print(f"stg-keys: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
