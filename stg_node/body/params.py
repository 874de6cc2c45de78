"""SMPL parameters, one type for them: a frame (:class:`SmplParams`), a sequence (:class:`SmplSequence`).

Every part that holds a body pose uses these: datasets deliver a :class:`SmplParams` per frame,
pose files read into a :class:`SmplSequence` (:mod:`stg_node.body.motion`), the synthetic
benchmark generates one, the trainer and renderer take them. On the bus the same numbers travel
as ``BodyPose``; ``BodyPose.from_smpl(params)`` and ``pose.to_smpl()`` in
:mod:`stg_node.bus.messages` are the one conversion, exact both ways.

Conventions (docs/BODY.md): SMPL's 24 joints in SMPL order; ``poses`` per-joint axis-angle in
radians, ``poses[0]`` SMPL's own global orientation about the pelvis; the body is placed in a
dataset's world as ZJU-MoCap / EasyMocap do, ``world = R(Rh) @ smpl(betas, poses) + Th`` with
``Rh`` axis-angle and ``Th`` in metres. Arrays are numpy float32 (a ``(72,)`` pose is reshaped
to ``(24, 3)``); shapes and finiteness are checked on construction and a bad value raises a
``ValueError`` naming the field.

numpy only: importing this module imports neither torch nor the bus (tests/bus checks it).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from stg_node.body.smpl_io import SMPL_NUM_JOINTS

#: body model tags: "smplx" where a dataset only ships SMPL-X fits (THuman4.0); the 22 shared joints
#: map over, but SMPL-X betas span another shape space.
MODEL_TAGS = ("smpl", "smplx")


#: The largest magnitude a value of each field can plausibly have: far beyond any real capture
#: (radians for poses and Rh, metres for Th, shape units for betas), far below what breaks the
#: arithmetic downstream (a pose of 1e30 is finite, and turns into NaN vertices). One place:
#: the datasets' readers check the same limits (stg_node.data.base).
LIMITS = {"poses": 1e3, "Rh": 1e3, "Th": 1e4, "betas": 1e3}


def magnitude_problem(name: str, array: np.ndarray) -> str:
    """Why ``array`` (finite) is not a plausible value of SMPL field ``name`` (empty: it is)."""
    limit = LIMITS.get(name.split("/")[0])
    peak = float(np.abs(array).max()) if limit is not None and array.size else 0.0
    if peak > limit:
        unit = {"Th": " m", "poses": " rad", "Rh": " rad"}.get(name, "")
        return f"{name} has values up to {peak:.3g}{unit}, beyond the plausible +-{limit:g}{unit}"
    return ""


def _float32(value, name: str, shape: tuple, owner: str) -> np.ndarray:
    """``value`` as a finite, plausibly sized float32 array of ``shape`` (None = any length
    there), else ValueError."""
    try:
        array = np.asarray(value, dtype=np.float32)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{owner}.{name} is not numeric ({exc})") from None
    fits = array.ndim == len(shape) and all(
        want is None or got == want for got, want in zip(array.shape, shape, strict=True)
    )
    if not fits:
        dims = ["N" if d is None else str(d) for d in shape]
        wanted = f"({dims[0]},)" if len(dims) == 1 else f"({', '.join(dims)})"
        raise ValueError(f"{owner}.{name} has shape {array.shape}, expected {wanted}")
    if not np.isfinite(array).all():
        raise ValueError(f"{owner}.{name} contains NaN or infinite values")
    problem = magnitude_problem(name, array)
    if problem:
        raise ValueError(f"{owner}.{problem}")
    return array


def _check_model(model: str, owner: str) -> None:
    if model not in MODEL_TAGS:
        raise ValueError(f"{owner}.model must be one of {MODEL_TAGS}, got {model!r}")


@dataclass(frozen=True, eq=False)
class SmplParams:
    """SMPL parameters of one frame (``world = R(Rh) @ smpl(betas, poses) + Th``)."""

    poses: np.ndarray  # (24, 3) float32 axis-angle per joint, radians; poses[0] = global orientation
    Rh: np.ndarray  # (3,) float32 axis-angle global rotation, radians
    Th: np.ndarray  # (3,) float32 global translation, metres
    betas: np.ndarray  # (S,) float32 shape coefficients, S >= 1
    model: str = "smpl"  # MODEL_TAGS: which body model the numbers belong to

    def __post_init__(self):
        poses = np.asarray(self.poses)
        if poses.shape == (SMPL_NUM_JOINTS * 3,):
            poses = poses.reshape(SMPL_NUM_JOINTS, 3)
        set_ = object.__setattr__
        set_(self, "poses", _float32(poses, "poses", (SMPL_NUM_JOINTS, 3), "SmplParams"))
        set_(self, "Rh", _float32(self.Rh, "Rh", (3,), "SmplParams"))
        set_(self, "Th", _float32(self.Th, "Th", (3,), "SmplParams"))
        set_(self, "betas", _float32(self.betas, "betas", (None,), "SmplParams"))
        if self.betas.size == 0:
            raise ValueError("SmplParams.betas is empty; expected at least one shape coefficient")
        _check_model(self.model, "SmplParams")


@dataclass(frozen=True, eq=False)
class SmplSequence:
    """SMPL parameters of T frames: the fields of :class:`SmplParams` with a leading frame axis.

    ``len(seq)`` is T; ``seq[i]`` is frame i as a :class:`SmplParams`; ``seq[a:b]`` (or a list of
    indices) is a shorter :class:`SmplSequence`. ``betas`` is one shape for the whole sequence
    (S,) or one per frame (T, S). ``dataclasses.replace(seq, Th=...)`` checks the new fields too.
    """

    poses: np.ndarray  # (T, 24, 3) float32; a (T, 72) input is reshaped
    Rh: np.ndarray  # (T, 3) float32
    Th: np.ndarray  # (T, 3) float32, metres
    betas: np.ndarray  # (S,) or (T, S) float32
    fps: float | None = None  # frame rate, where the source says it
    source: str = ""  # where the sequence came from (a path, a generator), for messages
    model: str = "smpl"

    def __post_init__(self):
        poses = np.asarray(self.poses)
        if poses.ndim == 2 and poses.shape[1] == SMPL_NUM_JOINTS * 3:
            poses = poses.reshape(len(poses), SMPL_NUM_JOINTS, 3)
        set_ = object.__setattr__
        owner = f"{self.source}: SmplSequence" if self.source else "SmplSequence"  # the file, if any
        set_(self, "poses", _float32(poses, "poses", (None, SMPL_NUM_JOINTS, 3), owner))
        count = len(self.poses)
        set_(self, "Rh", _float32(self.Rh, "Rh", (count, 3), owner))
        set_(self, "Th", _float32(self.Th, "Th", (count, 3), owner))
        betas = np.asarray(self.betas)
        betas = _float32(betas, "betas", (None,) if betas.ndim == 1 else (count, None), owner)
        if betas.shape[-1] == 0:
            raise ValueError("SmplSequence.betas is empty; expected at least one shape coefficient")
        set_(self, "betas", betas)
        if self.fps is not None and not (np.isfinite(self.fps) and self.fps > 0):
            raise ValueError(f"SmplSequence.fps must be positive, got {self.fps}")
        _check_model(self.model, "SmplSequence")

    @classmethod
    def from_frames(
        cls, frames: Sequence[SmplParams], fps: float | None = None, source: str = ""
    ) -> SmplSequence:
        """Stack single frames (same model and number of betas) into a sequence; betas (T, S)."""
        if not frames:
            raise ValueError("SmplSequence.from_frames needs at least one frame")
        models = {f.model for f in frames}
        sizes = {f.betas.size for f in frames}
        if len(models) > 1 or len(sizes) > 1:
            raise ValueError(f"frames mix body models {sorted(models)} or beta counts {sorted(sizes)}")
        return cls(
            poses=np.stack([f.poses for f in frames]),
            Rh=np.stack([f.Rh for f in frames]),
            Th=np.stack([f.Th for f in frames]),
            betas=np.stack([f.betas for f in frames]),
            fps=fps,
            source=source,
            model=frames[0].model,
        )

    def __len__(self) -> int:
        return int(self.poses.shape[0])

    @property
    def betas_per_frame(self) -> np.ndarray:
        """(T, S) betas, the single shape repeated where the sequence has one."""
        if self.betas.ndim == 2:
            return self.betas
        return np.broadcast_to(self.betas, (len(self), self.betas.size))

    def frame(self, index: int) -> SmplParams:
        """Frame ``index`` (negative counts from the end) as :class:`SmplParams`."""
        count = len(self)
        if not -count <= index < count:
            raise IndexError(f"frame {index} out of range for a sequence of {count} frames ({self.source})")
        betas = self.betas[index] if self.betas.ndim == 2 else self.betas
        return SmplParams(self.poses[index], self.Rh[index], self.Th[index], betas, self.model)

    def __getitem__(self, index):
        if isinstance(index, (int, np.integer)):
            return self.frame(int(index))
        selected = np.arange(len(self))[index]
        selected = np.atleast_1d(selected)
        betas = self.betas[selected] if self.betas.ndim == 2 else self.betas
        return SmplSequence(
            self.poses[selected],
            self.Rh[selected],
            self.Th[selected],
            betas,
            self.fps,
            self.source,
            self.model,
        )

    def __iter__(self):
        for index in range(len(self)):
            yield self.frame(index)


#: SMPL-X and SMPL share the pelvis and the 21 body joints that follow it in SMPL order (0-21);
#: SMPL's joints 22 and 23 are its hands, which SMPL-X models with finger joints instead.
SHARED_BODY_JOINTS = 22
#: Shape coefficients of the mean-shape betas an SMPL-X fit is given when converted (SMPL's count).
SMPL_NUM_BETAS = 10


def smplx_as_smpl(params: SmplParams, num_betas: int = SMPL_NUM_BETAS) -> SmplParams:
    """SMPL-X parameters (``model="smplx"``, THuman4.0's fits) as the nearest SMPL ones.

    The global orientation and the 21 body joints are the same joints with the same parent
    chain in both models, so ``poses[:22]``, ``Rh`` and ``Th`` carry over; SMPL's hand joints
    (22, 23) are set to rest. The betas do not: SMPL-X's shape space is another PCA basis, so
    its coefficients on an SMPL body give an unrelated shape; they become ``num_betas`` zeros
    (SMPL's mean shape). Not corrected (it needs the SMPL-X model file, which we do not ship):
    the two templates put the pelvis a few centimetres apart, so the SMPL body sits where
    SMPL's mean pelvis is, not exactly where the fit's pelvis was. SMPL parameters come back
    unchanged.
    """
    if params.model == "smpl":
        return params
    if params.model != "smplx":
        raise ValueError(f"smplx_as_smpl converts SMPL-X parameters, got {params.model!r} ones")
    if num_betas < 1:
        raise ValueError(f"num_betas must be at least 1, got {num_betas}")
    poses = np.array(params.poses, dtype=np.float32)
    poses[SHARED_BODY_JOINTS:] = 0.0
    return SmplParams(poses, params.Rh, params.Th, np.zeros(num_betas, np.float32), "smpl")
