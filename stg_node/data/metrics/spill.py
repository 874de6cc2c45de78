"""Spill: how much of a render covers pixels where the true subject is not, and next to which part.

A Gaussian stretched into a needle under a pose it was never trained in shows as a thin streak
hanging off a limb. PSNR counts it with every other error (a colour off, a limb a little
misplaced) and cannot say which it was; what sees it alone is the rendered opacity where the
true background is:

    spill = sum over true-background pixels farther than ``margin_px`` from the true silhouette
            of the rendered alpha (0..1), in percent of the true silhouette's area.

``margin_px`` (default 2) leaves out the antialiased rim every render has (a splat's footprint
is a few pixels wide); what reaches farther is a streak or a floater. Each spilled pixel is
charged to the region (body part) whose true pixel is nearest to it (a Euclidean distance
transform), so ``spill`` per part says which limb the streaks hang from; a part's figure is in
percent of that part's own true area, pooled over the views (as :class:`RegionScores` pools
squared errors). Alpha above one half counts separately as ``covered`` (pixels a viewer reads
as the avatar's, not as a faint haze).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

DEFAULT_MARGIN_PX = 2.0  # the antialiased rim of every render: not spill
COVERED_ALPHA = 0.5  # alpha at which a spilled pixel reads as the avatar's


class SpillScores:
    """Rendered alpha beyond the true silhouette, pooled over views, per region (see module doc)."""

    def __init__(self, margin_px: float = DEFAULT_MARGIN_PX):
        if margin_px < 0:
            raise ValueError(f"margin_px must be >= 0, got {margin_px}")
        self.margin_px = float(margin_px)
        self.spill: dict[str, float] = {}  # summed alpha of the spilled pixels charged to a region
        self.covered: dict[str, int] = {}  # spilled pixels with alpha >= COVERED_ALPHA
        self.area: dict[str, int] = {}  # true pixels of the region
        self.total_spill = 0.0
        self.total_covered = 0
        self.total_area = 0
        self.views = 0

    def add(
        self, alpha: np.ndarray, true_mask: np.ndarray, regions: dict[str, np.ndarray] | None = None
    ) -> None:
        """One view: ``alpha`` (H, W) rendered opacity (uint8 0..255 or floats 0..1), ``true_mask``
        (H, W) the true subject (bool, or uint8 > 127), ``regions`` name -> (H, W) bool true pixels
        of each part (optional: without them only the totals are kept)."""
        alpha = np.asarray(alpha)
        a = alpha.astype(np.float64) / 255.0 if alpha.dtype == np.uint8 else alpha.astype(np.float64)
        mask = np.asarray(true_mask)
        mask = mask > 127 if mask.dtype == np.uint8 else mask.astype(bool)
        if a.shape != mask.shape:
            raise ValueError(f"alpha {a.shape} and true mask {mask.shape} must have the same (H, W) shape")
        names = list(regions or {})
        labels = np.full(mask.shape, -1, np.int64)
        for i, name in enumerate(names):
            region = np.asarray(regions[name], bool)
            if region.shape != mask.shape:
                raise ValueError(f"region {name!r} has shape {region.shape}, the view {mask.shape}")
            labels[region & (labels < 0)] = i
        silhouette = mask | (labels >= 0)
        self.views += 1
        self.total_area += int(silhouette.sum())
        if not silhouette.any():
            return
        # distance of every pixel to the nearest silhouette pixel, and which pixel that is
        outside = ~silhouette
        distance, nearest = ndimage.distance_transform_edt(outside, return_indices=True)
        far = outside & (distance > self.margin_px)
        spilled = a * far
        self.total_spill += float(spilled.sum())
        self.total_covered += int((far & (a >= COVERED_ALPHA)).sum())
        if not names:
            return
        # charge each far pixel to the part of its nearest labelled pixel (silhouette pixels with
        # no part, e.g. a garment when no region names it, take the nearest labelled one instead)
        if (labels >= 0).any():
            _, nearest_labelled = ndimage.distance_transform_edt(labels < 0, return_indices=True)
            owner = labels[nearest_labelled[0], nearest_labelled[1]]
        else:
            owner = labels
        for i, name in enumerate(names):
            mine = far & (owner == i)
            self.spill[name] = self.spill.get(name, 0.0) + float(spilled[mine].sum())
            self.covered[name] = self.covered.get(name, 0) + int((mine & (a >= COVERED_ALPHA)).sum())
            self.area[name] = self.area.get(name, 0) + int((labels == i).sum())

    def percent(self, name: str | None = None) -> float:
        """Spill of region ``name`` (None: the whole subject) in percent of its true area; NaN when
        it was never seen."""
        spill, area = (
            (self.total_spill, self.total_area)
            if name is None
            else (self.spill.get(name, 0.0), self.area.get(name, 0))
        )
        return 100.0 * spill / area if area else float("nan")

    def report(self) -> dict:
        """``spill_pct``, ``covered_px`` (per view), ``margin_px``, ``views`` and ``regions``: name ->
        {spill_pct, covered_px (per view), pixels}."""
        per_view = max(self.views, 1)
        return {
            "spill_pct": self.percent(),
            "covered_px": self.total_covered / per_view,
            "margin_px": self.margin_px,
            "views": self.views,
            "regions": {
                name: {
                    "spill_pct": self.percent(name),
                    "covered_px": self.covered[name] / per_view,
                    "pixels": self.area[name],
                }
                for name in self.spill
            },
        }
