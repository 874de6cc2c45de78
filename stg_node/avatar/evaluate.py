"""Scoring a trained avatar on a test split (novel view, novel pose) under a named metric protocol.

Protocol: every view of the split is rendered at the dataset's size on a black background and
compared with the masked ground truth over the whole image (``full``: 3DGS-Avatar's ZJU-MoCap
evaluation; docs/METRICS.md), PSNR/SSIM (11x11 Gaussian window) and LPIPS (alex) averaged over
views. Novel-view frames are training frames seen from other cameras: they are rendered at their
own time with their (refined) training pose. Novel-pose frames take the time code of the nearest
training pose (timecode.py).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from stg_node.avatar.loading import corrected
from stg_node.avatar.renderer import AvatarRenderer
from stg_node.progress import progress


def evaluate_split(
    renderer: AvatarRenderer,
    dataset,
    *,
    split: str,
    protocol: str = "full",
    lpips_nets: tuple[str, ...] = ("alex",),
    pose_corrections: dict | None = None,
    show_progress: bool = True,
    keep_images: int = 0,
    regions=None,
) -> tuple[dict, list]:
    """Metrics over ``dataset`` (a SequenceDataset split); ``pose_corrections``: frame -> learned
    (75,) correction of the training pose (novel views of training frames).

    ``regions``: optional ``(frame, camera) -> {name: (H, W) bool}`` (e.g. the synthetic benchmark's
    body parts, stg_node.data.synth.body_parts); the report then has ``regions``: name -> {psnr,
    pixels}, squared errors pooled over the split's views per region.

    Views with a true mask also give ``spill`` (stg_node.data.metrics.spill): the rendered alpha
    beyond the true silhouette, per region when ``regions`` is given (streaks off a limb).
    """
    from stg_node.data.metrics import Evaluator
    from stg_node.data.metrics.spill import SpillScores
    from stg_node.data.synth.body_parts import RegionScores

    spill = SpillScores()
    evaluator = Evaluator(protocol, lpips_nets=lpips_nets)
    region_scores = RegionScores() if regions is not None else None
    kept = []
    times = []
    for sample in progress(dataset, desc=f"eval {split}", unit="view", enabled=show_progress):
        image = sample.image
        if sample.mask is not None:
            image = np.where(sample.mask[..., None] > 127, image, 0).astype(np.uint8)
        time_s = sample.time if split != "novel_pose" else None
        smpl = corrected(sample.smpl, (pose_corrections or {}).get(sample.index))
        out = renderer.render(sample.camera, smpl, time_s)
        times.append(out.render_ms)
        evaluator.add(out.image, image, sample.mask)
        view_regions = regions(sample.index, sample.camera) if regions is not None else None
        if region_scores is not None:
            region_scores.add(out.image, image, view_regions)
        if sample.mask is not None:
            spill.add(out.alpha, sample.mask, view_regions)
        if len(kept) < keep_images:
            kept.append((sample.index, sample.camera.name, out.image, image))
    report = evaluator.report().as_dict()
    report["render_ms_mean"] = float(np.mean(times)) if times else 0.0
    if region_scores is not None:
        report["regions"] = region_scores.report()
    if spill.views:
        report["spill"] = spill.report()
    return report, kept


def evaluate_trainer(
    trainer, data: str | Path, *, split: str = "novel_view", lpips_net: str | None = "alex"
) -> dict:
    """A live trainer's model scored on a dataset's held-out cameras (what the online trainer node
    reports at the end of the demo): the dataset at ``data`` (an stg-synth folder, else ZJU-MoCap),
    loaded at the size of the frames the trainer learnt from, its ``split``; the training poses
    with their learned corrections. Returns ``split``, ``views``, ``psnr``, ``ssim``, ``lpips``."""
    from stg_node.avatar.data_spec import DataSpec
    from stg_node.avatar.renderer import AvatarRenderer

    if trainer.model is None or not len(trainer.store):
        raise ValueError("the trainer has no model yet: nothing to evaluate")
    root = Path(data)
    fmt = "synthetic" if (root / "synth.json").is_file() else "zju"
    camera = trainer.store.frames[0].frame.camera
    size = max(int(camera.width), int(camera.height))
    dataset = DataSpec(str(root.resolve()), fmt, size=size).open(split)
    corrections = {}
    if trainer.pose_deltas is not None:
        deltas = trainer.pose_deltas.detach().cpu().numpy()
        corrections = {frame: deltas[slot] for frame, slot in trainer.pose_slots.items()}
    renderer = AvatarRenderer(trainer.model, backend=trainer.backend)
    nets = (lpips_net,) if lpips_net else ()
    report, _ = evaluate_split(
        renderer,
        dataset,
        split=split,
        lpips_nets=nets,
        pose_corrections=corrections if split == "novel_view" else None,
        show_progress=False,
    )
    lpips = report["lpips"].get(lpips_net) if lpips_net else None
    return {
        "split": split,
        "views": report["views"],
        "psnr": report["psnr"],
        "ssim": report["ssim"],
        "lpips": lpips,
    }


def save_comparison(views: list, path: Path) -> Path:
    """Rendered (top) over ground truth (bottom) for a few views, cropped to the person, as a PNG."""
    from PIL import Image

    tiles = []
    for _index, _camera, pred, gt in views:
        mask = (gt.sum(-1) > 0) | (pred.sum(-1) > 0)
        if mask.any():
            rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
            y0, y1 = max(rows[0] - 8, 0), min(rows[-1] + 9, gt.shape[0])
            x0, x1 = max(cols[0] - 8, 0), min(cols[-1] + 9, gt.shape[1])
        else:
            y0, y1, x0, x1 = 0, gt.shape[0], 0, gt.shape[1]
        tiles.append(np.concatenate([pred[y0:y1, x0:x1], gt[y0:y1, x0:x1]], axis=0))
    height = max(t.shape[0] for t in tiles)
    padded = [np.pad(t, ((0, height - t.shape[0]), (0, 4), (0, 0))) for t in tiles]
    Image.fromarray(np.concatenate(padded, axis=1)).save(path)
    return Path(path)
