"""Image metrics for judging renders: PSNR, SSIM, LPIPS, and evaluation protocols that state themselves.

- :mod:`.image`: PSNR and SSIM (11x11 Gaussian window, sigma 1.5, as scikit-image with
  ``gaussian_weights=True, use_sample_covariance=False``), full-image or masked.
- :mod:`.lpips`: LPIPS v0.1 (AlexNet and VGG16) in plain torch, from weights installed offline
  by :mod:`.lpips_weights`; never a substitute number when the weights are missing.
- :mod:`.report`: one call that evaluates a render against ground truth under a named protocol
  (full image, mask bounding box, masked) and returns numbers with the protocol written beside them.
"""

from __future__ import annotations

from stg_node.data.metrics.image import psnr, ssim
from stg_node.data.metrics.report import PROTOCOLS, EvaluationReport, Evaluator

__all__ = ["psnr", "ssim", "Evaluator", "EvaluationReport", "PROTOCOLS"]
