"""tools/error_budget.py: one region per pixel, and the split's PSNR were a region perfect, against the
closed form of PSNR for known squared errors."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))

import error_budget  # noqa: E402


def test_every_pixel_gets_one_region_edges_first():
    """A 12x12 view: a 6x6 body square (torso), its two left columns garment. Pixels on either side of
    the silhouette's edge (radius 1) are edges (garment edge where the garment is within 2 px), the
    rest of the garment is garment, the rest of the body its part, everything else background."""
    labels = np.full((12, 12), -1)
    labels[3:9, 3:9] = 1  # PARTS[1] = torso
    garment = np.zeros((12, 12), bool)
    garment[3:9, 3:5] = True
    region = error_budget.partition(labels, garment, radius=1)
    name = {i: n for i, n in enumerate(error_budget.ORDER)}
    assert name[int(region[0, 0])] == "background"
    assert name[int(region[5, 6])] == "torso"  # inside, away from the edge and the garment
    assert name[int(region[3, 7])] == "body edge"  # on the edge, garment 3 px away
    assert name[int(region[2, 3])] == "garment edge"  # just outside, beside the garment
    assert name[int(region[5, 3])] == "garment edge"  # inside, the garment's outermost column
    assert name[int(region[5, 4])] == "garment"  # inside, on the garment, off the edge
    assert region.shape == labels.shape and region.min() >= 0


def test_the_bound_is_the_mean_view_psnr_with_the_region_made_perfect():
    """Two 2x2 views, regions 0 and 1 half the pixels each; errors of 0.1 on region 0 and 0.2 on
    region 1 in view 1, 0.1 everywhere in view 2 (every channel). Shares and bounds in closed form."""
    budget = error_budget.Budget()
    region = np.array([[0, 0], [1, 1]])
    target = np.zeros((2, 2, 3), np.uint8)
    first = np.zeros((2, 2, 3), np.uint8)
    first[0] = 25.5
    first[1] = 51
    second = np.full((2, 2, 3), 25.5).astype(np.uint8)
    budget.add(first, target, region)
    budget.add(second, target, region)
    report = budget.report()

    def psnr(mse):
        return -10 * math.log10(mse)

    e0, e1 = (25 / 255) ** 2, (51 / 255) ** 2  # uint8 rounding of 25.5 -> 25
    view1, view2 = psnr((2 * e0 + 2 * e1) / 4), psnr(e0)
    assert report["psnr"] == pytest.approx((view1 + view2) / 2)
    r0 = report["regions"][error_budget.ORDER[0]]
    r1 = report["regions"][error_budget.ORDER[1]]
    assert r0["pixel_share"] == pytest.approx(0.5)
    assert r0["error_share"] == pytest.approx(4 * e0 / (4 * e0 + 2 * e1 + 2 * e0))
    assert r0["psnr"] == pytest.approx(psnr(e0))
    assert r1["psnr"] == pytest.approx(psnr((e1 + e0) / 2))
    # View 1 without region 0's error, view 2 without it: only region 1 remains.
    assert r0["bound_psnr"] == pytest.approx((psnr(2 * e1 / 4) + psnr(2 * e0 / 4)) / 2)
    # A region with no pixels: its bound is the split's own PSNR.
    assert report["regions"][error_budget.ORDER[2]]["bound_psnr"] == pytest.approx(report["psnr"])
