"""The Gaussian and step budget scaled with the person's size in pixels.

The presets were tuned on the synthetic benchmark at 512 x 512, where the person covers about
``REFERENCE_AREA_PX`` pixels (366 px tall). Detail to reconstruct grows with the pixels the person
covers: a person filling a phone's frame at the same resolution covers two to three times as
many, and with the same number of Gaussians each one has to cover more of them (blur); with the
same number of steps, each Gaussian is fitted less. So a run scales its preset by the ratio of the
person's median mask area in the training frames to the reference:

- Gaussians (``num_gaussians``, ``max_gaussians``) and new Gaussians per flow-guided round in
  proportion to the area ratio (Gaussians per person pixel kept);
- iterations by its square root (more Gaussians converge in fewer visits each than the ratio
  would say, since each step still renders all of them), at most twice the preset's;
- every setting that measures the body's motion or extent in pixels (``PIXEL_SETTINGS``: the
  motion thresholds of densification and of the motion gates, the crop's margin) by the linear
  size ratio (the square root of the area ratio), so that they keep meaning the same motion of the
  body in metres, and the flow term's weight (its residual is in pixels) by its inverse.

Left in pixels on purpose: what judges the image itself, pixel by pixel: the clone/split gradient
threshold (``grad_threshold``: a Gaussian's summed pull over the pixels it covers, which for the
same blur in pixels is the same at any size), the error regions (``region_px``: with the new
Gaussians per round scaled by the area the same share of them is seeded per bad region) and the
loss's SSIM window (11 px, 3DGS's: a larger person should be sharp at the pixels it has, not at the
reference's). The world-unit settings (scales, pruning, learning rates of the means) need nothing.

For the Gaussians and the steps the ratio is clamped to [1, ``MAX_SCALE``]: a person smaller than
the reference keeps the preset's, and a huge image does not make a run unbounded. Fewer Gaussians
for a smaller person would save time and cost quality: on the benchmark's subjects at 256 px (a
quarter of the reference's area), starting from the area's share of the preset's Gaussians
(3,100-3,400 instead of 12,000) ended with 40 % fewer, cost 0.2-0.65 dB on novel views (LPIPS
0.015 -> 0.021 on the still subject) and did not make a still subject's model smaller than a
dancer's (docs/BENCHMARKS.md, issue 22, round 10).

The pixel settings follow a smaller person down too, to half the reference's linear size
(``MIN_PIXEL_SCALE_AREA``): kept at the reference's pixels, a person a quarter of its area has to
move twice as far in metres to pass the motion gates and the non-rigid trial. The benchmark's
dancer at 256 px had its non-rigid part switched off (3.7 % of its Gaussians missing more than
1.5 px of flow a frame; the trial needs 5 %); following it down keeps the part and gains 0.6-0.9 dB
on novel views (novel poses: +0.5 dB on one subject draw, -0.5 dB on another). The floor: at half
the linear size the residual threshold is 0.75 px a frame, three times the optical flow's mean
error on a still subject at 256 px (0.25 px against the true flow); much lower, the gates would
read the flow's own error as motion.

``--set`` on any of these settings wins (the user said so), and ``--resume`` keeps the budget the
run started with.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

REFERENCE_AREA_PX = 20_000.0  # median person mask area of the benchmark's training frames at 512 px
MAX_SCALE = 4.0
# The pixel settings follow a smaller person down to a quarter of the reference's area (half its
# linear size); below it their thresholds would near the optical flow's own error (module docstring).
MIN_PIXEL_SCALE_AREA = 0.25
# Settings in pixels (at the reference size) that measure the body's motion or extent: x the linear ratio.
PIXEL_SETTINGS = (
    "densify.motion_floor_px",
    "densify.flow_consistency_px",
    "densify.residual_motion_px",
    "densify.motion_min_px",
    "crop_margin_px",
)
INVERSE_PIXEL_SETTINGS = ("loss.flow",)  # weights of residuals in pixels: / the linear ratio
SCALED = (
    "model.num_gaussians",
    "model.max_gaussians",
    "densify.flow_max_new",
    "iterations",
    *PIXEL_SETTINGS,
    *INVERSE_PIXEL_SETTINGS,
)


@dataclass(frozen=True)
class Budget:
    person_area_px: float  # median mask area over the training frames
    person_height_px: float  # median mask height
    scale: float  # the Gaussian budget's factor (the area ratio, clamped)
    steps_scale: float
    pixel_scale: float  # the pixel settings' factor (the linear size ratio, clamped to [0.5, 2])
    changes: dict  # setting -> new value (those the user did not set)

    def as_dict(self) -> dict:
        return {
            "person_area_px": self.person_area_px,
            "person_height_px": self.person_height_px,
            "reference_area_px": REFERENCE_AREA_PX,
            "gaussian_scale": self.scale,
            "steps_scale": self.steps_scale,
            "pixel_scale": self.pixel_scale,
            "changes": self.changes,
        }

    def describe(self) -> str:
        size = f"person {self.person_height_px:.0f} px tall, {self.person_area_px:.0f} px"
        if not self.changes:
            return f"{size}: the preset's budget"
        changed = ", ".join(
            f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in self.changes.items()
        )
        ratio = self.person_area_px / REFERENCE_AREA_PX
        return f"{size} ({ratio:.2f}x the presets' reference): budget scaled: {changed}"


def person_size(masks) -> tuple[float, float]:
    """(median area, median height) in pixels of the non-empty masks in ``masks`` (H, W uint8 arrays)."""
    areas, heights = [], []
    for mask in masks:
        if mask is None:
            continue
        on = np.asarray(mask) > 127
        if not on.any():
            continue
        rows = np.flatnonzero(on.any(axis=1))
        areas.append(float(on.sum()))
        heights.append(float(rows[-1] - rows[0] + 1))
    if not areas:
        return math.nan, math.nan
    return float(np.median(areas)), float(np.median(heights))


def sample_masks(dataset, count: int = 25):
    """The masks of ``count`` training views spread over ``dataset`` (a SequenceDataset)."""
    n = len(dataset)
    for i in sorted(set(np.linspace(0, n - 1, min(count, n)).round().astype(int).tolist())):
        yield dataset[i].mask


def scale_budget(config, masks, *, fixed: tuple[str, ...] = ()) -> tuple[object, Budget]:
    """``config`` with its budget scaled for the person in ``masks`` (module docstring); settings named
    in ``fixed`` (what the user set) are left alone. Returns the config and what was decided."""
    area, height = person_size(masks)
    if not math.isfinite(area):
        return config, Budget(area, height, 1.0, 1.0, 1.0, {})
    ratio = area / REFERENCE_AREA_PX
    scale = min(max(ratio, 1.0), MAX_SCALE)
    steps = min(math.sqrt(scale), 2.0)
    linear = math.sqrt(min(max(ratio, MIN_PIXEL_SCALE_AREA), MAX_SCALE))
    current = {key: setting_value(config, key) for key in SCALED}
    wanted = {
        "model.num_gaussians": round(current["model.num_gaussians"] * scale),
        "model.max_gaussians": round(current["model.max_gaussians"] * scale),
        "densify.flow_max_new": round(current["densify.flow_max_new"] * scale),
        "iterations": round(current["iterations"] * steps),
    }
    for key in PIXEL_SETTINGS:
        value = current[key] * linear
        wanted[key] = round(value) if isinstance(current[key], int) else value
    for key in INVERSE_PIXEL_SETTINGS:
        wanted[key] = current[key] / linear
    changes = {k: v for k, v in wanted.items() if k not in fixed and v != current[k]}
    budget = Budget(area, height, scale, steps, linear, changes)
    return (config.replace(**changes) if changes else config), budget


def setting_value(config, key: str):
    """The value of a dotted setting (``densify.region_px``) of ``config``."""
    value = config
    for name in key.split("."):
        value = getattr(value, name)
    return value
