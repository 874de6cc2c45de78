#!/usr/bin/env python3
"""What the non-rigid trial's first test reads, against the truth (docs/BENCHMARKS.md, issue 22).

Trains a synthetic subject with the fast preset (scaled) up to the trial's decision, then compares,
over the body's pixels of the training pairs (the flow valid, the render opaque): the optical flow,
the true flow, the model's rendered motion and its rigid part's. Prints the Gaussians' missed-flow
statistic, the moving fraction and the decision the trainer takes.

    python tools/trial_evidence.py --subject still --scale medium [--set KEY=VALUE ...]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import tradeoff  # noqa: E402


@torch.no_grad()
def rendered_motion(model, body, next_body, u, u_next, camera, backend):
    """(h, w, 2) alpha-normalised projected motion to the next frame, and the (h, w) alpha."""
    from stg_node.avatar.model import render

    posed = model.pose(body, u, camera.center)
    nxt = model.posed_means(model.bones(next_body), u_next)
    if posed.index is not None:
        nxt = nxt[posed.index]
    extra = camera.project(nxt) - camera.project(posed.means)
    image, alpha, _ = render(posed, camera, background=0.0, backend=backend, extra_channels=extra)
    return image[..., 3:5] / alpha.clamp_min(0.5), alpha[..., 0]


def main() -> None:
    import bench_nonrigid

    from stg_node.avatar import Trainer, nonrigid, preset
    from stg_node.avatar.config import apply_settings
    from stg_node.avatar.data_spec import DataSpec
    from stg_node.avatar.model import Camera3
    from stg_node.body import load_body_model
    from stg_node.data.synth.true_flow import benchmark_true_flow
    from stg_node.data.synth.writer import read_metadata
    from stg_node.threads import configure_threads

    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--subject", default="still", choices=sorted(tradeoff.SUBJECTS))
    parser.add_argument("--scale", default="medium", choices=("medium", "full"))
    parser.add_argument("--data-cache", type=Path, default=Path("runs/trial_evidence"))
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = parser.parse_args()
    configure_threads(None)
    scale = bench_nonrigid.SCALES[args.scale]
    folder = tradeoff.ensure_subject(args.data_cache, args.subject, scale)
    config = apply_settings(tradeoff.scaled(preset("fast"), scale), args.set)
    started = time.perf_counter()
    trainer = Trainer(config, seed=0)
    trainer.add_frames(DataSpec(str(folder), "synthetic", size=scale.size).open("train"))
    while trainer.iteration < config.nonrigid_decide_iter:
        trainer.step()
    threshold = config.densify.residual_motion_px
    resid = trainer.densify_state["resid_w"]
    seen = resid > 0
    quartiles = torch.quantile(resid[seen], torch.tensor([0.25, 0.5, 0.75, 0.9])).tolist()
    print(
        f"# {args.subject}, {scale.size} px, trained {trainer.iteration} steps "
        f"in {time.perf_counter() - started:.0f} s"
    )
    print("missed flow per Gaussian, quartiles / 90th: " + " ".join(f"{q:.2f}" for q in quartiles) + " px")

    model = trainer.model
    rigid, _ = nonrigid.rigid_part(model)
    meta = read_metadata(folder)
    faces = load_body_model().faces.cpu().numpy()
    cuts = tuple((meta.get("held_out") or {}).get("cuts", ()))
    sums: dict[str, list[float]] = {}

    def add(name, err):
        entry = sums.setdefault(name, [0.0, 0.0, 0.0])
        entry[0] += float(err.sum())
        entry[1] += float(err.numel())
        entry[2] += float((err > threshold).sum())

    for stored in trainer.store.frames:
        if stored.flow is None or stored.next_smpl is None:
            continue
        if nonrigid.held_out(stored.frame.index, config.nonrigid_holdout_every):
            continue
        x0, y0, w, h = stored.crop
        camera = Camera3.from_camera(stored.frame.camera, stored.crop, trainer.device)
        body = trainer.body_state(stored.frame)
        next_body = trainer.body_state(stored.frame, smpl=stored.next_smpl)
        u, u_next = model.time_axis(stored.frame.time), model.time_axis(stored.next_time)
        full, alpha = rendered_motion(model, body, next_body, u, u_next, camera, trainer.backend)
        rigid_flow, _ = rendered_motion(rigid, body, next_body, u, u_next, camera, trainer.backend)
        truth = benchmark_true_flow(
            folder, stored.frame.index, stored.frame.camera, faces, int(meta["num_frames"]), cuts=cuts
        )
        true = torch.from_numpy(truth.flow[y0 : y0 + h, x0 : x0 + w]).float()
        flow = torch.from_numpy(stored.flow.forward[y0 : y0 + h, x0 : x0 + w]).float()
        valid = torch.from_numpy(stored.flow.valid_forward[y0 : y0 + h, x0 : x0 + w])
        region = valid & torch.from_numpy(truth.covered[y0 : y0 + h, x0 : x0 + w]) & (alpha > 0.95)
        for name, a, b in (
            ("flow vs true flow", flow, true),
            ("full model's motion vs true flow", full, true),
            ("rigid part's motion vs true flow", rigid_flow, true),
            ("flow vs full model's motion (the test)", flow, full),
            ("flow vs rigid part's motion", flow, rigid_flow),
            ("full model's vs rigid part's motion", full, rigid_flow),
        ):
            add(name, (a - b).norm(dim=-1)[region])
    print(f"| compared (pixels) | mean | share above {threshold:g} px |")
    print("|---|---|---|")
    for name, (total, count, above) in sums.items():
        print(f"| {name} | {total / max(count, 1):.2f} px | {100 * above / max(count, 1):.1f} % |")
    trainer._decide()
    decision = trainer.decision
    print(f"decision: {decision.chose}: {decision.why}")


if __name__ == "__main__":
    main()
