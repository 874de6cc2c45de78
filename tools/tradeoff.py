"""The speed/accuracy trade, measured: every preset and ablation of STG-Avatar on the synthetic benchmark.

    python tools/tradeoff.py            # the full grid (hours on a CPU): docs/BENCHMARKS.md + the Pareto PNG
    python tools/tradeoff.py --quick    # a reduced grid in minutes (tiny images, few iterations), into --out
    python tools/tradeoff.py --list     # the configurations, without running anything

What runs. Synthetic subjects are generated deterministically (``stg_node.data.synth.generate``,
seed 0) into ``--data-cache``: ``dance`` (fast, garment dynamics: the main subject), ``still``
(standing, breathing: the model-economy check) and the default ``mixed``; 125 frames at
512 x 512, so frames 0-99 train (camera 1) and 100-124 are held-out poses; 8 held-out cameras
render every 10th frame. The benchmark conditions (:data:`SUBJECTS`, :data:`CONDITIONS`) train on
the same 100 frames under a light fixed in the room, flat light or three coloured lights, and
hold out orientations (a turn) or motions (docs/SYNTH.md); each row also reports its novel-pose
PSNR per body part and the held-out frames' distances from training. Every configuration trains
with :class:`stg_node.avatar.Trainer` through the public API only (``preset(...)``,
``TrainConfig.replace`` with dotted keys), is saved as a run folder ``stg-eval`` / ``stg-render``
open (``--out/runs/NAME``), and is scored:

- training time (optimisation steps only; loading frames and optical flow, computed once per
  subject, are reported apart) and it/s;
- render FPS at the dataset's size (pose + colour + splat, median of repeated renders of
  held-out views) on the CPU, and on CUDA when ``torch.cuda.is_available()``; the same renders
  with the zero-motion skip turned off (the skip's gain);
- Gaussians, the fraction (and count) with active motion terms, model size;
- PSNR / SSIM / LPIPS on the novel-view and novel-pose splits (``stg-eval``'s protocol:
  :func:`stg_node.avatar.evaluate.evaluate_split`);
- PSNR on the fast-moving regions only: pixels whose true motion (the benchmark's ground-truth
  vertices of this frame and the next, projected into the evaluation camera and rasterized:
  :mod:`stg_node.data.synth.true_flow`) exceeds 5 px per frame at 512 x 512 (scaled with the
  image width), the squared errors of those pixels pooled over the split's views;
- PSNR on the garment's pixels only: where the true surface seen is the loose cloth
  (:mod:`stg_node.data.synth.garment_truth`), pooled the same way; and the fraction of the
  Gaussians with active motion terms that lie on the garment.

Each configuration's result is kept in ``--out/results/NAME.json`` with a fingerprint of its
settings and data: a re-run (or a run resumed after Ctrl-C) skips what is already measured;
``--fresh`` generates the subjects and measures everything again. The report
(:mod:`tradeoff_report`) goes between marker comments in ``--docs`` (re-runs replace the
section) with the command line and the machine, beside the Pareto plot ``--plot``.

``--quick`` shrinks everything (96 x 96 images, 30 frames, 2 held-out cameras, iterations / 25,
Gaussian budgets / 10, every iteration-valued schedule scaled alike, pixel-valued thresholds with
the image) so the grid runs in minutes;
its numbers show the pipeline works, not how the method performs. ``--scale mid`` sits between
(256 x 256 images, the full 125 frames, 4 held-out cameras, iterations / 3, Gaussian budgets / 2):
a few benchmark conditions in well under an hour on a shared 2-core machine, for comparing
configurations with each other (not with the full grid's numbers).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import hashlib
import json
import logging
import math
import os
import platform
import statistics
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(Path(__file__).resolve().parent))

log = logging.getLogger("tradeoff")

RESULT_VERSION = 2  # 2: garment PSNR, active motion on the garment, the non-rigid choice
LPIPS_NET = "alex"


@dataclass(frozen=True)
class Subject:
    """A synthetic subject: what ``stg-synth`` generates beyond the scale's sizes (docs/SYNTH.md).

    ``held_out_factor`` lengthens the held-out tail (n_train stays the scale's), for conditions
    that play several held-out motions one after another.
    """

    motion: str
    shading: str = "lambert"
    test_motion: str | None = None
    train_yaw_deg: float | None = None
    test_yaw_deg: float | None = None
    held_out_factor: int = 1
    title: str = ""
    self_shadow: bool = False  # the body occludes its own light (stg-synth --self-shadow)

    def synth_options(self) -> dict:
        return {
            "motion": self.motion,
            "shading": self.shading,
            "self_shadow": self.self_shadow,
            "test_motion": self.test_motion,
            "train_yaw_deg": self.train_yaw_deg,
            "test_yaw_deg": self.test_yaw_deg,
        }


# The subjects (benchmark conditions) rows train on, by name. The first three have a light that
# turns with the body and a held-out tail that continues the training motion; the conditions
# below separate geometry (poses never seen: another motion) from shading (a light fixed in the
# room, orientations never seen: a turn held out), each against flat light.
SUBJECTS = {
    "dance": Subject("dance", title="dance, light turning with the body"),
    "still": Subject("still", title="still, light turning with the body"),
    "mixed": Subject("mixed", title="mixed, light turning with the body"),
    "room_turn_held_out": Subject(
        "turn",
        "room",
        train_yaw_deg=60.0,
        test_yaw_deg=150.0,
        title="room light, turn held out (train facing the camera +-30 deg, test turned 150 deg)",
    ),
    "flat_turn_held_out": Subject(
        "turn",
        "none",
        train_yaw_deg=60.0,
        test_yaw_deg=150.0,
        title="flat light, turn held out (as above, albedo only)",
    ),
    "env_turn_held_out": Subject(
        "turn",
        "environment",
        train_yaw_deg=60.0,
        test_yaw_deg=150.0,
        title="three coloured room lights, turn held out",
    ),
    "room_facing": Subject(
        "turn",
        "room",
        train_yaw_deg=60.0,
        title="room light, never turning (train and test facing the camera +-30 deg)",
    ),
    # A near-still subject that never turns (issue 22): from one camera its back is never seen.
    "still_facing": Subject(
        "still",
        train_yaw_deg=60.0,
        title="still, never turning (training frames face the camera +-30 deg): its back never seen",
    ),
    # The issue's words taken literally (issue 22, round 9): standing and breathing, facing the camera,
    # no turn at all (`still` itself turns a full revolution: the coverage rule's turntable).
    "still_standing": Subject(
        "still",
        train_yaw_deg=0.0,
        title="still, standing (facing the camera, no turn): breathing and small head turns only",
    ),
    "room_new_motions": Subject(
        "turn",
        "room",
        test_motion="wave,dance,crouch,arms_up",
        held_out_factor=4,
        title="room light, full turn in training, held-out motions wave / dance / crouch / arms up",
    ),
    "flat_reach": Subject(
        "turn",
        "none",
        test_motion="reach",
        held_out_factor=4,
        title="flat light, full turn in training, held out: arms folded far overhead (reach)",
    ),
    # What the body casts on itself (issue 21's ambient-occlusion term): trained on a full turn
    # (every side seen under the room's light), held out dancing and crouching, arms across and in
    # front of the torso, in poses the turn never showed.
    "room_self_shadow": Subject(
        "turn",
        "room",
        test_motion="dance,crouch",
        held_out_factor=2,
        self_shadow=True,
        title="room light with self-shadowing, full turn in training, held out: dance / crouch",
    ),
}


# --- the scale of a run ------------------------------------------------------------------------
@dataclass(frozen=True)
class Scale:
    """Data and schedule sizes: the full grid or the quick one."""

    name: str
    size: int  # square image size, generated and evaluated
    frames: int  # frames generated (80 % train; subjects with a longer held-out tail add to it)
    views: int  # held-out cameras
    view_every: int  # held-out cameras render every K-th frame
    supersample: int
    iteration_factor: float  # x every iteration count and iteration-valued schedule
    gaussian_factor: float  # x every Gaussian budget
    render_repeats: int  # timed renders per view for the FPS figures
    render_views: int  # views the FPS is timed on

    @property
    def fast_threshold_px(self) -> float:
        from stg_node.data.synth.true_flow import FAST_FLOW_PX_AT_512

        return FAST_FLOW_PX_AT_512 * self.size / 512.0


FULL = Scale("full", 512, 125, 8, 10, 2, 1.0, 1.0, 5, 4)
QUICK = Scale("quick", 96, 30, 2, 6, 1, 1 / 25, 1 / 10, 2, 2)
MID = Scale("mid", 256, 125, 4, 10, 1, 1 / 3, 1 / 2, 2, 2)
SCALES = {s.name: s for s in (FULL, MID, QUICK)}

# Settings counted in iterations (scaled by Scale.iteration_factor) and in Gaussians
# (Scale.gaussian_factor). TrainConfig.replace raises on a name that no longer exists, so a
# renamed setting fails loudly here rather than silently keeping its full-size value.
ITERATION_KEYS = (
    "iterations",
    "loss.warmup_iters",
    "densify.start_iter",
    "densify.interval",
    "densify.gate_start_iter",
    "densify.flow_interval",
    "sh_increase_every",
    "checkpoint_every",
    "log_every",
    "nonrigid_decide_iter",
    "normal_decide_iter",
    "densify.unseen_after_views",
)
GAUSSIAN_KEYS = ("model.num_gaussians", "model.max_gaussians", "densify.flow_max_new")
# Settings in pixels of the 512 x 512 benchmark (scaled with the image width), and whether integer.
PIXEL_KEYS = {
    "densify.motion_floor_px": False,
    "densify.region_px": True,
    "densify.flow_consistency_px": False,
    "densify.residual_motion_px": False,
    "densify.motion_min_px": False,
    "crop_margin_px": True,
}


def scaled(config, scale: Scale):
    """``config`` with its iteration counts, Gaussian budgets and pixel sizes scaled to ``scale``."""
    from stg_node.avatar.budget import setting_value

    pixel_factor = scale.size / 512.0
    if scale.iteration_factor == 1.0 and scale.gaussian_factor == 1.0 and pixel_factor == 1.0:
        return config

    def known(keys):  # a baseline tree's config (tools/baseline.py) may predate a key: it has none to scale
        for key in keys:
            try:
                yield key, setting_value(config, key)
            except AttributeError:
                continue

    changes = {}
    for key, value in known(ITERATION_KEYS):
        changes[key] = max(1, round(value * scale.iteration_factor))
    for key, value in known(GAUSSIAN_KEYS):
        changes[key] = max(1, round(value * scale.gaussian_factor))
    for key, value in known(PIXEL_KEYS):
        changes[key] = max(2, round(value * pixel_factor)) if PIXEL_KEYS[key] else value * pixel_factor
    return config.replace(**changes)


# --- the grid ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class Configuration:
    """One row of the table: a preset, possibly with switches flipped, trained on one subject."""

    name: str  # file names and --only
    label: str  # the table's first column
    group: str  # "preset", "ablation", "economy", "subject", "condition"
    subject: str  # a key of SUBJECTS
    preset: str
    changes: dict = field(default_factory=dict)  # dotted TrainConfig keys -> values
    alias_of: str | None = None  # the same run as another row (shown again for the reader)

    def config(self, scale: Scale):
        from stg_node.avatar import preset

        return scaled(preset(self.preset).replace(**self.changes), scale)


def grid(base: str = "fast") -> list[Configuration]:
    """Every configuration: the presets, the ablations on ``base``, the still subject, the mixed one."""
    from stg_node.avatar import PRESETS, preset

    if base not in PRESETS:
        raise ValueError(f"--base must be one of {', '.join(PRESETS)}, got {base!r}")
    b = preset(base)
    n_p, n_q, n_b = b.model.motion_order, b.model.rotation_order, b.model.motion_basis
    budget = (b.model.num_gaussians, b.model.max_gaussians)
    full = f"preset_{base}"
    rows = [Configuration(f"preset_{p}", f"{p} (preset)", "preset", "dance", p) for p in PRESETS]
    # The paper's per-Gaussian polynomials (STG), as the previous default ran them: every ablation
    # of the motion's polynomial order (n_p) is of this model.
    poly = {"model.motion_basis": 0, "densify.motion_signal": "flow", "nonrigid": "on"}
    ablations = [
        Configuration(
            f"full_{base}",
            f"full model (= {base}: {n_b} shared motion bases, n_q={n_q}, MLP, flow-guided, the trial)",
            "ablation",
            "dance",
            base,
            alias_of=full,
        ),
        Configuration(
            "polynomial",
            f"per-Gaussian polynomials (STG: n_p={n_p}, n_q={n_q}), local rigidity, no trial",
            "ablation",
            "dance",
            base,
            poly,
        ),
        Configuration(
            "forced_on",
            "non-rigid part forced on (nonrigid=on: no trial)",
            "ablation",
            "dance",
            base,
            {"nonrigid": "on"},
        ),
        Configuration(
            "lbs_only",
            "LBS only (no spacetime, no flow-guided densification)",
            "ablation",
            "dance",
            base,
            {"model.spacetime": False, "densify.flow_guided": False},
        ),
        Configuration(
            "no_flow_densify",
            "no flow-guided densification",
            "ablation",
            "dance",
            base,
            {"densify.flow_guided": False},
        ),
        Configuration(
            "sh_color", "SH colour instead of the MLP", "ablation", "dance", base, {"model.color": "sh"}
        ),
    ]
    for symbol, key, orders, current, same, extra in (
        ("n_p", "model.motion_order", range(4), n_p, "polynomial", poly),
        ("n_q", "model.rotation_order", range(2), n_q, full, {}),
    ):
        for order in orders:
            name, label = f"{symbol}{order}", f"{symbol} = {order}" + (" (polynomials)" if extra else "")
            if order == current:  # the same run as another row, shown again in its series
                ablations.append(
                    Configuration(name, f"{label} (= {same})", "ablation", "dance", base, alias_of=same)
                )
            else:
                changes = extra | {key: order}
                ablations.append(Configuration(name, label, "ablation", "dance", base, changes))
    for name, factor, word in (("budget_half", 0.5, "halved"), ("budget_double", 2.0, "doubled")):
        changes = {
            "model.num_gaussians": round(budget[0] * factor),
            "model.max_gaussians": round(budget[1] * factor),
        }
        label = f"Gaussian budget {word} (initial and maximum x{factor:g})"
        ablations.append(Configuration(name, label, "ablation", "dance", base, changes))
    ablations.append(
        Configuration(
            "baked", "colour baked, as before shading (BAKED)", "ablation", "dance", base, dict(BAKED)
        )
    )
    rows += ablations
    rows.append(Configuration(f"still_{base}", f"still subject, {base} preset", "economy", "still", base))
    rows.append(Configuration(f"mixed_{base}", f"mixed subject, {base} preset", "subject", "mixed", base))
    rows.append(
        Configuration(
            "mixed_lbs_only",
            "mixed subject, LBS only",
            "subject",
            "mixed",
            base,
            {"model.spacetime": False, "densify.flow_guided": False},
        )
    )
    rows += condition_rows(base)
    return rows


CONDITIONS = (
    "room_turn_held_out",
    "flat_turn_held_out",
    "env_turn_held_out",
    "room_facing",
    "room_new_motions",
    "flat_reach",
    "room_self_shadow",
)
# The colour as it was before shading (issue 21): the light baked in, spherical initial Gaussians,
# no cap on their scale ratio, no isometry term, no joint shrink.
BAKED = {
    "model.shading": False,
    "model.init_flatness": 1.0,
    "model.max_scale_ratio": 0.0,
    "loss.isometry": 0.0,
    "model.joint_shrink": False,
}
# Each of shading's parts switched off alone, on the room-light subject with a held-out turn.
SHADING_ABLATIONS = (
    (
        "no_shading",
        "no shading (the light baked into the colour; discs, cap, isometry kept)",
        {"model.shading": False},
    ),
    ("no_scale_cap", "no cap on the scale ratio", {"model.max_scale_ratio": 0.0}),
    ("no_isometry", "no as-isometric-as-possible term", {"loss.isometry": 0.0}),
    ("sphere_init", "spherical initial Gaussians instead of discs", {"model.init_flatness": 1.0}),
    ("sh_light", "free second-order SH light instead of distant lights", {"model.light_model": "sh"}),
)


# The joint shrink (rigid.joint_shrink, issue 21's streaks) switched off, on the held-out reach
# (joints folded far beyond training) and on the room light's held-out turn (novel views must not
# pay for it); and both with the non-rigid part off, so that its trial (on or off by a margin)
# cannot decide the comparison.
NEEDLE_ABLATIONS = (
    ("flat_reach", "no_joint_shrink", "no joint shrink", {"model.joint_shrink": False}),
    ("flat_reach", "rigid", "non-rigid part off", {"nonrigid": "off"}),
    (
        "flat_reach",
        "rigid_no_joint_shrink",
        "non-rigid part off, no joint shrink",
        {"nonrigid": "off", "model.joint_shrink": False},
    ),
    ("room_turn_held_out", "no_joint_shrink", "no joint shrink", {"model.joint_shrink": False}),
)
# The body's ambient-occlusion term (occlusion.py, on in the presets) switched off, on the subject
# that casts shadows on itself and on the conditions without self-shadowing (it must not cost there).
NO_OCCLUSION = {"model.occlusion": False}
OCCLUSION_ABLATIONS = (
    ("room_self_shadow", "no_occlusion", "without the ambient-occlusion term", NO_OCCLUSION),
    ("room_turn_held_out", "no_occlusion", "without the ambient-occlusion term", NO_OCCLUSION),
    ("flat_turn_held_out", "no_occlusion", "without the ambient-occlusion term", NO_OCCLUSION),
)


# Shading normals with the side the disc initialisation gave them in training
# (model.normal_sign=outward, shading.outward_normals) instead of facing the training camera (the
# default), on each lit condition and on flat light.
OUTWARD_NORMALS = {"model.normal_sign": "outward"}
# The presets decide the sign from the learned light ("auto", normal_trial.py); these rows force
# either one.
CAMERA_NORMALS = {"model.normal_sign": "camera"}
NORMAL_SIGN_ABLATIONS = tuple(
    (subject, suffix, label, changes)
    for subject in (
        "room_turn_held_out",
        "env_turn_held_out",
        "flat_turn_held_out",
        "room_facing",
        "room_new_motions",
        "room_self_shadow",
    )
    for suffix, label, changes in (
        ("outward_normals", "outward normals in training", OUTWARD_NORMALS),
        ("camera_normals", "normals facing the camera in training", CAMERA_NORMALS),
    )
)


def condition_rows(base: str) -> list[Configuration]:
    """The ``base`` preset on each benchmark condition that separates geometry from shading, the colour
    before shading (``baked``) on each, and shading's ablations on the room-light held-out turn."""
    rows = []
    for name in CONDITIONS:
        title = SUBJECTS[name].title
        rows.append(Configuration(f"{name}_{base}", f"{title}, {base} preset", "condition", name, base))
        rows.append(
            Configuration(
                f"{name}_baked",
                f"{title}, {base} preset, colour baked (before shading)",
                "condition",
                name,
                base,
                dict(BAKED),
            )
        )
    for suffix, label, changes in SHADING_ABLATIONS:
        rows.append(
            Configuration(
                f"room_turn_held_out_{suffix}",
                f"room light, turn held out: {label}",
                "shading",
                "room_turn_held_out",
                base,
                changes,
            )
        )
    for group, ablations in (
        ("needles", NEEDLE_ABLATIONS),
        ("occlusion", OCCLUSION_ABLATIONS),
        ("normal_sign", NORMAL_SIGN_ABLATIONS),
    ):
        for subject, suffix, label, changes in ablations:
            rows.append(
                Configuration(
                    f"{subject}_{suffix}",
                    f"{SUBJECTS[subject].title}: {label}",
                    group,
                    subject,
                    base,
                    changes,
                )
            )
    return rows


# --- data ---------------------------------------------------------------------------------------
def subject_folder(cache: Path, subject: str, scale: Scale, seed: int) -> Path:
    return cache / f"{subject}_{scale.frames}f_{scale.size}px_v{scale.views}e{scale.view_every}_s{seed}"


def subject_frames(subject: str, scale: Scale) -> tuple[int, float]:
    """(frames, train fraction) of ``subject`` at ``scale``: the scale's training frames, and its
    held-out tail times the subject's ``held_out_factor``."""
    n_train = max(1, min(scale.frames, int(round(0.8 * scale.frames))))
    frames = n_train + SUBJECTS[subject].held_out_factor * (scale.frames - n_train)
    return frames, n_train / frames


def ensure_subject(cache: Path, subject: str, scale: Scale, seed: int = 0, fresh: bool = False) -> Path:
    """The synthetic subject's folder, generated once (deterministic: same seed, same files);
    ``fresh`` generates it again (and drops the fast regions computed from the old one)."""
    from stg_node.data.synth.generate import SynthConfig, generate
    from stg_node.data.synth.writer import read_metadata

    spec = SUBJECTS[subject]
    frames, fraction = subject_frames(subject, scale)
    out = subject_folder(cache, subject, scale, seed)
    try:
        meta = read_metadata(out)
        wanted = (
            spec.motion,
            frames,
            [scale.size, scale.size],
            scale.view_every,
            seed,
            spec.shading,
            spec.self_shadow,
        )
        found = (
            meta["motion"],
            meta["num_frames"],
            meta["size"],
            meta["view_every"],
            meta["seed"],
            meta["shading"]["mode"],
            "self_shadow" in meta["shading"],
        )
        held = meta.get("held_out") or {}
        same_held_out = (
            held.get("test_motion") or None,
            held.get("train_yaw_deg"),
            held.get("test_yaw_deg"),
        ) == (_motions(spec.test_motion), spec.train_yaw_deg, spec.test_yaw_deg)
        if found == wanted and same_held_out and not fresh:
            return out
    except (FileNotFoundError, ValueError, KeyError):
        pass
    log.info("generating the %s subject into %s", subject, out)
    for stale in out.glob("fast_regions_*.npz"):
        stale.unlink()
    generate(
        SynthConfig(
            out=out,
            seed=seed,
            num_frames=frames,
            size=scale.size,
            num_novel_views=scale.views,
            view_every=scale.view_every,
            train_fraction=fraction,
            supersample=scale.supersample,
            overwrite=True,
            **spec.synth_options(),
        ),
        progress=False,
    )
    return out


def subject_text(name: str, scale: Scale) -> str:
    """How a subject is generated, in stg-synth's words."""
    spec = SUBJECTS[name]
    frames, fraction = subject_frames(name, scale)
    options = [f"--motion {spec.motion}", f"--shading {spec.shading}", f"--frames {frames}"]
    if spec.self_shadow:
        options.append("--self-shadow")
    if fraction != 0.8:
        options.append(f"--train-fraction {fraction:g}")
    if spec.test_motion:
        options.append(f"--test-motion {spec.test_motion}")
    if spec.train_yaw_deg is not None:
        options.append(f"--train-yaw {spec.train_yaw_deg:g}")
    if spec.test_yaw_deg is not None:
        options.append(f"--test-yaw {spec.test_yaw_deg:g}")
    return f"{spec.title} (`{' '.join(options)}`)"


def _motions(test_motion: str | None) -> list[str] | None:
    from stg_node.data.synth.motions import held_out_motions

    return list(held_out_motions(test_motion)) or None


def _cached_regions(folder: Path, scale: Scale, cache: Path, region_of) -> dict[str, dict]:
    """Per split, (frame, camera name) -> (H, W) bool ``region_of(sample)``; cached in ``cache``."""
    import numpy as np

    from stg_node.avatar.data_spec import DataSpec

    regions: dict[str, dict] = {"novel_view": {}, "novel_pose": {}}
    if cache.is_file():
        with np.load(cache) as stored:
            for key in stored.files:
                split, frame, camera = key.split("|")
                regions[split][(int(frame), camera)] = (
                    np.unpackbits(stored[key])[: scale.size**2].reshape(scale.size, scale.size).astype(bool)
                )
        return regions
    spec = DataSpec(str(folder), "synthetic", size=scale.size)
    packed = {}
    for split in regions:
        for sample in spec.open(split):
            region = region_of(sample)
            regions[split][(sample.index, sample.camera.name)] = region
            packed[f"{split}|{sample.index}|{sample.camera.name}"] = np.packbits(region)
    np.savez_compressed(cache, **packed)
    return regions


def fast_regions(folder: Path, scale: Scale) -> dict[str, dict[tuple[int, str], object]]:
    """Per split, (frame, camera name) -> (H, W) bool fast-moving pixels; cached beside the data."""
    from stg_node.body import load_body_model
    from stg_node.data.synth.true_flow import benchmark_true_flow, fast_region
    from stg_node.data.synth.writer import read_metadata

    threshold = scale.fast_threshold_px
    meta = read_metadata(folder)
    faces = load_body_model().faces.cpu().numpy()
    cuts = tuple((meta.get("held_out") or {}).get("cuts", ()))

    def region_of(sample):
        flow = benchmark_true_flow(
            folder, sample.index, sample.camera, faces, int(meta["num_frames"]), cuts=cuts
        )
        return fast_region(flow, threshold)

    return _cached_regions(folder, scale, folder / f"fast_regions_{threshold:.3f}px.npz", region_of)


def garment_regions(folder: Path, scale: Scale) -> dict[str, dict[tuple[int, str], object]]:
    """Per split, (frame, camera) -> (H, W) bool pixels where the garment is seen; cached with the data."""
    from stg_node.body import load_body_model
    from stg_node.data.synth.garment_truth import benchmark_garment_pixels, benchmark_looseness, garment_faces

    body = load_body_model()
    faces = body.faces.cpu().numpy()
    is_garment = garment_faces(faces, benchmark_looseness(folder, body))

    def region_of(sample):
        return benchmark_garment_pixels(folder, sample.index, sample.camera, faces, is_garment)

    return _cached_regions(folder, scale, folder / "garment_regions.npz", region_of)


def active_on_garment(trainer, folder: Path) -> dict:
    """How many of the Gaussians with active motion terms lie on the garment (synthetic ground truth)."""
    from stg_node.data.synth.garment_truth import benchmark_looseness, on_garment

    table = trainer.model.table
    active = table.motion_active()
    if not bool(active.any()):
        return {"active_on_garment": 0, "active_on_garment_fraction": float("nan")}
    looseness = benchmark_looseness(folder, trainer.body)
    on = on_garment(table["means"].detach()[active].cpu(), trainer.canonical_vertices.cpu(), looseness)
    return {"active_on_garment": int(on.sum()), "active_on_garment_fraction": float(on.mean())}


# --- measuring one configuration ----------------------------------------------------------------
def data_id(folder: Path) -> str:
    """What identifies a generated subject: a hash of its synth.json (seed, motion, cameras, garment...)."""
    meta = Path(folder) / "synth.json"
    return hashlib.sha256(meta.read_bytes()).hexdigest()[:12] if meta.is_file() else "missing"


def fingerprint(config, row: Configuration, scale: Scale, seed: int, backend: str, data: str) -> str:
    """The settings a result depends on; a stored result with another fingerprint is measured again."""
    record = {
        "version": RESULT_VERSION,
        "data": data,
        "config": config.to_dict(),
        "subject": row.subject,
        "scale": dataclasses.asdict(scale),
        "seed": seed,
        "backend": backend,
    }
    return hashlib.sha256(json.dumps(record, sort_keys=True, default=str).encode()).hexdigest()[:16]


def train_run(row: Configuration, config, data: Path, run_dir: Path, scale: Scale, args) -> dict:
    """Train one configuration into a run folder (the layout stg-train writes); its training figures."""
    from stg_node.avatar import Trainer
    from stg_node.avatar.data_spec import DataSpec
    from stg_node.avatar.run import RunDir, write_json
    from stg_node.avatar.snapshot import write_snapshot_file
    from stg_node.data.flow import FlowCache
    from stg_node.progress import progress

    run = RunDir(run_dir)
    spec = DataSpec(str(data.resolve()), "synthetic", size=scale.size)
    run.write_config(
        {
            "config": config.to_dict(),
            "data": spec.to_dict(),
            "body_model": "open",
            "seed": args.seed,
            "backend": args.backend,
            "device": args.device,
            "versions": {"tool": "tools/tradeoff.py", "configuration": row.name},
        }
    )
    trainer = Trainer(
        config,
        device=args.device,
        backend=args.backend,
        seed=args.seed,
        flow_cache=FlowCache(data / "flow_cache"),
    )
    started = time.perf_counter()
    trainer.add_frames(spec.open("train"))
    prep_s = time.perf_counter() - started
    bar = progress(desc=f"train {row.name}", unit="it", total=config.iterations, enabled=not args.no_progress)
    while trainer.iteration < config.iterations:
        result = trainer.step()
        bar.update(1)
        if result.iteration % config.log_every == 0:
            bar.set_postfix(psnr=f"{result.psnr:.2f}", gaussians=result.num_gaussians, refresh=False)
    bar.close()
    trainer.save(run.checkpoint)
    write_snapshot_file(run.avatar, trainer.snapshot())
    stats = trainer.stats()
    summary = {
        "finished": True,
        "iterations": trainer.iteration,
        "train_seconds": trainer.train_seconds,
        "prep_seconds": prep_s,
        "skipped_steps": trainer.skipped_steps,
        "frames": len(trainer.store),
        "preset": config.preset,
        **stats,
        "active_motion_count": round(stats["active_motion_fraction"] * stats["gaussians"]),
        "densify": trainer.densify_counts,
        "nonrigid": trainer.nonrigid_report(),
        "normal_sign": trainer.normal_sign_report(),
        **active_on_garment(trainer, data),
    }
    write_json(run.summary, summary)
    return summary


RENDER_METHOD = "interleaved"  # how the render times were taken; older results are re-timed


def _render_ms(renderer, samples, corrections, repeats: int) -> tuple[float, float]:
    """Median wall times (ms) of pose + colour + splat, with the zero-motion skip and without.

    Both go through the same code and alternate render by render, so load on a shared machine
    falls on both alike; only ``skip_inactive`` differs.
    """
    import torch

    from stg_node.avatar.loading import corrected
    from stg_node.avatar.model import BodyState, Camera3, render

    runs: dict[bool, list[float]] = {True: [], False: []}
    for sample in samples:
        smpl = corrected(sample.smpl, corrections.get(sample.index))
        cam = Camera3.from_camera(sample.camera, device=renderer.device)
        u = renderer.time_for(smpl, sample.time)
        for i in range(repeats + 1):
            for skip in (True, False):
                t0 = time.perf_counter()
                with torch.no_grad():
                    body = BodyState.from_smpl(smpl, renderer.device)
                    posed = renderer.model.pose(body, u, cam.center, skip_inactive=skip)
                    image, _, _ = render(posed, cam, background=0.0, backend=renderer.backend)
                    image.cpu()
                if i:  # the first render of a view warms caches
                    runs[skip].append((time.perf_counter() - t0) * 1e3)
    return statistics.median(runs[True]), statistics.median(runs[False])


def measure_render(run_dir: Path, scale: Scale, loaded=None) -> dict:
    """Render time of a trained run on the CPU (and CUDA when present), with and without the skip.

    ``loaded``: what ``load_run_renderer(run_dir)`` returned, when the caller has it already.
    """
    import torch

    from stg_node.avatar import AvatarRenderer
    from stg_node.avatar.loading import load_run_renderer
    from stg_node.avatar.snapshot import read_snapshot_file

    run, renderer, corrections, _ = loaded or load_run_renderer(run_dir)
    dataset = run.data_spec().open("novel_view")
    samples = [dataset[i] for i in range(scale.render_views)]
    out = {"method": RENDER_METHOD, "cuda_ms": None, "cuda_ms_no_skip": None}
    out["cpu_ms"], out["cpu_ms_no_skip"] = _render_ms(renderer, samples, corrections, scale.render_repeats)
    if torch.cuda.is_available():
        gpu = AvatarRenderer.from_snapshot(read_snapshot_file(run.avatar), device="cuda", backend="cuda")
        out["cuda_ms"], out["cuda_ms_no_skip"] = _render_ms(gpu, samples, corrections, scale.render_repeats)
    return out


def evaluate_run(run_dir: Path, regions: dict, scale: Scale, garment: dict | None = None) -> dict:
    """Quality on both held-out splits (stg-eval's protocol), fast-region and per-body-part PSNR,
    the benchmark's condition (held-out distances), render speed; with ``garment`` (split -> (frame,
    camera) -> mask), the garment's PSNR pooled the same way as the body parts'."""
    import numpy as np

    from stg_node.avatar.evaluate import evaluate_split
    from stg_node.avatar.loading import load_run_renderer
    from stg_node.avatar.shape_stats import shape_stats
    from stg_node.data.metrics import psnr
    from stg_node.data.synth.body_parts import SynthPartLabeller
    from stg_node.data.synth.split_distances import benchmark_condition
    from stg_node.data.synth.writer import read_metadata

    loaded = load_run_renderer(run_dir)
    run, renderer, corrections, _ = loaded
    spec = run.data_spec()
    labeller = SynthPartLabeller(spec.root)
    out: dict = {}
    for split in ("novel_view", "novel_pose"):
        dataset = spec.open(split)
        report, kept = evaluate_split(
            renderer,
            dataset,
            split=split,
            lpips_nets=(LPIPS_NET,),
            pose_corrections=corrections if split == "novel_view" else None,
            show_progress=False,
            keep_images=len(dataset),
            regions=labeller.regions if garment is None else _with_garment(labeller.regions, garment[split]),
        )
        pred_px, gt_px, body_px = [], [], 0
        for index, camera, pred, gt in kept:
            region = regions[split][(index, camera)]
            pred_px.append(pred[region])
            gt_px.append(gt[region])
            body_px += int((gt.sum(-1) > 0).sum())
        fast = np.concatenate(pred_px), np.concatenate(gt_px)
        out[split] = {
            "psnr": report["psnr"],
            "ssim": report["ssim"],
            "lpips": report["lpips"].get(LPIPS_NET, math.nan),
            "views": report["views"],
            "fast_pixels": int(fast[0].shape[0]),
            "fast_fraction_of_body": fast[0].shape[0] / max(body_px, 1),
            "fast_psnr": psnr(fast[0][None], fast[1][None]) if fast[0].shape[0] else math.nan,
            "parts": {name: value["psnr"] for name, value in report["regions"].items() if name != "garment"},
            "spill": report.get("spill"),
            "protocol": report["protocol"],
        }
        if garment is not None:
            seen = report["regions"].get("garment", {"psnr": math.nan, "pixels": 0})
            out[split] |= {
                "garment_psnr": seen["psnr"],
                "garment_pixels": seen["pixels"],
                "garment_fraction_of_body": seen["pixels"] / max(body_px, 1),
            }
        if split == "novel_pose":
            frames = sorted({int(f) for f in dataset.frames})
            out["condition"] = benchmark_condition(read_metadata(Path(spec.root)), frames)
    out["shape"] = shape_stats(renderer.model).to_dict()
    out["render"] = measure_render(run_dir, scale, loaded)
    return out


def _with_garment(parts, masks: dict):
    """The body-part labeller's regions of a view plus its garment pixels (as one more region)."""

    def regions(frame: int, camera) -> dict:
        return parts(frame, camera) | {"garment": masks[(frame, camera.name)]}

    return regions


def machine() -> dict:
    import torch

    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    record = {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "threads": torch.get_num_threads(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
    }
    return record


def measure(
    row: Configuration, scale: Scale, args, regions_by_subject: dict, data: dict, garment_by_subject=None
) -> dict:
    """Train and score one configuration, or read its result if already measured with these settings."""
    from stg_node.avatar.run import write_json

    config = row.config(scale)
    key = fingerprint(config, row, scale, args.seed, args.backend, data_id(data[row.subject]))
    result_file = Path(args.out) / "results" / f"{row.name}.json"
    if result_file.is_file() and not args.fresh:
        stored = json.loads(result_file.read_text())
        if stored.get("fingerprint") == key:
            log.info(
                "%s: reusing the result in %s (same settings; --fresh measures again)", row.name, result_file
            )
            if stored.get("render", {}).get("method") != RENDER_METHOD:
                log.info("%s: timing its renders again (%s)", row.name, RENDER_METHOD)
                stored["render"] = measure_render(Path(stored["run_dir"]), scale)
                write_json(result_file, stored)
            return stored
    log.info("%s: training %d iterations on the %s subject", row.name, config.iterations, row.subject)
    run_dir = Path(args.out) / "runs" / row.name
    summary = train_run(row, config, data[row.subject], run_dir, scale, args)
    garment = (garment_by_subject or {}).get(row.subject)
    scores = evaluate_run(run_dir, regions_by_subject[row.subject], scale, garment)
    result = {
        "name": row.name,
        "label": row.label,
        "group": row.group,
        "subject": row.subject,
        "preset": row.preset,
        "changes": row.changes,
        "fingerprint": key,
        "config": config.to_dict(),
        "scale": scale.name,
        "seed": args.seed,
        "run_dir": str(run_dir),
        "train": summary,
        "it_per_s": summary["iterations"] / max(summary["train_seconds"], 1e-9),
        **scores,
        "machine": machine(),
        "date": datetime.date.today().isoformat(),
    }
    result_file.parent.mkdir(parents=True, exist_ok=True)
    write_json(result_file, result)
    return result


# --- the command -------------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    from stg_node.cli.runner import add_log_level_option

    p = argparse.ArgumentParser(
        prog="tradeoff.py",
        description="Train every STG-Avatar preset and ablation on the synthetic benchmark; write the "
        "trade-off table into docs/BENCHMARKS.md and a Pareto plot.",
    )
    p.add_argument(
        "--quick", action="store_true", help="a reduced grid in minutes (tiny images, few iterations)"
    )
    p.add_argument(
        "--scale",
        default=None,
        choices=tuple(SCALES),
        help="data and schedule sizes: full (default), mid (256 px, iterations / 3), quick (= --quick)",
    )
    p.add_argument(
        "--out",
        default=None,
        help="runs, results and (default) the data cache "
        "(default runs/tradeoff, or runs/tradeoff_SCALE for another scale)",
    )
    p.add_argument(
        "--data-cache", default=None, help="where the synthetic subjects are generated (default OUT/data)"
    )
    p.add_argument(
        "--docs",
        default=None,
        help="markdown file the section goes into "
        "(default docs/BENCHMARKS.md; at another scale, OUT/BENCHMARKS_SCALE.md)",
    )
    p.add_argument(
        "--plot",
        default=None,
        help="Pareto plot PNG (default docs/tradeoff_pareto.png; "
        "at another scale, OUT/tradeoff_pareto_SCALE.png)",
    )
    p.add_argument(
        "--base", default="fast", help="the preset the ablations flip switches of (default %(default)s)"
    )
    p.add_argument(
        "--only", nargs="+", default=None, metavar="NAME", help="measure only these configurations"
    )
    p.add_argument(
        "--fresh",
        action="store_true",
        help="generate the subjects and measure again even where results exist",
    )
    p.add_argument("--list", action="store_true", help="print the configurations and exit")
    p.add_argument("--seed", type=int, default=0, help="training seed (default %(default)s)")
    p.add_argument(
        "--backend", default="auto", choices=("auto", "cpu", "cuda", "torch"), help="splatting backend"
    )
    p.add_argument("--device", default="cpu", help="torch device for training (default %(default)s)")
    p.add_argument("--threads", default=None, help="CPU threads (default: STG_THREADS or 1)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    add_log_level_option(p)
    return p


def command_line(argv: list[str]) -> str:
    return " ".join(["python tools/tradeoff.py", *argv])


def run(args: argparse.Namespace, argv: list[str]) -> int:
    import tradeoff_report

    from stg_node.cli.runner import UsageError
    from stg_node.progress import progress
    from stg_node.threads import configure_threads

    if args.quick and args.scale not in (None, "quick"):
        raise UsageError(f"--quick and --scale {args.scale} contradict each other")
    scale = SCALES[args.scale or ("quick" if args.quick else "full")]
    reduced = scale is not FULL
    try:
        rows = grid(args.base)
    except ValueError as exc:
        raise UsageError(str(exc)) from exc
    names = {r.name for r in rows}
    if args.only:
        unknown = sorted(set(args.only) - names)
        if unknown:
            raise UsageError(f"--only: unknown configuration(s) {', '.join(unknown)}; see --list")
    if args.list:
        for row in rows:
            target = f"= {row.alias_of}" if row.alias_of else f"{row.preset} {row.changes or ''}"
            print(f"{row.name:18s} {row.subject:6s} {row.group:8s} {target}")
        return 0
    configure_threads(args.threads)
    out = Path(args.out or (f"runs/tradeoff_{scale.name}" if reduced else "runs/tradeoff"))
    args.out = str(out)
    cache = Path(args.data_cache) if args.data_cache else out / "data"
    docs = (
        Path(args.docs)
        if args.docs
        else (out / f"BENCHMARKS_{scale.name}.md" if reduced else REPO / "docs/BENCHMARKS.md")
    )
    plot = (
        Path(args.plot)
        if args.plot
        else (out / f"tradeoff_pareto_{scale.name}.png" if reduced else REPO / "docs/tradeoff_pareto.png")
    )
    selected = [r for r in rows if not r.alias_of and (not args.only or r.name in args.only)]
    subjects = sorted({r.subject for r in selected}, key=list(SUBJECTS).index)
    data, regions, garment = {}, {}, {}
    for subject in progress(subjects, desc="subjects", unit="subject", enabled=not args.no_progress):
        data[subject] = ensure_subject(cache, subject, scale, fresh=args.fresh)
        regions[subject] = fast_regions(data[subject], scale)
        garment[subject] = garment_regions(data[subject], scale)
    results = {}
    bar = progress(desc="configurations", unit="config", total=len(selected), enabled=not args.no_progress)
    for row in selected:
        bar.set_postfix(config=row.name, refresh=True)
        results[row.name] = measure(row, scale, args, regions, data, garment)
        bar.update(1)
    bar.close()
    # Rows measured earlier with the same settings (a partial --only run) join the report.
    for row in rows:
        if row.alias_of or row.name in results:
            continue
        stored = Path(args.out) / "results" / f"{row.name}.json"
        if stored.is_file():
            record = json.loads(stored.read_text())
            folder = subject_folder(cache, row.subject, scale, 0)
            key = fingerprint(row.config(scale), row, scale, args.seed, args.backend, data_id(folder))
            if record.get("fingerprint") == key:
                results[row.name] = record
    docs, plot = partial_report_targets(rows, results, args, out, docs, plot, reduced)
    context = tradeoff_report.ReportContext(
        command=command_line(argv),
        machine=machine(),
        scale=dataclasses.asdict(scale),
        fast_threshold_px=scale.fast_threshold_px,
        base=args.base,
        date=datetime.date.today().isoformat(),
        plot=plot,
        docs=docs,
        subjects={name: subject_text(name, scale) for name in SUBJECTS},
    )
    report = tradeoff_report.build(rows, results, context)
    (out / "results.json").write_text(json.dumps(report.records, indent=1, default=float))
    tradeoff_report.write_plot(report, plot)
    tradeoff_report.write_section(docs, report.markdown)
    print(report.markdown)
    return 0


def partial_report_targets(rows, results, args, out: Path, docs: Path, plot: Path, reduced: bool):
    """Where the report goes: the full-scale table in docs/BENCHMARKS.md takes only a complete grid
    (every row measured now or stored with the same settings); a partial run writes beside its
    runs instead, unless ``--docs`` / ``--plot`` name a file. A partial run once replaced that
    table with a column of 'not measured' rows."""
    missing = [r.name for r in rows if not r.alias_of and r.name not in results]
    if reduced or not missing:
        return docs, plot
    if not args.docs:
        docs = out / "BENCHMARKS_partial.md"
        log.info(
            "%d of the grid's rows are not measured with these settings (%s...): the report goes "
            "into %s, not docs/BENCHMARKS.md (--docs to choose)",
            len(missing),
            ", ".join(missing[:3]),
            docs,
        )
    if not args.plot:
        plot = out / "tradeoff_pareto_partial.png"
    return docs, plot


def main(argv: list[str] | None = None) -> int:
    from stg_node.cli.runner import run_main

    argv = list(sys.argv[1:] if argv is None else argv)
    return run_main(build_parser(), lambda args: run(args, argv), argv)


if __name__ == "__main__":
    sys.exit(main())
