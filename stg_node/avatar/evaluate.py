"""Scoring a trained avatar on a test split (novel view, novel pose) under a named metric protocol.

Protocol: every view of the split is rendered at the dataset's size on a black background and
compared with the masked ground truth over the whole image (``full``: 3DGS-Avatar's ZJU-MoCap
evaluation; docs/METRICS.md), PSNR/SSIM (11x11 Gaussian window) and LPIPS (alex) averaged over
views. Novel-view frames are training frames seen from other cameras: they are rendered at their
own time with their (refined) training pose. Novel-pose frames take the time code of the nearest
training pose (timecode.py).
"""

from __future__ import annotations

import numpy as np

from stg_node.avatar.renderer import AvatarRenderer
from stg_node.progress import progress


def evaluate_split(
    renderer: AvatarRenderer,
    dataset,
    *,
    split: str,
    protocol: str = "full",
    lpips_nets: tuple[str, ...] = ("alex",),
    body_states=None,
    show_progress: bool = True,
    keep_images: int = 0,
) -> tuple[dict, list]:
    """Metrics over ``dataset`` (a SequenceDataset split); ``body_states``: frame -> BodyState override."""
    from stg_node.data.metrics import Evaluator

    evaluator = Evaluator(protocol, lpips_nets=lpips_nets)
    kept = []
    times = []
    for sample in progress(dataset, desc=f"eval {split}", unit="view", enabled=show_progress):
        image = sample.image
        if sample.mask is not None:
            image = np.where(sample.mask[..., None] > 127, image, 0).astype(np.uint8)
        time_s = sample.time if split != "novel_pose" else None
        body = body_states.get(sample.index) if body_states else None
        out = renderer.render(sample.camera, sample.smpl, time_s, body=body)
        times.append(out.render_ms)
        evaluator.add(out.image, image, sample.mask)
        if len(kept) < keep_images:
            kept.append((sample.index, sample.camera.name, out.image, image))
    report = evaluator.report().as_dict()
    report["render_ms_mean"] = float(np.mean(times)) if times else 0.0
    return report, kept
