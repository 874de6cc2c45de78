"""Where a trained avatar's novel-view error lies, and how much fixing each part could gain at most.

    python tools/error_budget.py --data runs/mv/zju23 --runs full=RUN_A lbs=RUN_B [--mid]

For each run, the novel-view split of tools/tradeoff_multiview.py (the cameras no row trains on,
every ``view_every``-th training frame) is rendered and every pixel is put in one region of a
partition, from the synthetic benchmark's true surface of that frame:

- ``garment edge`` / ``body edge``: within ``--band`` pixels of the true silhouette's edge, inside
  or out (a few pixels of pose, shape or cloth error show here first), split by whether a garment
  pixel is within ``--band`` + 1 pixels (the hem's and sleeves' swing shows at their outline);
- ``garment``: the rest of the pixels where a garment face is seen (the non-rigid part's target,
  stg_node.data.synth.garment_truth);
- the body parts of stg_node.data.synth.body_parts (head, torso, arms, hands, legs, feet) for the
  remaining body pixels (the limbs are where fast rigid motion is);
- ``background``: the rest (spill beyond the silhouette).

Per region it reports the share of pixels, the share of the squared error, the pooled PSNR, and
the **bound**: the split's PSNR (mean over views, as stg-eval scores it) were that region perfect.
The bound of the garment is the most a better non-rigid part could gain on this metric; the
difference between two runs per region says where one beats the other.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(Path(__file__).resolve().parent))

ORDER = (
    "garment edge",
    "body edge",
    "garment",
    "head",
    "torso",
    "arms",
    "hands",
    "legs",
    "feet",
    "background",
)


def band(mask: np.ndarray, radius: int) -> np.ndarray:
    """(H, W) bool: pixels within ``radius`` of the edge of ``mask`` (dilation minus erosion)."""
    import cv2

    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
    m = mask.astype(np.uint8)
    return (cv2.dilate(m, kernel) - cv2.erode(m, kernel)) > 0


def partition(labels: np.ndarray, garment: np.ndarray, radius: int) -> np.ndarray:
    """(H, W) int index into ORDER: one region per pixel (edges first, then garment, parts, rest)."""
    from stg_node.data.synth.body_parts import PARTS

    out = np.full(labels.shape, ORDER.index("background"), np.int64)
    for i, name in enumerate(PARTS):
        out[labels == i] = ORDER.index(name)
    out[garment] = ORDER.index("garment")
    edge = band(labels >= 0, radius)
    near_garment = band(garment, radius + 1) | garment
    out[edge & near_garment] = ORDER.index("garment edge")
    out[edge & ~near_garment] = ORDER.index("body edge")
    return out


class Budget:
    """Squared error per region pooled over views, and the per-view PSNR with each region zeroed."""

    def __init__(self):
        self.sq = np.zeros(len(ORDER))
        self.count = np.zeros(len(ORDER))
        self.view_psnr: list[float] = []
        self.bound_psnr: list[np.ndarray] = []

    def add(self, pred: np.ndarray, target: np.ndarray, region: np.ndarray) -> None:
        err = ((pred.astype(np.float64) - target.astype(np.float64)) / 255.0) ** 2  # (H, W, 3)
        per_pixel = err.sum(axis=-1)
        sq = np.bincount(region.ravel(), per_pixel.ravel(), minlength=len(ORDER))
        self.sq += sq
        self.count += np.bincount(region.ravel(), minlength=len(ORDER))
        total = err.size
        self.view_psnr.append(_psnr(sq.sum() / total))
        self.bound_psnr.append(np.array([_psnr((sq.sum() - s) / total) for s in sq]))

    def report(self) -> dict:
        psnr = float(np.mean(self.view_psnr))
        bounds = np.mean(np.stack(self.bound_psnr), axis=0)
        out = {"psnr": psnr, "views": len(self.view_psnr), "regions": {}}
        for i, name in enumerate(ORDER):
            out["regions"][name] = {
                "pixel_share": float(self.count[i] / self.count.sum()),
                "error_share": float(self.sq[i] / self.sq.sum()),
                "psnr": _psnr(self.sq[i] / max(3 * self.count[i], 1)),
                "bound_psnr": float(bounds[i]),
            }
        return out


def _psnr(mse: float) -> float:
    return math.inf if mse <= 0 else -10.0 * math.log10(mse)


def budget_of(run_dir: Path, data: Path, scale, radius: int) -> dict:
    from tradeoff_multiview import held_out_split

    from stg_node.avatar.loading import corrected, load_run_renderer
    from stg_node.body import load_body_model
    from stg_node.data.synth.body_parts import SynthPartLabeller
    from stg_node.data.synth.garment_truth import benchmark_garment_pixels, benchmark_looseness, garment_faces

    _, renderer, corrections, _ = load_run_renderer(run_dir)
    body = load_body_model()
    labeller = SynthPartLabeller(data, body)
    is_garment = garment_faces(labeller.faces, benchmark_looseness(data, body))
    budget = Budget()
    for sample in held_out_split(data, scale):
        image = sample.image
        if sample.mask is not None:
            image = np.where(sample.mask[..., None] > 127, image, 0).astype(np.uint8)
        smpl = corrected(sample.smpl, (corrections or {}).get(sample.index))
        out = renderer.render(sample.camera, smpl, sample.time)
        labels = labeller(sample.index, sample.camera)
        garment = benchmark_garment_pixels(data, sample.index, sample.camera, labeller.faces, is_garment)
        budget.add(out.image, image, partition(labels, garment, radius))
    return budget.report()


def table(reports: dict[str, dict]) -> str:
    names = list(reports)
    head = "| region | pixels | " + " | ".join(f"{n}: error share / PSNR / bound" for n in names) + " |"
    lines = [head, "|" + "---|" * (2 + len(names))]
    first = reports[names[0]]
    for region in ORDER:
        cells = [
            f"{r['regions'][region]['error_share'] * 100:.1f} % / {r['regions'][region]['psnr']:.2f} / "
            f"{r['regions'][region]['bound_psnr']:.2f}"
            for r in reports.values()
        ]
        lines.append(
            f"| {region} | {first['regions'][region]['pixel_share'] * 100:.2f} % | "
            + " | ".join(cells)
            + " |"
        )
    lines.append("| whole image | 100 % | " + " | ".join(f"{r['psnr']:.2f}" for r in reports.values()) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    from tradeoff_multiview import FULL, MID

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", required=True, help="the study's subject folder")
    p.add_argument("--runs", nargs="+", required=True, metavar="NAME=RUN_DIR", help="trained runs")
    p.add_argument("--mid", action="store_true", help="the study's --mid scale (256 px)")
    p.add_argument("--band", type=int, default=None, help="boundary band in px (default 1 per 128 px)")
    p.add_argument("--json", default=None, help="write the reports here")
    args = p.parse_args(argv)
    scale = MID if args.mid else FULL
    radius = args.band if args.band is not None else max(1, scale.size // 128)
    reports = {}
    for item in args.runs:
        name, _, path = item.partition("=")
        if not path:
            p.error(f"--runs: expected NAME=RUN_DIR, got {item!r}")
        reports[name] = budget_of(Path(path), Path(args.data), scale, radius)
    if args.json:
        Path(args.json).write_text(json.dumps(reports, indent=1))
    print(f"boundary band: {radius} px")
    print(table(reports))
    return 0


if __name__ == "__main__":
    sys.exit(main())
