"""Whether the non-rigid part pays on this subject, and the rigid model it becomes when it does not.

Model only what the scene requires. A subject whose motion the skinned body explains gains
nothing from non-rigid terms but their cost (training speed, model size, render work); one with
loose clothing needs them. The trainer cannot know which from the data's name, so it finds out
(:class:`Trainer`, ``nonrigid = "auto"``), once, at ``nonrigid_decide_iter``:

1. **Is there motion the rigid model misses?** Every visible Gaussian keeps a running mean of
   the optical flow its own rendered motion does not explain (``resid_w``, densify.py: per
   training camera, the most any camera sees). When
   fewer than ``nonrigid_min_moving`` of the Gaussians seen see more than ``residual_motion_px``
   (pixels per frame at the frames' size), nothing moves that skinning does not: off. (The missed
   flow is the *full* model's: where its motion terms already follow the cloth it falls. From
   several cameras the Gaussians whose motion terms are on at the decision count as moving too:
   their gates opened on missed flow, and their learned motion, which every camera's images
   constrain, stayed above ``densify.motion_min_px``. From one camera that motion may be a
   training view's residue, so there they do not count.) The test is
   only as good as the flow: its error must stay well under that threshold, hence DIS down to the
   frames' own pixels (``FlowSettings.finest_scale``; at a quarter of the resolution its error
   alone made a still subject at 256 px read as 25 % moving, docs/BENCHMARKS.md).
2. **Do the non-rigid terms explain frames they were not trained on?** Until the decision every
   ``nonrigid_holdout_every``-th training frame is held out. Each is rendered with the model and
   with the model's rigid part alone (:func:`rigid_part`), and the squared errors are pooled over
   the pixels where the two renders differ: the gain, in dB, is what the non-rigid terms buy on
   unseen instants where they act. Below ``nonrigid_min_gain_db``: off. (Zeroing the terms of a
   model trained with them favours keeping them, so a gain that small means they do not pay.)

Off means the trainer continues with :func:`rigid_part` of its model and LBS-only settings (no
spacetime terms, no flow-guided densification): it trains and renders at LBS-only speed from
then on, and the published model carries no motion columns. The run's summary records the
choice, the evidence and why (:class:`Decision`); ``nonrigid = "on"`` keeps the terms whatever
the evidence, and ``model.spacetime=false`` is LBS only from the start.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import torch

from stg_node.avatar.gaussians import GaussianTable
from stg_node.avatar.model import AvatarModel, Camera3, render
from stg_node.avatar.spacetime import PERSISTENT_SCALE, SpacetimeState

NONRIGID_COLUMNS = ("motion", "motion_coef", "rot_motion", "motion_gate", "t_center", "t_log_scale")
CHANGED_LEVEL = 1.0 / 255.0  # renders differing by less than one grey level count as equal


@dataclass
class Decision:
    """What the trainer chose for the non-rigid part, and why (the run's summary holds it)."""

    chose: str  # "on" or "off"
    why: str
    iteration: int
    evidence: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> Decision | None:
        return cls(**data) if data else None


def held_out(frame_index: int, every: int) -> bool:
    """Frames set aside to judge the non-rigid part until the decision (every ``every``-th, mid-stride)."""
    return every > 1 and frame_index % every == every // 2


def moving_fraction(
    resid_w: torch.Tensor, seen: torch.Tensor, threshold_px: float, moving_terms: torch.Tensor | None = None
) -> float:
    """Share of the Gaussians ``seen`` whose missed flow (running mean, px per frame) exceeds threshold_px,
    or, where ``moving_terms`` (n,) bool is given, whose motion terms are on (from several cameras:
    the module's test 1)."""
    count = int(seen.sum())
    moving = resid_w > threshold_px
    if moving_terms is not None:
        moving = moving | moving_terms
    return float(moving[seen].sum()) / count if count else 0.0


def rigid_part(model: AvatarModel) -> tuple[AvatarModel, torch.Tensor]:
    """``model`` without its non-rigid part: the same Gaussians, colour and skeleton under LBS only
    (no motion columns, no temporal opacity; the same light where it is shaded), and the rows
    kept (Gaussians on a finite temporal window model one moment and are dropped)."""
    table = model.table
    keep = torch.ones(table.num, dtype=torch.bool, device=model.device)
    if "t_log_scale" in table:
        keep = table["t_log_scale"].detach().exp() >= PERSISTENT_SCALE
        if not bool(keep.any()):
            keep[:] = True  # nothing persistent at all: keep everything rather than nothing
    columns = {name: table[name].detach()[keep] for name in table.names() if name not in NONRIGID_COLUMNS}
    columns["means"] = _mean_placed(model)[keep]
    config = dataclasses.replace(model.config, spacetime=False)
    rigid = AvatarModel(
        config, GaussianTable(columns), model.skeleton, model.bounds, model.time_axis, model.pose_index
    ).to(model.device)
    if model.color_mlp is not None:
        rigid.color_mlp.load_state_dict(model.color_mlp.state_dict())
    if model.shading is not None:  # the same learned light and mean training orientation
        rigid.shading.load_state_dict(model.shading.state_dict())
    return rigid, keep


@torch.no_grad()
def faded_state(
    model: AvatarModel, state: SpacetimeState, weight: float, keep: torch.Tensor, mean_offsets: torch.Tensor
) -> SpacetimeState:
    """``model``'s spacetime terms ``state`` (at some instant) taken ``weight`` of the way from its
    rigid part (0: each moving row at its mean offset, its base rotation, the rows :func:`rigid_part`
    drops at zero opacity; ``keep`` is that part's mask, ``mean_offsets`` :func:`mean_offsets`) to
    the instant (1): offsets, rotation deltas and temporal opacity blended linearly, rendered in one
    pass of the full model (the renderer's fade beyond the pose index's reach, timecode.py). The
    ends agree with the two renders to float rounding (the renderer takes those renders there)."""
    table = model.table
    offsets = mean_offsets if state.offsets is None else torch.lerp(mean_offsets, state.offsets, weight)
    base_quats = table["quats"].detach()
    quats = torch.lerp(base_quats, state.quats, weight)
    temporal = torch.ones(table.num, device=keep.device) if state.temporal is None else state.temporal
    rigid_opacity = keep.to(temporal.dtype)  # kept rows show fully, dropped ones not at all
    return SpacetimeState(offsets, quats, torch.lerp(rigid_opacity, temporal, weight))


def mean_offsets(model: AvatarModel) -> torch.Tensor:
    """(N, 3) the offset :func:`rigid_part` gives each row (its mean over the knots; zero where static)."""
    with torch.no_grad():
        return _mean_placed(model) - model.table["means"].detach()


def _mean_placed(model: AvatarModel) -> torch.Tensor:
    """(N, 3) canonical centres with each moving row's mean offset over the knots (shared bases) added:
    a constant offset is a displaced centre, not motion (as when a gate settles, densify.py), so the
    rigid part keeps where the motion held a Gaussian on average rather than snapping it back."""
    table, bases = model.table, model.motion_bases
    means = table["means"].detach()
    gate = table.motion_gate()
    if bases is None or gate is None or "motion_coef" not in table:
        return means
    rows = gate.nonzero().squeeze(1)
    with torch.no_grad():
        _, mean = bases.variation(table["motion_coef"].detach()[rows], means[rows])
    return means.index_add(0, rows, mean)


@torch.no_grad()
def validation_gain(model: AvatarModel, rigid: AvatarModel, views, backend: str = "auto") -> dict:
    """What the non-rigid terms buy on held-out views: ``views`` yields (camera: Camera3, body, u,
    target (h, w, 3) in [0, 1]); returns the gain (dB) pooled over the pixels where the two renders
    differ, those pixels' share, and both whole-view PSNRs."""
    se_full = se_rigid = 0.0
    changed = total = 0
    whole_full = whole_rigid = 0.0
    for camera, body, u, target in views:
        full_img = _render(model, camera, body, u, backend)
        rigid_img = _render(rigid, camera, body, u, backend)
        differ = (full_img - rigid_img).abs().amax(dim=-1) > CHANGED_LEVEL
        err_full = ((full_img - target) ** 2).mean(-1)
        err_rigid = ((rigid_img - target) ** 2).mean(-1)
        se_full += float(err_full[differ].sum())
        se_rigid += float(err_rigid[differ].sum())
        changed += int(differ.sum())
        total += differ.numel()
        whole_full += float(err_full.sum())
        whole_rigid += float(err_rigid.sum())
    gain = 10.0 * math.log10(max(se_rigid, 1e-12) / max(se_full, 1e-12)) if changed else 0.0
    return {
        "gain_db": gain,
        "changed_fraction": changed / max(total, 1),
        "psnr_full": _psnr(whole_full, total),
        "psnr_rigid": _psnr(whole_rigid, total),
    }


def _render(model: AvatarModel, camera: Camera3, body, u: float, backend: str) -> torch.Tensor:
    posed = model.pose(body, u, camera.center, skip_inactive=True)
    image, _, _ = render(posed, camera, background=0.0, backend=backend)
    return image[..., :3].clamp(0, 1)


def _psnr(squared_error_sum: float, pixels: int) -> float:
    return -10.0 * math.log10(max(squared_error_sum / max(pixels, 1), 1e-12))
