"""``stg-render``: novel views and animations of a trained avatar, as an MP4 or a folder of PNGs.

    stg-render RUN_DIR -o OUT(.mp4|dir) [--views orbit|follow|dataset] [--poses FILE] [--fill F]
               [--light LIGHT]

``--views orbit`` (default without --poses): a turntable around the avatar.
``--views follow`` (default with --poses): the training camera's bearing (when animating: the
body's front), following the body.
Both frame the avatar: centred and about two thirds of the image tall (``--fill``), whatever
the distance of the training camera, aimed at the body of each frame so it is never cut
(stg_node/avatar/framing.py). ``--views dataset``: every camera of the dataset, tiled in a
grid per frame, as they are.
``--poses FILE``: animate with SMPL parameters (``.npz`` with poses/Rh/Th, a ZJU-MoCap
``new_params`` folder, or a subject folder holding one); the avatar keeps its own body shape
(the file's betas are ignored) and each pose takes the time code of the nearest training pose,
kept stable along the sequence (docs/AVATAR.md). Without --poses the training frames are used.
``--light`` (an avatar trained with shading): ``learned`` (default: its learned light, fixed in the
world, so the avatar is lit by the room as it turns), ``baked`` (the light turns with the body, as
a colour without shading), ``albedo`` (unlit), 27 comma-separated SH irradiance numbers, or a JSON
file with ``sh`` or ``ambient`` and ``lights`` (docs/AVATAR.md).
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from stg_node.cli.runner import UsageError, add_log_level_option, run_main
from stg_node.threads import configure_threads

log = logging.getLogger("stg_node.cli.render")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="stg-render", description="Render a trained STG-Avatar run.")
    p.add_argument("run", help="run folder written by stg-train")
    p.add_argument("-o", "--out", required=True, help="output .mp4 file or folder for PNGs")
    p.add_argument(
        "--views",
        default=None,
        choices=("orbit", "follow", "dataset"),
        help="cameras (default: orbit, or follow with --poses)",
    )
    p.add_argument(
        "--fill",
        type=float,
        default=None,
        metavar="F",
        help="orbit/follow: the avatar's height as a fraction of the image's (default 2/3)",
    )
    p.add_argument("--poses", default=None, help="SMPL pose file (.npz) or ZJU-style folder to animate")
    p.add_argument(
        "--frames", type=int, default=None, help="number of frames (default: all poses; orbit 120)"
    )
    p.add_argument("--size", type=int, default=None, help="image size (default: the dataset's)")
    p.add_argument("--fps", type=float, default=30.0, help="MP4 frame rate (default %(default)s)")
    p.add_argument(
        "--light",
        default="learned",
        help="learned (default), baked, albedo, 27 comma-separated SH numbers, or a JSON file",
    )
    p.add_argument("--data", default=None, help="dataset folder (default: the one the run trained on)")
    p.add_argument("--backend", default="auto", choices=("auto", "cpu", "cuda", "torch"))
    p.add_argument("--device", default="cpu")
    p.add_argument("--threads", default=None)
    p.add_argument("--no-progress", action="store_true")
    add_log_level_option(p)
    return p


def main(argv: list[str] | None = None) -> int:
    from stg_node.avatar.snapshot import SnapshotError
    from stg_node.data.errors import DatasetError

    return run_main(build_parser(), run, argv, expected=(DatasetError, SnapshotError))


def run(args: argparse.Namespace) -> int:
    if args.frames is not None and args.frames < 1:
        raise UsageError("--frames must be >= 1")
    out = Path(args.out)
    if out.suffix and out.suffix.lower() != ".mp4":
        raise UsageError(f"-o must be a .mp4 file or a folder, got {out}")
    if args.fill is not None and not 0.05 <= args.fill <= 1.0:
        raise UsageError(f"--fill must lie in [0.05, 1], got {args.fill}")
    configure_threads(args.threads)
    from stg_node.avatar.animation import render_run
    from stg_node.avatar.framing import FramingRule
    from stg_node.avatar.shading import parse_light

    try:
        light = parse_light(args.light)
    except ValueError as exc:
        raise UsageError(str(exc)) from exc

    rule = FramingRule() if args.fill is None else FramingRule(fraction=args.fill)
    summary = render_run(
        Path(args.run),
        out,
        views=args.views,
        poses=args.poses,
        frames=args.frames,
        size=args.size,
        fps=args.fps,
        data=args.data,
        device=args.device,
        backend=args.backend,
        show_progress=not args.no_progress,
        rule=rule,
        light=light,
    )
    print(f"wrote {summary.frames} frames to {out}")
    framing = summary.framing
    if framing.frames:
        print(
            f"framing ({summary.views}): the avatar whole in {100 * framing.whole:.0f}% of frames, "
            f"at least {100 * framing.min_height:.0f}% of the image tall in "
            f"{100 * framing.tall_enough:.0f}%, "
            f"median height {100 * framing.median_height:.0f}%"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
