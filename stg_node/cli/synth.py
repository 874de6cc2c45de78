"""``stg-synth``: generate the synthetic benchmark (ground truth images, masks, SMPL, vertices; ZJU layout).

    stg-synth --out DIR [--seed S --frames N --size PX --motion NAME --views C --view-every K ...]
              [--shading lambert|none|room|environment] [--self-shadow]
              [--test-motion NAMES] [--train-yaw DEG --test-yaw DEG]

See docs/SYNTH.md for what is rendered, the garment model, the cameras and splits, and the layout.
Exit 2 for bad usage (an invalid option value, an --out that holds other files without
--overwrite), 1 when the work fails (e.g. a --body file that cannot be read), 130 on Ctrl-C.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from stg_node.cli.runner import UsageError, add_log_level_option, run_main
from stg_node.threads import configure_threads


def build_parser() -> argparse.ArgumentParser:
    from stg_node.data.synth.generate import SHADING_MODES, SynthConfig
    from stg_node.data.synth.motions import MOTIONS

    defaults = SynthConfig(out=Path("."))
    parser = argparse.ArgumentParser(
        prog="stg-synth",
        description="Render the synthetic avatar benchmark (open SMPL-format body, procedural motion, "
        "garment dynamics, z-buffered mesh rasterizer) in ZJU-MoCap's original layout.",
    )
    parser.add_argument("--out", required=True, type=Path, help="output folder (created; must be empty)")
    parser.add_argument("--seed", type=int, default=defaults.seed, help="random seed (default %(default)s)")
    parser.add_argument(
        "--frames", type=int, default=defaults.num_frames, help="frames (default %(default)s)"
    )
    parser.add_argument(
        "--size", type=int, default=defaults.size, help="square image size in pixels (default %(default)s)"
    )
    parser.add_argument(
        "--motion", choices=MOTIONS, default=defaults.motion, help="motion (default %(default)s)"
    )
    parser.add_argument("--fps", type=float, default=defaults.fps, help="frame rate (default %(default)s)")
    parser.add_argument(
        "--views",
        type=int,
        default=defaults.num_novel_views,
        help="held-out cameras around the subject (default %(default)s)",
    )
    parser.add_argument(
        "--view-every",
        type=int,
        default=defaults.view_every,
        help="render the held-out cameras every K-th frame (default %(default)s, the ZJU-MoCap protocol)",
    )
    parser.add_argument(
        "--train-cameras",
        default="1",
        metavar="N,...",
        help="cameras that render every frame, by number (1 = Camera_B1, the training camera; e.g. 1,7,13,18 "
        "for multi-view training with --views 22: docs/RIGS.md); the others every --view-every-th",
    )
    parser.add_argument(
        "--train-fraction",
        type=float,
        default=defaults.train_fraction,
        help="leading fraction of frames used for training; the rest are novel poses (default %(default)s)",
    )
    parser.add_argument(
        "--supersample",
        type=int,
        default=defaults.supersample,
        help="anti-aliasing samples per pixel side (default %(default)s; 1 = none)",
    )
    parser.add_argument(
        "--shading",
        choices=SHADING_MODES,
        default=defaults.shading,
        help="lighting (default %(default)s: a light fixed in the body frame, turning with it; "
        "none: albedo only; room: a light fixed in the world; environment: several coloured lights "
        "fixed in the world)",
    )
    parser.add_argument(
        "--self-shadow",
        action="store_true",
        help="the body occludes its own light: ambient occlusion from the posed body on the ambient "
        "light, shadows of the distant lights (about 1.3 s per frame more; docs/SYNTH.md)",
    )
    parser.add_argument(
        "--test-motion",
        default=None,
        metavar="NAMES",
        help="motion(s) of the held-out frames, comma-separated, played in equal parts "
        f"({', '.join(MOTIONS)}; default: a fresh draw of --motion)",
    )
    parser.add_argument(
        "--train-yaw",
        type=float,
        default=None,
        metavar="DEG",
        help="the training frames face the camera within a window of DEG degrees "
        "(default: they turn through at least one full revolution)",
    )
    parser.add_argument(
        "--test-yaw",
        type=float,
        default=None,
        metavar="DEG",
        help="the held-out frames' window is turned DEG degrees from the training one "
        "(orientations never seen in training; needs --train-yaw)",
    )
    parser.add_argument("--depth", action="store_true", help="also write depth/ (uint16 PNG, millimetres)")
    filming = parser.add_argument_group("filming conditions (real footage)")
    filming.add_argument(
        "--distance",
        type=float,
        default=defaults.camera_distance,
        metavar="M",
        help="distance of the cameras to the subject (default %(default)s m; closer films it larger "
        "with --fov)",
    )
    filming.add_argument(
        "--fov",
        type=float,
        default=None,
        metavar="DEG",
        help="field of view of every camera (default: each frames 2.4 m of height at the subject)",
    )
    filming.add_argument(
        "--exposure-jitter",
        type=float,
        default=defaults.exposure_jitter,
        metavar="S",
        help="per-frame exposure and white-balance drift of the training camera: std of the log "
        "gain (default %(default)s: steady; 0.15 is a phone's auto-exposure)",
    )
    parser.add_argument("--overwrite", action="store_true", help="replace a previous benchmark in --out")
    parser.add_argument(
        "--body", default=None, help="SMPL-format model file or folder (default: the open body)"
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--threads", default=None, help="CPU threads (default: STG_THREADS or 1)")
    add_log_level_option(parser)
    return parser


def run(args: argparse.Namespace) -> int:
    try:
        configure_threads(args.threads)
    except ValueError as exc:
        raise UsageError(str(exc)) from exc

    from stg_node.data.synth.generate import SynthConfig, generate

    try:
        train_cameras = tuple(int(n) - 1 for n in args.train_cameras.split(","))
    except ValueError:
        raise UsageError(
            f"--train-cameras must be camera numbers like 1,7,13, got {args.train_cameras!r}"
        ) from None
    config = SynthConfig(
        out=args.out,
        seed=args.seed,
        num_frames=args.frames,
        size=args.size,
        motion=args.motion,
        fps=args.fps,
        num_novel_views=args.views,
        view_every=args.view_every,
        train_fraction=args.train_fraction,
        supersample=args.supersample,
        shading=args.shading,
        self_shadow=args.self_shadow,
        test_motion=args.test_motion,
        train_yaw_deg=args.train_yaw,
        test_yaw_deg=args.test_yaw,
        write_depth=args.depth,
        overwrite=args.overwrite,
        train_cameras=train_cameras,
        camera_distance=args.distance,
        fov_deg=args.fov,
        exposure_jitter=args.exposure_jitter,
    )
    try:
        config.validate()
    except ValueError as exc:
        raise UsageError(str(exc)) from exc
    body = None
    if args.body is not None:
        from stg_node.body import load_body_model

        body = load_body_model(args.body)
    try:
        result = generate(config, body=body, progress=not args.no_progress)
    except FileExistsError as exc:  # --out holds something else: the command line must change
        raise UsageError(str(exc)) from exc
    print(f"wrote {result.num_views} views of {config.num_frames} frames to {result.out}")
    summary = result.metadata["held_out"]["summary"]
    if summary["frames"]:
        pose, turn = summary["pose_rms_deg"], summary["orientation_deg"]
        print(
            f"held-out frames: {summary['frames']}; distance to the nearest training pose "
            f"{pose['median']:.1f} deg RMS over the joints (median; max {pose['max']:.1f}), "
            f"to the nearest training orientation {turn['median']:.1f} deg (median; max {turn['max']:.1f})"
        )
    return 0


def main(argv: list[str] | None = None) -> int:
    return run_main(build_parser(), run, argv)


if __name__ == "__main__":
    sys.exit(main())
