"""``stg-calibrate``: a rig's intrinsics and extrinsics from recordings of a ChArUco board -> rig.json.

    stg-calibrate CAM1.mp4 CAM2.mp4 ... --out rig.json --board 7x5 --square 0.08 --marker 0.06
                  [--cameras NAME,...] [--dictionary DICT_5X5_100] [--origin camera|board] [--every N]
    stg-calibrate --write-board board.png --board 7x5 --square 0.08 --marker 0.06 [--dpi 300]

Each input is one camera's recording (a video file or an image folder), all filmed at once;
frames are matched by time stamp. Prints and stores (rig.json "calibration") the reprojection
error per camera. Exit codes as every command (docs/CLI.md): 0 done, 1 the calibration failed
(a camera never saw the board, unsynchronised inputs, ...), 2 bad usage. See docs/RIGS.md.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from stg_node.cli.runner import UsageError, add_log_level_option, run_main
from stg_node.threads import configure_threads

INCH_M = 0.0254


def build_parser() -> argparse.ArgumentParser:
    from stg_node.calibration.board import DEFAULT_DICTIONARY

    p = argparse.ArgumentParser(
        prog="stg-calibrate",
        description="Calibrate a rig of cameras (intrinsics, lens distortion, poses in one world frame) "
        "from recordings of a ChArUco board, and write rig.json.",
    )
    p.add_argument("inputs", nargs="*", type=Path, help="one video file or image folder per camera")
    p.add_argument("--out", type=Path, default=None, help="the rig.json to write")
    p.add_argument(
        "--cameras",
        default=None,
        metavar="NAME,...",
        help="camera names, in input order (default: file names)",
    )
    p.add_argument(
        "--board", default="7x5", metavar="COLSxROWS", help="squares across x down (default %(default)s)"
    )
    p.add_argument(
        "--square", type=float, default=None, metavar="M", help="square side as printed, metres (measure it)"
    )
    p.add_argument("--marker", type=float, default=None, metavar="M", help="marker side as printed, metres")
    p.add_argument(
        "--dictionary", default=DEFAULT_DICTIONARY, help="ArUco dictionary of the board (default %(default)s)"
    )
    p.add_argument(
        "--legacy-board", action="store_true", help="a board printed by OpenCV < 4.6 (even row count)"
    )
    p.add_argument(
        "--origin",
        choices=("camera", "board"),
        default="camera",
        help="world frame: the first camera's (default), or the board where it was first seen, z out of its "
        "face (lay it face up on the floor first: a z-up world on the floor)",
    )
    p.add_argument("--every", type=int, default=1, metavar="N", help="look at every N-th instant (default 1)")
    p.add_argument(
        "--max-skew-ms", type=float, default=None, help="frame time tolerance (default half a frame)"
    )
    p.add_argument("--fps", type=float, default=None, help="frame rate of image-folder inputs (default 30)")
    p.add_argument(
        "--k3", action="store_true", help="also fit the third radial distortion term (wide-angle lenses)"
    )
    p.add_argument(
        "--write-board", type=Path, default=None, metavar="PNG", help="write the board to print, then exit"
    )
    p.add_argument("--dpi", type=float, default=300.0, help="--write-board resolution (default %(default)s)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--threads", default=None, help="CPU threads (default: STG_THREADS or 1)")
    add_log_level_option(p)
    return p


def _board(args):
    from stg_node.calibration.board import BoardError, BoardSpec, parse_board_size

    if args.square is None or args.marker is None:
        raise UsageError(
            "--square and --marker are required: the printed sizes in metres (measure the print)"
        )
    try:
        columns, rows = parse_board_size(args.board)
        spec = BoardSpec(columns, rows, args.square, args.marker, args.dictionary, args.legacy_board)
        spec.validate()
    except BoardError as exc:
        raise UsageError(str(exc)) from exc
    return spec


def run(args: argparse.Namespace) -> int:
    import cv2

    try:
        configure_threads(args.threads)
    except ValueError as exc:
        raise UsageError(str(exc)) from exc
    spec = _board(args)
    if args.write_board is not None:
        pixels_per_metre = args.dpi / INCH_M
        if not cv2.imwrite(str(args.write_board), spec.image(pixels_per_metre)):
            raise OSError(f"could not write {args.write_board}")
        width, height = spec.size_m
        print(
            f"wrote {args.write_board}: {spec.columns}x{spec.rows} squares, "
            f"{width * 100:.1f} x {height * 100:.1f} cm at {args.dpi:g} dpi; print at 100 % scale and "
            "measure a square"
        )
        return 0
    if not args.inputs:
        raise UsageError("give one recording (video file or image folder) per camera")
    if args.out is None:
        raise UsageError("--out rig.json is required")
    if args.every < 1:
        raise UsageError(f"--every must be >= 1, got {args.every}")
    missing = [str(p) for p in args.inputs if not p.exists()]
    if missing:
        raise UsageError(f"no such input: {', '.join(missing)}")
    names = camera_names(args.cameras, args.inputs)

    from stg_node.calibration.capture import calibrate_capture, detect_capture
    from stg_node.calibration.rig import write_rig

    capture = detect_capture(
        args.inputs,
        names,
        spec,
        every=args.every,
        max_skew_s=None if args.max_skew_ms is None else args.max_skew_ms / 1e3,
        fps=args.fps,
        progress=not args.no_progress,
    )
    result = calibrate_capture(capture, spec, origin=args.origin, k3=args.k3)
    write_rig(args.out, result.rig)
    print(f"wrote {args.out}: {len(names)} cameras, board seen at {result.instants} instants")
    print(f"  {'camera':12s} {'views':>6s} {'corners':>8s} {'RMS px':>8s} {'max px':>8s}  centre (m)")
    for report, camera in zip(result.reports, result.rig.cameras, strict=True):
        centre = ", ".join(f"{v:+.3f}" for v in camera.center)
        print(
            f"  {report.name:12s} {report.views:6d} {report.corners:8d} {report.rms_px:8.3f} "
            f"{report.max_px:8.3f}  ({centre})"
        )
    return 0


def camera_names(text: str | None, inputs) -> list[str]:
    """``--cameras a,b`` or the inputs' file names (without suffix), checked unique and valid."""
    from stg_node.calibration.rig import NAME_PATTERN

    names = [n.strip() for n in text.split(",")] if text else [Path(p).stem for p in inputs]
    if len(names) != len(inputs):
        raise UsageError(f"--cameras names {len(names)} cameras for {len(inputs)} inputs")
    bad = [n for n in names if not NAME_PATTERN.match(n)]
    if bad:
        raise UsageError(f"camera names may hold letters, digits, '_', '.', '-' only: {bad} (use --cameras)")
    if len(set(names)) != len(names):
        raise UsageError(f"camera names must be unique, got {names} (use --cameras)")
    return names


def main(argv: list[str] | None = None) -> int:
    from stg_node.calibration.solve import CalibrationError
    from stg_node.tracking.sync import UnsynchronisedError

    return run_main(build_parser(), run, argv, expected=(CalibrationError, UnsynchronisedError))


if __name__ == "__main__":
    sys.exit(main())
