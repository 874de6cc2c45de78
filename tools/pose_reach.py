"""How far the time-code rule reaches on a run or a subject, and which steps it leaves out.

A pose without a time (an animation, the novel-pose split) renders the non-rigid state of its
nearest training instant only within the *reach*, the largest step between training poses adjacent
in time (stg_node/avatar/timecode.py); steps across skipped frames and the tracker's jumps and
one-frame glitches do not count. This prints, per input, the median step, the largest step (what
the reach would be if every step counted), the reach, and the steps left out by kind:

    python tools/pose_reach.py RUN_DIR ...               # the run's own index (avatar.stgsnap)
    python tools/pose_reach.py SYNTH_DIR --frames 72     # an stg-synth subject's true poses, frames 0..71

Used for docs/BENCHMARKS.md, "The reach on tracked poses".
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from stg_node.avatar.timecode import STEP_KINDS, classify_steps, motion_steps, pose_key  # noqa: E402


def run_index(folder: Path) -> tuple[np.ndarray, np.ndarray]:
    """(keys, times) of a run's pose index, as its renderer sees them."""
    from stg_node.avatar.snapshot import model_from_snapshot, read_snapshot_file

    index = model_from_snapshot(read_snapshot_file(folder / "avatar.stgsnap")).pose_index
    return index.keys, index.times


def synth_index(folder: Path, frames: int | None) -> tuple[np.ndarray, np.ndarray]:
    """(keys, times) of an stg-synth subject's true poses (``new_params/I.npy``), frames 0..frames-1."""
    count = len(list((folder / "new_params").glob("*.npy")))
    count = count if frames is None else min(count, frames)
    files = [folder / "new_params" / f"{i}.npy" for i in range(count)]
    poses = [np.load(f, allow_pickle=True).item()["poses"] for f in files]
    return pose_key(np.asarray(poses, np.float32).reshape(-1, 24, 3)), np.arange(count, dtype=np.float64)


def report(keys: np.ndarray, times: np.ndarray) -> dict:
    order = np.argsort(times, kind="stable")
    keys, times = keys[order], times[order]
    steps, kinds = classify_steps(keys, times)
    out = {
        "keys": int(keys.shape[0]),
        "median_step": float(np.median(steps)),
        "largest_step": float(steps.max()),
        "reach": float(motion_steps(keys, times).max()),  # what PoseTimeIndex.reach measures
    }
    for number, kind in enumerate(STEP_KINDS[1:], start=1):
        left = steps[kinds == number]
        out[kind] = [round(float(v), 3) for v in np.sort(left)[::-1]]
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("paths", nargs="+", type=Path, help="run folders or stg-synth folders")
    parser.add_argument("--frames", type=int, default=None, help="stg-synth folders: the first N frames")
    args = parser.parse_args(argv)
    for path in args.paths:
        if (path / "avatar.stgsnap").exists():
            keys, times = run_index(path)
        elif (path / "new_params").is_dir():
            keys, times = synth_index(path, args.frames)
        else:
            parser.error(f"{path}: neither a run folder (avatar.stgsnap) nor an stg-synth one (new_params/)")
        if keys.shape[0] < 2:
            print(f"{path}: {keys.shape[0]} training pose(s): no step to measure")
            continue
        r = report(keys, times)
        left = "; ".join(f"{k} {r[k]}" for k in STEP_KINDS[1:] if r[k]) or "none"
        print(
            f"{path}: {r['keys']} poses, median step {r['median_step']:.3f}, "
            f"largest {r['largest_step']:.3f}, reach {r['reach']:.3f} "
            f"({r['reach'] / r['largest_step']:.2f}x the largest); left out: {left}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
