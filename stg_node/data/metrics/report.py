"""Evaluating renders against ground truth under a named protocol that travels with the numbers.

A PSNR without its protocol cannot be compared with anything: papers on ZJU-MoCap differ in
whether they score the whole frame, the person's bounding box or the person's pixels, and which
SSIM window and LPIPS network they use. :class:`Evaluator` accumulates per-view metrics under
one protocol and :class:`EvaluationReport` carries a ``protocol`` string stating all of it.

Protocols (the mask is the ground-truth person mask):

- ``full``: the whole image (black background). This is what 3DGS-Avatar's ZJU-MoCap test
  scores (``render.py`` calls its evaluator without a mask).
- ``bbox``: both images cropped to the mask's bounding box (``cv2.boundingRect``), as the
  optional ``valid_mask`` path of 3DGS-Avatar's evaluator and Neural Body-style evaluations.
  LPIPS needs 32 px each way: a thinner box (a small person seen from the side) is grown about
  its centre to 32 px for LPIPS only (PSNR and SSIM keep the box).
- ``masked``: PSNR over mask pixels, SSIM averaged over mask pixels, LPIPS on the bounding box
  with both images black outside the mask.

Scores are means over views of per-view values.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from stg_node.data.metrics.image import psnr, ssim, to_tensor
from stg_node.data.metrics.lpips import LpipsUnavailable, get_lpips

PROTOCOLS = {
    "full": "whole {w}x{h} image, black background",
    "bbox": "crop to the bounding box of the ground-truth mask",
    "masked": "PSNR and SSIM over ground-truth mask pixels; LPIPS on the mask bounding box, black outside it",
}
SSIM_TEXT = {
    "gaussian": "SSIM 11x11 Gaussian window sigma 1.5 (scikit-image gaussian_weights, population covariance)",
    "uniform7": "SSIM 7x7 uniform window, sample covariance (scikit-image defaults)",
}


@dataclass(frozen=True)
class ViewMetrics:
    psnr: float
    ssim: float
    lpips: dict[str, float]


@dataclass
class EvaluationReport:
    protocol: str
    protocol_name: str
    views: int
    psnr: float
    ssim: float
    lpips: dict[str, float] = field(default_factory=dict)
    lpips_unavailable: dict[str, str] = field(default_factory=dict)

    def as_dict(self) -> dict:
        return {"protocol": self.protocol, "protocol_name": self.protocol_name, "views": self.views,
                "psnr": self.psnr, "ssim": self.ssim, "lpips": dict(self.lpips),
                "lpips_unavailable": dict(self.lpips_unavailable)}  # fmt: skip

    def __str__(self) -> str:
        parts = [f"PSNR {self.psnr:.2f} dB", f"SSIM {self.ssim:.4f}"]
        parts += [f"LPIPS-{net} {value:.4f}" for net, value in self.lpips.items()]
        parts += [f"LPIPS-{net} unavailable ({why})" for net, why in self.lpips_unavailable.items()]
        return f"{', '.join(parts)} over {self.views} views [protocol: {self.protocol}]"


def mask_bbox(mask: np.ndarray) -> tuple[int, int, int, int]:
    """(x, y, w, h) of the non-zero pixels, as cv2.boundingRect."""
    m = (np.asarray(mask) > 0).astype(np.uint8)
    if not m.any():
        raise ValueError("ground-truth mask is empty: no bounding box to evaluate on")
    return cv2.boundingRect(m)


LPIPS_MIN_PX = 32


def grown_box(box, least: int, width: int, height: int) -> tuple[int, int, int, int]:
    """``box`` (x, y, w, h) grown about its centre to at least ``least`` px each way, kept inside a
    ``width`` x ``height`` image (LPIPS on a thin person's box: a side view far away)."""
    x, y, w, h = box
    out = []
    for start, size, limit in ((x, w, width), (y, h, height)):
        grown = min(max(size, least), limit)
        start = min(max(start - (grown - size) // 2, 0), limit - grown)
        out += [start, grown]
    return out[0], out[2], out[1], out[3]


def _as_float_image(image) -> np.ndarray:
    return to_tensor(image).permute(1, 2, 0).numpy()


class Evaluator:
    """Accumulates PSNR / SSIM / LPIPS over views under one protocol."""

    def __init__(self, protocol: str = "full", lpips_nets: tuple[str, ...] = ("alex", "vgg"),
                 ssim_window: str = "gaussian", lpips_dir: Path | None = None):  # fmt: skip
        if protocol not in PROTOCOLS:
            raise ValueError(f"protocol must be one of {sorted(PROTOCOLS)}, got {protocol!r}")
        if ssim_window not in SSIM_TEXT:
            raise ValueError(f"ssim_window must be one of {sorted(SSIM_TEXT)}, got {ssim_window!r}")
        self.protocol_name = protocol
        self.ssim_window = ssim_window
        self.lpips_models = {}
        self.lpips_unavailable: dict[str, str] = {}
        for net in lpips_nets:
            try:
                self.lpips_models[net] = get_lpips(net, lpips_dir)
            except LpipsUnavailable as exc:
                self.lpips_unavailable[net] = str(exc)
        self.views: list[ViewMetrics] = []
        self._size: tuple[int, int] | None = None

    def add(self, pred, target, mask=None) -> ViewMetrics:
        """Score one view: ``pred``/``target`` (H, W, 3) in [0, 1] or uint8; ``mask`` (H, W) ground truth."""
        import torch

        a, b = _as_float_image(pred), _as_float_image(target)
        if a.shape != b.shape:
            raise ValueError(f"prediction {a.shape} and target {b.shape} differ in shape")
        self._size = (a.shape[1], a.shape[0])
        if self.protocol_name == "full":
            crop_a, crop_b, m = a, b, None
            lpips_a, lpips_b = a, b
        else:
            if mask is None:
                raise ValueError(f"protocol {self.protocol_name!r} needs the ground-truth mask")
            x, y, w, h = mask_bbox(mask)
            crop_a, crop_b = a[y : y + h, x : x + w], b[y : y + h, x : x + w]
            m = None
            if self.protocol_name == "masked":
                m = np.asarray(mask)[y : y + h, x : x + w] > 0
                crop_a = crop_a * m[..., None]
                crop_b = crop_b * m[..., None]
            lpips_a, lpips_b = crop_a, crop_b
            if min(w, h) < LPIPS_MIN_PX <= min(a.shape[:2]):  # LPIPS's five poolings need 32 px
                lx, ly, lw, lh = grown_box((x, y, w, h), LPIPS_MIN_PX, a.shape[1], a.shape[0])
                lpips_a, lpips_b = a[ly : ly + lh, lx : lx + lw], b[ly : ly + lh, lx : lx + lw]
                if self.protocol_name == "masked":
                    lm = np.asarray(mask)[ly : ly + lh, lx : lx + lw, None] > 0
                    lpips_a, lpips_b = lpips_a * lm, lpips_b * lm
        view_psnr = psnr(crop_a, crop_b, mask=m)
        view_ssim = ssim(crop_a, crop_b, mask=m, window=self.ssim_window)
        scores = {}
        if self.lpips_models:
            ta = torch.from_numpy(np.ascontiguousarray(lpips_a.transpose(2, 0, 1))).float()[None]
            tb = torch.from_numpy(np.ascontiguousarray(lpips_b.transpose(2, 0, 1))).float()[None]
            with torch.no_grad():
                for net, model in self.lpips_models.items():
                    scores[net] = float(model(ta, tb)[0])
        view = ViewMetrics(view_psnr, view_ssim, scores)
        self.views.append(view)
        return view

    @property
    def protocol(self) -> str:
        w, h = self._size or (0, 0)
        region = PROTOCOLS[self.protocol_name].format(w=w, h=h)
        nets = "/".join(self.lpips_models) or "none"
        return (f"{self.protocol_name}: {region}; PSNR (data range 1); {SSIM_TEXT[self.ssim_window]}; "
                f"LPIPS v0.1 ({nets}) on [0,1] RGB; mean over views")  # fmt: skip

    def report(self) -> EvaluationReport:
        if not self.views:
            raise ValueError("no views evaluated")
        finite = [v.psnr for v in self.views]
        mean_psnr = float(np.mean(finite)) if all(math.isfinite(p) for p in finite) else math.inf
        lpips = {net: float(np.mean([v.lpips[net] for v in self.views])) for net in self.lpips_models}
        mean_ssim = float(np.mean([v.ssim for v in self.views]))
        return EvaluationReport(protocol=self.protocol, protocol_name=self.protocol_name, views=len(self.views),  # noqa: E501
                                psnr=mean_psnr, ssim=mean_ssim, lpips=lpips,
                                lpips_unavailable=dict(self.lpips_unavailable))  # fmt: skip
