"""``stg-export``: a trained avatar as a standard 3DGS PLY (opens in ordinary splat viewers).

    stg-export RUN_DIR -o FILE.ply [--frame N | --canonical]

``--canonical`` (default): the Gaussians in the canonical big pose. ``--frame N``: posed at
training frame N (its pose and time), in the dataset's world. See stg_node/avatar/export.py.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from stg_node.cli.runner import UsageError, add_log_level_option, run_main


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="stg-export", description="Export a trained STG-Avatar as a 3DGS PLY.")
    p.add_argument("run", help="run folder written by stg-train")
    p.add_argument("-o", "--out", required=True, help="output .ply file")
    which = p.add_mutually_exclusive_group()
    which.add_argument("--frame", type=int, default=None, help="pose the avatar at this training frame")
    which.add_argument("--canonical", action="store_true", help="the canonical big pose (default)")
    p.add_argument("--data", default=None, help="dataset folder (for --frame; default: the run's)")
    add_log_level_option(p)
    return p


def main(argv: list[str] | None = None) -> int:
    from stg_node.avatar.snapshot import SnapshotError
    from stg_node.data.errors import DatasetError

    return run_main(build_parser(), run, argv, expected=(DatasetError, SnapshotError))


def run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    if out.suffix.lower() != ".ply":
        raise UsageError(f"-o must name a .ply file, got {out}")
    from stg_node.avatar.export import export_canonical, export_posed
    from stg_node.avatar.loading import corrected, load_run_renderer

    run_dir, renderer, corrections, _ = load_run_renderer(Path(args.run))
    model = renderer.model
    out.parent.mkdir(parents=True, exist_ok=True)
    if args.frame is None:
        export_canonical(model, out)
        print(f"wrote {model.table.num} canonical Gaussians to {out}")
        return 0
    spec = run_dir.data_spec()
    if args.data:
        spec = spec.with_root(Path(args.data).resolve())
    train = spec.open("train")
    if args.frame not in train.frames:
        raise UsageError(
            f"--frame {args.frame} is not a training frame ({train.frames[0]}..{train.frames[-1]})"
        )
    smpl = corrected(train.smpl(args.frame), corrections.get(args.frame))
    export_posed(model, smpl, train.time(args.frame), train.camera(train.camera_names[0]), out)
    print(f"wrote the avatar at frame {args.frame} to {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
