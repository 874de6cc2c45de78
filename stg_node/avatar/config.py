"""Every setting of an STG-Avatar model and its training, as plain dataclasses.

Three groups, one dataclass each, composed by :class:`TrainConfig`:

- :class:`ModelConfig`: what the avatar *is* (Gaussian budget, polynomial orders, colour model,
  which parts are switched on). Its numeric fields travel inside every GaussianSnapshot so a
  renderer rebuilds the same model from the message alone.
- :class:`LossConfig`: the weights of the loss terms and the adaptive weighting.
- :class:`DensifyConfig`: clone/split/prune and the flow-guided densification thresholds.

Presets (fast / balanced / quality) live in :mod:`stg_node.avatar.presets`; ablations are the
same dataclasses with a switch flipped (``dataclasses.replace``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

COLOR_MODES = ("mlp", "sh")
SKIN_INIT = ("barycentric", "nearest")
NONRIGID_MODES = ("auto", "on", "off")
# What switching the non-rigid part off sets: LBS only (no spacetime terms, no flow-guided densification).
LBS_ONLY = {"model.spacetime": False, "densify.flow_guided": False}
LIGHT_MODELS = ("distant", "sh")  # the learned light: an ambient term and distant lights, or free SH
NORMAL_SIGNS = ("outward", "camera", "auto")  # a shading normal's sign in training (normal_trial.py)
# What settings added later mean for a model or configuration written before they existed: the
# behaviour it was trained with (snapshot.model_config_from_meta, TrainConfig.from_dict).
# A group's entries are a dict; a top-level setting's entry is its value.
PREDATING_DEFAULTS = {
    "model": {
        "shading": False,
        "init_flatness": 1.0,
        "max_scale_ratio": 0.0,
        "motion_basis": 0,
        "joint_shrink": False,
        "occlusion": False,
        "normal_sign": "camera",
    },
    "loss": {"isometry": 0.0, "flow_every": 1, "isometry_every": 1},
    "densify": {"flow_seed_missed": False, "motion_min_px": 0.0, "occlusion_m": 0.0, "unseen_cell_m": 0.0},
    "nonrigid": "on",  # runs stored before the trial kept their non-rigid part
    "lr_exposure": 0.0,  # no exposure correction before real footage had one
    "color_every": 1,  # the colour MLP on every row every step before issue 24's turns
}


@dataclass(frozen=True)
class ModelConfig:
    num_gaussians: int = 20_000  # initial Gaussians sampled on the canonical (big-pose) body surface
    max_gaussians: int = 60_000  # densification never grows the model past this
    init_scale_factor: float = 0.6  # initial scale = factor x mean spacing of the surface samples
    skin_init: str = "barycentric"  # skinning weights of a sample: barycentric blend or nearest vertex
    learn_skin_weights: bool = True  # learned per-Gaussian correction of the body's weights
    # Spacetime Gaussians (non-rigid part). spacetime=False is the "LBS only" ablation.
    spacetime: bool = True
    motion_order: int = 2  # n_p: polynomial order of the centre offset (0 = none)
    rotation_order: int = 1  # n_q: polynomial order of the rotation (0 = static rotation)
    temporal_opacity: bool = True  # sigma_i(t) = sigma_i exp(-((t - mu_tau)/s)^2)
    time_unit_s: float = 1.0  # one unit of the normalised time axis, in seconds
    time_horizon: float = 1.0  # local time is bounded to +-horizon units (tanh), so polynomials stay bounded
    init_time_scale: float = 1e3  # temporal scale of the initial Gaussians (units): present at all times
    # Shared motion bases (motion_basis.py): B > 0 replaces the per-Gaussian offset polynomial by
    # per-Gaussian mixtures of B shared affine motions (24: one per bone, GART's latent bones),
    # piecewise linear in time over knots basis_knot_s apart.
    motion_basis: int = 24
    basis_knot_s: float = 1.0 / 15.0
    # Colour: "mlp" (the paper's light MLP) or "sh" (per-Gaussian spherical harmonics).
    color: str = "mlp"
    sh_degree: int = 1  # view dependence (SH mode: per-Gaussian coefficients; MLP mode: direction encoding)
    feature_dim: int = 16  # per-Gaussian appearance feature fed to the MLP (f_mot)
    mlp_width: int = 64
    mlp_layers: int = 2  # hidden layers
    pos_freqs: int = 4  # gamma(mu): sin/cos frequencies of the positional encoding
    pose_dim: int = 8  # gamma(theta): the body pose is encoded to this many features (0 = no pose input)
    # Shading (shading.py): the colour above is the albedo, times the irradiance of each Gaussian's
    # world normal (its shortest axis) under a light fixed in the world, learned; False = the colour
    # as is, the training clip's light baked in (the earlier behaviour).
    shading: bool = True
    light_model: str = "distant"  # the learned light: ambient + light_count distant lights, or free SH
    light_count: int = 2
    # Which way a Gaussian's shading normal points in training: "camera", flipped towards the
    # training camera, "outward", the side its disc was initialised with on the body surface
    # (while its local z axis is the shortest; shading.outward_normals), or "auto" (the default):
    # the camera's until TrainConfig.normal_decide_iter, then outward when the learned light has
    # the contrast for a sign to matter (normal_trial.py). Renders flip every normal towards the
    # viewer either way (docs/AVATAR.md, "Which way a normal points").
    normal_sign: str = "auto"
    init_flatness: float = 0.3  # initial Gaussians: discs along the surface, normal axis x this (1 = spheres)
    max_scale_ratio: float = 10.0  # largest / smallest axis of a rendered Gaussian at most this (0 = no cap)
    # A Gaussian between bones that bend apart shrinks as linear blend skinning squeezes the surface
    # there (rigid.joint_shrink), instead of keeping its size and sticking out of a folded joint.
    joint_shrink: bool = True
    # What the body casts on itself (occlusion.py): with shading, the irradiance times the share of
    # each Gaussian's sky the posed body (spheres fitted to it) leaves open, at a learned strength.
    # On by default since its C++ kernel (csrc/sphere_occlusion.cpp) made it cheap: docs/AVATAR.md.
    occlusion: bool = True

    def validate(self) -> None:
        if self.light_model not in LIGHT_MODELS:
            raise ValueError(f"light_model must be one of {LIGHT_MODELS}, got {self.light_model!r}")
        if not 1 <= self.light_count <= 4:
            raise ValueError(f"light_count must be 1..4, got {self.light_count}")
        if self.normal_sign not in NORMAL_SIGNS:
            raise ValueError(f"normal_sign must be one of {NORMAL_SIGNS}, got {self.normal_sign!r}")
        if not 0.0 < self.init_flatness <= 1.0:
            raise ValueError(f"init_flatness must be in (0, 1], got {self.init_flatness}")
        if self.max_scale_ratio != 0 and self.max_scale_ratio < 1.0:
            raise ValueError(f"max_scale_ratio must be 0 (no cap) or >= 1, got {self.max_scale_ratio}")
        if self.color not in COLOR_MODES:
            raise ValueError(f"color must be one of {COLOR_MODES}, got {self.color!r}")
        if self.skin_init not in SKIN_INIT:
            raise ValueError(f"skin_init must be one of {SKIN_INIT}, got {self.skin_init!r}")
        if not 1 <= self.num_gaussians <= self.max_gaussians:
            raise ValueError(
                f"need 1 <= num_gaussians <= max_gaussians, got {self.num_gaussians} and {self.max_gaussians}"
            )
        if not 0 <= self.motion_order <= 4 or not 0 <= self.rotation_order <= 2:
            raise ValueError(
                f"motion_order must be 0..4 and rotation_order 0..2, got {self.motion_order}, "
                f"{self.rotation_order}"
            )
        if not 0 <= self.sh_degree <= 3:
            raise ValueError(f"sh_degree must be 0..3, got {self.sh_degree}")
        if self.time_unit_s <= 0 or self.time_horizon <= 0 or self.init_time_scale <= 0:
            raise ValueError("time_unit_s, time_horizon and init_time_scale must be > 0")
        if not 0 <= self.motion_basis <= 24 or not self.basis_knot_s > 0:
            raise ValueError(
                f"motion_basis must be 0..24 and basis_knot_s > 0, got {self.motion_basis}, "
                f"{self.basis_knot_s}"
            )

    @property
    def n_p(self) -> int:
        """Active order of the motion polynomial (0 when spacetime is off or shared bases replace it)."""
        return self.motion_order if self.spacetime and not self.motion_basis else 0

    @property
    def n_b(self) -> int:
        """Shared motion bases in use (0 when spacetime is off)."""
        return self.motion_basis if self.spacetime else 0

    @property
    def n_q(self) -> int:
        return self.rotation_order if self.spacetime else 0

    @property
    def uses_temporal_opacity(self) -> bool:
        return self.spacetime and self.temporal_opacity


@dataclass(frozen=True)
class LossConfig:
    ssim: float = 0.2  # L = (1 - w) L1 + w (1 - SSIM), as 3DGS
    mask: float = 0.1  # |alpha - mask|
    flow: float = 0.05  # rendered Gaussian motion vs optical flow (pixels, on valid flow only)
    # The flow term on every k-th step only, at k x its weight (issue 24): the other steps skip the
    # next frame's skinning and the two flow channels of the splat. Densification's flow rounds
    # always get it. 1: every step (as before).
    flow_every: int = 4
    temporal: float = 0.1  # offsets (cm) and temporal opacities at consecutive frames agree
    rigidity: float = 0.05  # neighbouring Gaussians move together (cm; rigidity.py)
    line_of_sight: float = 0.0  # motion along the training camera's rays (cm; motion_priors.py; 1 camera)
    motion_sparsity: float = 0.3  # proximal L1 threshold, x the motion learning rate (optim.soft_threshold)
    motion_smooth: float = 1e-3  # higher polynomial orders cost more (|b_ik| (k - 1))
    basis_smooth: float = 0.01  # shared motion bases: |second difference| of their knots (cm)
    scale: float = 0.01  # penalises scales above scale_max_m
    scale_max_m: float = 0.03
    opacity: float = 0.0  # entropy-style push of opacities towards 0 or 1
    skin: float = 0.01  # keeps the learned skinning correction small
    pose_refine: float = 1e-3  # keeps per-frame pose corrections small
    # Shading and shape (shading.py, isometry.py).
    light: float = 1e-3  # keeps the learned light near uniform (mean square of its non-constant terms)
    # A distant light cast mostly on normals no training camera faces (shading.py): nothing in the
    # training images can confirm it, so it goes.
    light_unseen: float = 1e-2
    isometry: float = 0.05  # posed distances between canonical neighbours stay as in canonical space (cm)
    # The isometry term on every k-th step only, at k x its weight (issue 24, as flow_every): the
    # other steps skip its ~96k edges (20k Gaussians). 1: every step (as before).
    isometry_every: int = 4
    # Real footage (pose_refine.py, exposure.py).
    pose_smooth: float = 0.0  # refined poses smooth in time (pose_refine.py; on for tracked poses)
    adaptive: bool = True  # balance the auxiliary terms against the photometric term (see losses.py)
    warmup_iters: int = 300  # auxiliary terms ramp in over these iterations


@dataclass(frozen=True)
class DensifyConfig:
    enabled: bool = True
    start_iter: int = 300
    stop_fraction: float = 0.75  # no densification after this fraction of the iterations
    interval: int = 200
    gate_start_iter: int = 150  # motion gates are revised every interval from here (densify.py)
    # Mean |dL/dmeans2d| x rendered pixels (AbsGS-style, made independent of the crop's size) that
    # triggers clone/split: about the top 5 % of Gaussians early in training.
    grad_threshold: float = 0.3
    percent_dense: float = 0.01  # scale separating clone (small) from split (large), x body extent
    prune_opacity: float = 0.02  # harder than 3DGS's 0.005
    prune_score: float = 0.02  # C_i (1 + gamma W_i) below this is pruned
    prune_scale_m: float = 0.15  # larger Gaussians are pruned
    motion_protect_gamma: float = 4.0  # gamma in C_i (1 + gamma W_i)
    # Flow-guided densification (STG-Avatar).
    flow_guided: bool = True
    flow_interval: int = 50  # steps between flow-guided densification rounds
    region_px: int = 16  # regions are square image tiles of this size
    error_threshold: float = 0.08  # tau: mean |render - gt| of a region that counts as badly explained
    # delta: a Gaussian moves fast when its time-integrated flow (running mean of |flow| under it,
    # px per frame) exceeds max(motion_floor_px, motion_relative x the median flow of the frames):
    # relative, so a turning subject does not make everything "fast"; floored, so a still one
    # does not make its breathing "fast".
    motion_floor_px: float = 1.0
    motion_relative: float = 1.5
    motion_min_m: float = 5e-4  # at each density step, motion terms smaller than this (m) are zeroed
    flow_step: float = 0.5  # Delta: new centre = seed + Delta * (metric flow residual) along v/|v|
    flow_noise_m: float = 0.005  # sigma of N(0, sigma^2) added to new centres
    flow_consistency_px: float = 1.5  # reject new Gaussians whose projected motion disagrees with the flow
    flow_max_new: int = 500  # per flow-guided round
    # A Gaussian sees motion the model misses when the optical flow under it differs from the model's
    # own rendered motion by more than this (running mean, px per frame): where non-rigid terms may pay.
    residual_motion_px: float = 1.5
    # What opens a Gaussian's motion gate (with the image still pulling on it): "residual", flow the
    # model's own motion misses (> residual_motion_px); "flow", the flow itself (> delta, STG-Avatar's).
    motion_signal: str = "residual"
    # Shared motion bases: a static Gaussian also starts to move where moving with its bones' shared
    # motions would lower the loss: -sum <dL/dx, m> / sum |dL/dx| |m| over an interval above this.
    motion_help: float = 0.3
    # Motion terms only where they are measured (densify.py, issue 22): flow-guided seeds need flow the
    # model's own motion misses (> residual_motion_px), not the raw flow; a dynamic Gaussian whose
    # offset swings over time by less than motion_min_px pixels of the views it is seen in settles (its
    # mean offset kept in its centre). From one camera small swings are mostly the training view's
    # residue: at 3, 6 and 12 px (512 px frames) the medium study's dance and mixed subjects scored best
    # on held-out views at 6 (docs/BENCHMARKS.md, "The non-rigid part").
    flow_seed_missed: bool = True
    motion_min_px: float = 6.0
    # Clone and split where the image is still wrong (issue 22): each step's screen gradient counts in
    # proportion to its region's error over error_threshold (tau, capped at 1). Under L1 the gradient's
    # size does not fall as the fit improves, so fine texture that is already reproduced keeps cloning.
    # Off by default: at 256 px it cut clones 3-5x and raised every held-out figure, at 512 px it shrank
    # the models by ~40 % with whole images within 0.1 dB but cost the still subject's garment pixels
    # 0.41 dB (docs/BENCHMARKS.md, "The non-rigid part", round 5).
    clone_on_error: bool = False
    # Flow statistics and flow-guided seeds count a Gaussian only where it is the surface its pixel
    # sees: at most this far (m) behind the rendered depth there (densify._in_front; issue 25); 0: every
    # Gaussian under the pixel counts (the behaviour before).
    occlusion_m: float = 0.04
    # Surface no training view shows (issue 22): at each density step, Gaussians that were the surface
    # seen (densify._in_front) in none of the unseen_after_views or more depth-rendered steps (the flow
    # term's) they existed in are thinned to one per unseen_cell_m cube of the canonical space (the
    # cube's opacity-weighted mean, its most opaque row's opacity, sized to the cube): there is no
    # detail to learn there, only a cover for the silhouette and the prior's colour. A subject filmed
    # from one side keeps about 40 % of its surface unseen; one that turns, 4 % (tools/surface_coverage.py).
    # 0: off.
    # Off by default: on the study's subjects (all turn) it thins 0.2 % or less; on a still subject that never
    # turns 6 %, but its novel views lose 0.15 dB (0.76 dB on their garment pixels): docs/BENCHMARKS.md,
    # "The non-rigid part", round 8. 0.05 (m) is the setting measured.
    unseen_cell_m: float = 0.0
    unseen_after_views: int = 50
    new_time_scale: float = 0.25  # temporal scale (units) of Gaussians added along the flow
    resample_fraction: float = 0.3  # re-sample body parts whose density fell below this x initial
    # Temporal split: a dynamic Gaussian that the image still pulls on is replaced by copies on
    # shorter temporal windows (spacetime densification), down to min_time_scale (time units).
    temporal_split: bool = True
    temporal_split_max: int = 6  # copies of a Gaussian present at all times
    min_time_scale: float = 0.06


@dataclass(frozen=True)
class TrainConfig:
    preset: str = "custom"
    model: ModelConfig = field(default_factory=ModelConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    densify: DensifyConfig = field(default_factory=DensifyConfig)
    iterations: int = 3000
    # Learning rates (Adam), per parameter group as in 3DGS / SpacetimeGaussians.
    lr_means: float = 1.6e-4  # x body extent, decayed x0.01 over training
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    lr_opacity: float = 5e-2
    lr_color: float = 2.5e-3  # SH coefficients / per-Gaussian features
    lr_mlp: float = 1e-3
    lr_motion: float = 1e-3  # offset polynomials, and the shared bases' trajectories (metres)
    lr_motion_coef: float = 1e-3  # coefficients of the shared motion bases
    lr_rot_motion: float = 1e-3
    lr_time: float = 1e-3
    lr_skin: float = 1e-3
    lr_pose: float = 1e-4  # per-frame pose refinement (0 = off)
    # The learned light (shading.py). 5e-3 left it limited by its rate: on the mid-scale room-light
    # benchmark half the true contrast at the end of the schedule, a 2.3 dB novel-pose gap (0.99 at 3e-2).
    lr_light: float = 3e-2
    # Real footage (pose_refine.py, exposure.py).
    pose_refine_joints: bool = True  # False: refine each frame's alignment only (root rotation, Th)
    # Poses first (pose_refine.py, pose_warmup_factor): for the first pose_warmup fraction of the
    # iterations the pose corrections learn at pose_warmup_boost x lr_pose, easing back to 1 x over
    # the next pose_warmup fraction (1.0 = off).
    pose_warmup: float = 0.25
    pose_warmup_boost: float = 1.0
    # Per-frame exposure / white-balance gains (exposure.py): the share of each draw's least-squares
    # gains taken (0 = off, 1 = the draw's estimate as is), from step exposure_start on. Off for data
    # filmed at a fixed exposure (datasets, stg-synth); footage (--format video, live cameras) turns
    # it on with exposure.for_footage.
    lr_exposure: float = 0.0
    exposure_start: int = 100
    lr_schedule_final: float = 0.1  # every rate but the means' decays to this fraction (cosine)
    crop_margin_px: int = 16  # render the mask's bounding box plus this margin, not the whole frame
    full_frame_every: int = 0  # every K-th step renders the whole frame (0 = never)
    # The colour MLP in turns on a CPU (issue 24, color_cache.TrainingColorTurns): a step evaluates
    # it, with its gradient (x color_every), on every color_every-th row only; the other rows keep
    # their last colour, and the features learn at lr_color x sqrt(color_every) (Adam on a gradient
    # 1 step in k). 3: a third of the MLP's cost per step (docs/BENCHMARKS.md, issue 24 round 7).
    # 1: every row every step (as on a GPU).
    color_every: int = 3
    sh_increase_every: int = 500  # SH degree grows by one every this many steps, up to sh_degree
    checkpoint_every: int = 500
    log_every: int = 10
    max_frames: int = 0  # frames kept for training (0 = all); the online trainer bounds this
    # Annealed time noise (Deformable 3DGS): the spacetime terms see the frame's time plus N(0, s^2),
    # s = time_noise_frames frame intervals at the start, falling to 0 at time_noise_until x iterations.
    time_noise_frames: float = 0.0
    time_noise_until: float = 0.5
    # The non-rigid part earns its place (nonrigid.py): "auto" decides at nonrigid_decide_iter whether
    # it pays on this subject and switches it off when not (LBS only from then on); "on" keeps it;
    # "off" is LBS only from the start (as model.spacetime=false with densify.flow_guided=false).
    # Until the decision every nonrigid_holdout_every-th training frame is held out to judge it.
    nonrigid: str = "auto"
    nonrigid_decide_iter: int = 600
    nonrigid_holdout_every: int = 10
    nonrigid_min_moving: float = 0.05  # share of the Gaussians seeing flow the rigid model misses
    nonrigid_min_gain_db: float = 0.3  # on the held-out frames' pixels the non-rigid terms change
    # model.normal_sign = "auto" (normal_trial.py): at normal_decide_iter, outward normals from then
    # on when the learned light's contrast (std of its irradiance over directions / mean) is at least
    # normal_min_contrast, else the camera's sign stays. 0.35 lies between the subjects lit by a light
    # that turns with them (0.23-0.29 at 512 px, where outward cost the dance 0.2-0.56 dB) and a room
    # lamp (0.45-0.57, where it gains 0.6-0.9 dB); three coloured lights (0.29-0.38) score alike
    # either way, flat light decides at 0.03-0.17 (docs/BENCHMARKS.md, 2026-11-27 round 11).
    normal_decide_iter: int = 300
    normal_min_contrast: float = 0.35

    def validate(self) -> None:
        self.model.validate()
        if self.iterations < 1:
            raise ValueError(f"iterations must be >= 1, got {self.iterations}")
        for f in dataclasses.fields(self):
            if f.name.startswith("lr_") and getattr(self, f.name) < 0:
                raise ValueError(f"{f.name} must be >= 0, got {getattr(self, f.name)}")
        if self.loss.flow_every < 1:
            raise ValueError(
                f"loss.flow_every must be >= 1 (1: the flow term every step), got {self.loss.flow_every}"
            )
        if self.loss.isometry_every < 1:
            raise ValueError(
                "loss.isometry_every must be >= 1 (1: the isometry term every step), got "
                f"{self.loss.isometry_every}"
            )
        if self.color_every < 1:
            raise ValueError(f"color_every must be >= 1 (1: every row every step), got {self.color_every}")
        if self.nonrigid not in NONRIGID_MODES:
            raise ValueError(f"nonrigid must be one of {NONRIGID_MODES}, got {self.nonrigid!r}")
        if not 0.0 <= self.pose_warmup <= 0.5:
            raise ValueError(
                f"pose_warmup must be in [0, 0.5] (a fraction of the run), got {self.pose_warmup}"
            )
        if self.pose_warmup_boost <= 0:
            raise ValueError(f"pose_warmup_boost must be > 0, got {self.pose_warmup_boost}")
        if self.densify.unseen_cell_m < 0 or self.densify.unseen_after_views < 1:
            raise ValueError(
                "densify.unseen_cell_m must be >= 0 (0: off) and densify.unseen_after_views >= 1, got "
                f"{self.densify.unseen_cell_m} and {self.densify.unseen_after_views}"
            )

    def replace(self, **changes) -> TrainConfig:
        """A copy with top-level fields or dotted sub-fields changed: replace(**{"model.color": "sh"})."""
        top: dict = {}
        nested: dict[str, dict] = {}
        for key, value in changes.items():
            if "." in key:
                group, name = key.split(".", 1)
                nested.setdefault(group, {})[name] = value
            else:
                top[key] = value
        for group, values in nested.items():
            top[group] = dataclasses.replace(getattr(self, group), **values)
        return dataclasses.replace(self, **top)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> TrainConfig:
        """From :meth:`to_dict`; a setting a stored config lacks (written before it existed) takes the
        value that reproduces what that run did (PREDATING_DEFAULTS), else its default."""
        data = dict(data)
        groups = {"model": ModelConfig, "loss": LossConfig, "densify": DensifyConfig}
        kwargs = {}
        for f in dataclasses.fields(cls):
            if f.name not in data:
                if f.name in PREDATING_DEFAULTS and f.name not in groups:
                    kwargs[f.name] = PREDATING_DEFAULTS[f.name]
                continue
            value = data[f.name]
            if f.name in groups:
                known = {g.name for g in dataclasses.fields(groups[f.name])}
                # Written before some settings existed: those take the value it trained with.
                value = {**PREDATING_DEFAULTS.get(f.name, {}), **value}
                value = groups[f.name](**{k: v for k, v in value.items() if k in known})
            kwargs[f.name] = value
        return cls(**kwargs)


def apply_settings(config: TrainConfig, items) -> TrainConfig:
    """``config`` with ``KEY=VALUE`` settings applied (``model.spacetime=false``, ``iterations=800``).

    Values are read as YAML scalars and must have the type of the setting they replace (an int
    is accepted for a float; a string setting takes a word YAML would read as a boolean as that
    word: ``nonrigid=off``), so a typo fails here with the known names rather than deep in a run.
    Raises ValueError.
    """
    import yaml

    changes = {}
    for item in items:
        key, sep, text = str(item).partition("=")
        key = key.strip()
        if not sep or not key:
            raise ValueError(f"{item!r}: expected KEY=VALUE, e.g. model.spacetime=false")
        current = _setting(config, key)
        try:
            value = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            raise ValueError(f"{key}: cannot read the value {text!r}") from exc
        if isinstance(current, str) and isinstance(value, bool):
            value = text.strip()  # YAML reads on/off/yes/no as booleans; a string setting means the word
        changes[key] = _same_type(key, value, current)
    try:
        return config.replace(**changes)
    except (TypeError, ValueError) as exc:
        raise ValueError(str(exc)) from exc


def _setting(config: TrainConfig, key: str):
    """The current value of a top-level or ``group.name`` setting; ValueError naming the known ones."""
    head, _, rest = key.partition(".")
    top = {f.name: getattr(config, f.name) for f in dataclasses.fields(config)}
    if head not in top:
        raise ValueError(f"unknown setting {key!r}; known: {', '.join(sorted(top))}")
    value = top[head]
    group = dataclasses.is_dataclass(value)
    if group and not rest:
        names = ", ".join(f"{head}.{f.name}" for f in dataclasses.fields(value))
        raise ValueError(f"{key!r} is a group; set one of its fields: {names}")
    if not group and rest:
        raise ValueError(f"unknown setting {key!r}: {head} has no fields")
    if rest:
        fields = {f.name for f in dataclasses.fields(value)}
        if rest not in fields:
            known = ", ".join(f"{head}.{name}" for name in sorted(fields))
            raise ValueError(f"unknown setting {key!r}; known in {head}: {known}")
        value = getattr(value, rest)
    return value


def _same_type(key: str, value, current):
    if current is None:
        return value
    if isinstance(current, bool):
        ok = isinstance(value, bool)
    elif isinstance(current, int):
        ok = isinstance(value, int) and not isinstance(value, bool)
    elif isinstance(current, float):
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        value = float(value) if ok else value
    elif isinstance(current, tuple):
        ok = isinstance(value, list)
        value = tuple(value) if ok else value
    else:
        ok = isinstance(value, type(current))
    if not ok:
        raise ValueError(f"{key}: expected {type(current).__name__} (now {current!r}), got {value!r}")
    return value
