"""``stg-splat-prebuild``: build the splat kernels now instead of at the first render.

    stg-splat-prebuild [--backend cpu|cuda|all]

Exit status: 0 built (or cached, or not applicable here), 1 a build failed, 2 bad usage.
See docs/SPLAT.md ("Prebuilding the kernels").
"""

from __future__ import annotations

import argparse
import sys

from stg_node.cli.runner import add_log_level_option, run_main


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="stg-splat-prebuild",
        description="Compile and cache the splat kernels: the cpu backend's C++ kernels and gsplat's "
        "CUDA kernels (cuda backend), which otherwise build on first use.",
    )
    parser.add_argument(
        "--backend",
        choices=("cpu", "cuda", "all"),
        default="all",
        help="which kernels (default %(default)s; 'all' skips cuda where torch has no CUDA)",
    )
    add_log_level_option(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    return run_main(build_parser(), run, argv)


def run(args: argparse.Namespace) -> int:
    from stg_node.splat.prebuild import PREBUILD_BACKENDS, prebuild

    backends = PREBUILD_BACKENDS if args.backend == "all" else (args.backend,)
    results = prebuild(backends, required=args.backend != "all")
    for r in results:
        state = "skipped" if r.skipped else ("ok" if r.ok else "FAILED")
        print(f"{r.backend}: {state}: {r.detail}", file=sys.stdout if r.ok else sys.stderr)
    return 0 if all(r.ok for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
