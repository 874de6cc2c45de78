"""Generates the synthetic benchmark: motion -> body -> garment -> cameras -> rasterized views -> ZJU layout.

:func:`generate` is what ``stg-synth`` runs. Everything is drawn from one seed through
independent ``numpy.random.SeedSequence`` children (motion, body shape, cameras), so changing
the number of held-out cameras does not change the motion, and the same seed and settings give
bit-identical files on the same machine and thread count. See docs/SYNTH.md.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

import stg_node
from stg_node.body.motion import drive_body
from stg_node.body.params import SmplSequence
from stg_node.data.synth import writer
from stg_node.data.synth.cameras import DEFAULT_DISTANCE_M, make_rig
from stg_node.data.synth.exposure import apply_gain, jitter_gains
from stg_node.data.synth.garment import GarmentParams, garment_regions, simulate_garment
from stg_node.data.synth.lighting import AMBIENT, DIFFUSE, LIGHT_DIRECTION_BODY, SHADING_MODES, lighting
from stg_node.data.synth.mesh_raster import TexturedMesh, render_mesh
from stg_node.data.synth.motions import DEFAULT_MOTION, MOTIONS, held_out_motions, make_motion
from stg_node.data.synth.occlusion import DEFAULT_DIRECTIONS, DEFAULT_TEXEL_M
from stg_node.data.synth.split_distances import held_out_distances, summarise
from stg_node.progress import progress as progress_bar

log = logging.getLogger(__name__)

__all__ = ["AMBIENT", "DIFFUSE", "LIGHT_DIRECTION_BODY", "SHADING_MODES", "SynthConfig", "generate"]
BODY_CHUNK_FRAMES = 64
MAX_PENDING_WRITES = 16


@dataclass(frozen=True)
class SynthConfig:
    """Everything that determines a generated benchmark (the output is a function of these)."""

    out: Path
    seed: int = 0
    num_frames: int = 300
    size: int = 512
    motion: str = DEFAULT_MOTION
    fps: float = 30.0
    num_novel_views: int = 8
    view_every: int = 30  # held-out cameras render every view_every-th frame (ZJU protocol: 30)
    train_fraction: float = 0.8  # the first frames train; the rest are held-out (novel) poses
    supersample: int = 2
    shading: str = "lambert"  # lighting.SHADING_MODES: lambert (turns with the body), none, room, environment
    self_shadow: bool = False  # the body occludes its own light (ambient occlusion, shadows: occlusion.py)
    # Held-out poses and orientations (motions.make_motion): the held-out frames' motion(s), e.g.
    # "crouch,arms_up" (None: a fresh draw of the training motion); the training frames' window of
    # orientations in degrees (None: at least one full turn); the held-out frames' turn from it.
    test_motion: str | None = None
    train_yaw_deg: float | None = None
    test_yaw_deg: float | None = None
    write_depth: bool = False
    cull_backfaces: bool = True
    betas_std: float = 0.5
    overwrite: bool = False
    garment: GarmentParams = field(default_factory=GarmentParams)
    # Multi-view training (docs/RIGS.md): 0-based cameras that render every frame, as camera 0
    # does; the others render every view_every-th frame.
    train_cameras: tuple[int, ...] = (0,)
    # Filming conditions (real footage): the rig's distance and field of view, and the training
    # camera's per-frame exposure / white-balance drift (exposure.py).
    camera_distance: float = DEFAULT_DISTANCE_M
    fov_deg: float | None = None  # None: each camera frames VIEW_HEIGHT_M at the subject
    exposure_jitter: float = 0.0  # std of the per-frame log exposure gain (0: steady)

    def validate(self) -> None:
        if self.motion not in MOTIONS:
            raise ValueError(f"unknown motion {self.motion!r}; choose one of {', '.join(MOTIONS)}")
        if self.shading not in SHADING_MODES:
            raise ValueError(f"unknown shading {self.shading!r}; choose one of {', '.join(SHADING_MODES)}")
        held_out_motions(self.test_motion)  # raises on an unknown name
        if self.train_yaw_deg is not None and not 0.0 <= self.train_yaw_deg < 360.0:
            raise ValueError(f"--train-yaw must be in [0, 360) degrees, got {self.train_yaw_deg}")
        if self.test_yaw_deg is not None and self.train_yaw_deg is None:
            raise ValueError(
                "--test-yaw needs --train-yaw (with a full turn in training no orientation is held out)"
            )
        if self.num_frames < 1:
            raise ValueError(f"--frames must be >= 1, got {self.num_frames}")
        if self.size < 8:
            raise ValueError(f"--size must be >= 8 pixels, got {self.size}")
        if self.num_novel_views < 0 or self.view_every < 1:
            raise ValueError("--views must be >= 0 and --view-every >= 1")
        if not 0.0 < self.train_fraction <= 1.0:
            raise ValueError(f"train_fraction must be in (0, 1], got {self.train_fraction}")
        if self.supersample < 1:
            raise ValueError(f"--supersample must be >= 1, got {self.supersample}")
        if not self.fps > 0:
            raise ValueError(f"--fps must be positive, got {self.fps}")
        count = self.num_novel_views + 1
        if not self.train_cameras or len(set(self.train_cameras)) != len(self.train_cameras):
            raise ValueError(f"--train-cameras must name distinct cameras, got {self.train_cameras}")
        outside = [k + 1 for k in self.train_cameras if not 0 <= k < count]
        if outside:
            raise ValueError(
                f"--train-cameras {outside}: the rig has cameras 1-{count} (--views {count - 1})"
            )
        if not 1.0 <= self.camera_distance <= 50.0:
            raise ValueError(f"--distance must be 1 to 50 metres, got {self.camera_distance}")
        if self.fov_deg is not None and not 10.0 <= self.fov_deg <= 120.0:
            raise ValueError(f"--fov must be 10 to 120 degrees, got {self.fov_deg}")
        if not 0.0 <= self.exposure_jitter <= 1.0:
            raise ValueError(f"--exposure-jitter must be 0 to 1 (a log-gain std), got {self.exposure_jitter}")

    @property
    def num_train_frames(self) -> int:
        return max(1, min(self.num_frames, int(round(self.train_fraction * self.num_frames))))


@dataclass
class SynthResult:
    out: Path
    metadata: dict
    num_views: int  # rendered (camera, frame) pairs
    timings: dict[str, float]  # seconds per stage


def held_out_frames(config: SynthConfig) -> list[int]:
    """Frames the held-out cameras render: every view_every-th of the training range, and of the rest.

    ``range(0, n_train, K)`` and ``range(n_train, N, K)``: exactly the frames of the loaders'
    novel-view and novel-pose splits (stg_node.data.splits with ``train_frames=(0, n_train)``).
    """
    n_train, every = config.num_train_frames, config.view_every
    return list(range(0, n_train, every)) + list(range(n_train, config.num_frames, every))


def render_schedule(config: SynthConfig) -> list[list[int]]:
    """Cameras per frame: the training cameras always, the held-out ones on :func:`held_out_frames`."""
    train = sorted(config.train_cameras)
    novel = [k for k in range(config.num_novel_views + 1) if k not in train]
    strided = set(held_out_frames(config))
    return [sorted(train + (novel if frame in strided else [])) for frame in range(config.num_frames)]


def split_spec(config: SynthConfig) -> dict[str, list[dict]]:
    """Train / novel-view / novel-pose splits as lists of {cameras, frames} products (0-based cameras).

    The same selections ``open_dataset(..., train_frames=FrameRange(0, n_train))`` makes, plus
    every held-out frame from the training camera (the monocular camera's own novel poses).
    """
    n_train = config.num_train_frames
    train = sorted(config.train_cameras)
    novel = [k for k in range(config.num_novel_views + 1) if k not in train]
    strided = held_out_frames(config)
    splits: dict[str, list[dict]] = {
        "train": [{"cameras": train, "frames": list(range(n_train))}],
        "novel_view": [],
        "novel_pose": [],
    }
    view_frames = [f for f in strided if f < n_train]
    if novel and view_frames:
        splits["novel_view"].append({"cameras": novel, "frames": view_frames})
    if n_train < config.num_frames:
        splits["novel_pose"].append({"cameras": train, "frames": list(range(n_train, config.num_frames))})
        pose_frames = [f for f in strided if f >= n_train]
        if novel and pose_frames:
            splits["novel_pose"].append({"cameras": novel, "frames": pose_frames})
    return splits


def _outward_faces(rest_vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, bool]:
    """Faces wound counter-clockwise seen from outside (positive signed volume); flipped if needed."""
    tri = rest_vertices[faces].astype(np.float64)
    volume = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0
    if volume >= 0:
        return faces, False
    return faces[:, [0, 2, 1]], True


def _body_forward(model, params: SmplSequence) -> np.ndarray:
    """World vertices (T, V, 3) float32 for every frame, in fixed-size chunks (deterministic)."""
    chunks = []
    with torch.no_grad():
        for lo in range(0, len(params), BODY_CHUNK_FRAMES):
            out = drive_body(model, params, frames=slice(lo, lo + BODY_CHUNK_FRAMES))
            chunks.append(out.vertices.detach().to(torch.float32).cpu().numpy())
    return np.concatenate(chunks, axis=0)


# Motions whose walking plants its feet. ``mixed`` (the benchmark's default subject, with a walking
# segment) keeps its sliding gait, so the figures recorded on it stay comparable.
PLANTED = ("walk", "approach")


def _body_joints(model, betas: np.ndarray, poses: np.ndarray, Rh: np.ndarray) -> np.ndarray:
    """World joints (T, 24, 3) float64 of ``model`` posed by ``poses`` and ``Rh`` (no translation),
    in the same chunks as :func:`_body_forward`: the skeleton the walks plant their feet with."""
    sequence = SmplSequence(poses=poses, Rh=Rh, Th=np.zeros_like(Rh), betas=betas)
    chunks = []
    with torch.no_grad():
        for lo in range(0, len(sequence), BODY_CHUNK_FRAMES):
            out = drive_body(model, sequence, frames=slice(lo, lo + BODY_CHUNK_FRAMES))
            chunks.append(out.joints.detach().to(torch.float64).cpu().numpy())
    return np.concatenate(chunks, axis=0)


def _lambert_shade(vertices: torch.Tensor, faces: torch.Tensor, Rh: np.ndarray) -> torch.Tensor:
    """The ``lambert`` mode's shade (light fixed in the body frame): lighting.lighting("lambert")."""
    return lighting("lambert").vertex_shade(vertices, faces, Rh)


def _clips(num_frames: int, cuts: tuple[int, ...]) -> list[tuple[int, int]]:
    """(start, stop) of the continuous clips a sequence with ``cuts`` is made of."""
    bounds = [0] + [c for c in cuts if 0 < c < num_frames] + [num_frames]
    return [(a, b) for a, b in zip(bounds[:-1], bounds[1:], strict=True) if b > a]


def _shading_record(light, self_shadow: bool = False) -> dict:
    """synth.json's ``shading``: the mode and its lights (the keys earlier versions wrote for
    ``lambert`` and ``none`` are kept as they were); ``self_shadow`` only where it is on."""
    if light.mode in ("lambert", "none"):
        record = {
            "mode": light.mode,
            "light_direction_body": LIGHT_DIRECTION_BODY.tolist(),
            "ambient": AMBIENT,
            "diffuse": DIFFUSE,
        }
    else:
        record = light.to_dict()
    if self_shadow and light.lit:
        record["self_shadow"] = {
            "ambient_occlusion_directions": DEFAULT_DIRECTIONS,
            "texel_m": DEFAULT_TEXEL_M,
        }
    return record


def _held_out_record(config: SynthConfig, motion, n_train: int) -> dict:
    """synth.json's ``held_out``: how the held-out frames differ from training, and by how much."""
    distances = held_out_distances(motion.poses, motion.Rh, range(n_train), range(n_train, config.num_frames))
    return {
        "test_motion": list(held_out_motions(config.test_motion)) or None,
        "train_yaw_deg": config.train_yaw_deg,
        "test_yaw_deg": config.test_yaw_deg,
        "cuts": list(motion.cuts),
        "summary": summarise(distances),
        "distances": [d.to_dict() for d in distances],
    }


def generate(config: SynthConfig, body=None, progress: bool = True) -> SynthResult:
    """Generate the benchmark described by ``config``; ``body`` defaults to the shipped open body."""
    config.validate()
    timings: dict[str, float] = {}
    t_start = time.perf_counter()
    if body is None:
        from stg_node.body import load_body_model

        body = load_body_model()
    if getattr(body, "uv", None) is None or getattr(body, "texture", None) is None:
        raise ValueError(
            f"body model {getattr(body, 'name', type(body).__name__)!r} has no uv/uv_faces/texture; "
            "stg-synth renders a textured body (the shipped open body has one)"
        )
    out = writer.prepare_output(Path(config.out), config.overwrite)

    # A fourth child for the exposure drift: the first three are those of spawn(3), unchanged.
    motion_seq, shape_seq, camera_seq, exposure_seq = np.random.SeedSequence(config.seed).spawn(4)
    n_train = config.num_train_frames
    betas = np.clip(
        np.random.default_rng(shape_seq).normal(0.0, config.betas_std, size=int(body.num_betas)),
        -3 * config.betas_std,
        3 * config.betas_std,
    ).astype(np.float32)
    motion = make_motion(
        config.motion,
        config.num_frames,
        config.fps,
        np.random.default_rng(motion_seq),
        n_train,
        betas=betas,
        test_motion=config.test_motion,
        train_yaw_deg=config.train_yaw_deg,
        test_yaw_deg=config.test_yaw_deg,
        # walks plant their feet (gait.py); the default mixed subject keeps its recorded walk
        skeleton=(lambda poses, Rh: _body_joints(body, betas, poses, Rh))
        if config.motion in PLANTED
        else None,
    )
    light = lighting(config.shading)
    cameras = make_rig(
        config.size,
        config.num_novel_views,
        np.random.default_rng(camera_seq),
        distance=config.camera_distance,
        fov_deg=config.fov_deg,
    )
    gains = jitter_gains(
        config.num_frames, n_train, config.exposure_jitter, config.fps, np.random.default_rng(exposure_seq)
    )

    # Skinned body; then lift every frame so its lowest vertex touches the floor (z = 0).
    t0 = time.perf_counter()
    skinned = _body_forward(body, motion)
    Th = motion.Th.copy()
    Th[:, 2] += -skinned[:, :, 2].min(axis=1)
    motion = dataclasses.replace(motion, Th=Th)
    skinned = _body_forward(body, motion)
    zero = np.zeros((1, 3), dtype=np.float32)
    with torch.no_grad():
        rest = body(
            betas=torch.as_tensor(betas[None]),
            poses=torch.zeros(1, 72),
            Rh=torch.as_tensor(zero),
            Th=torch.as_tensor(zero),
        )
    rest_vertices = rest.vertices[0].detach().cpu().numpy()
    rest_joints = rest.joints[0].detach().cpu().numpy()
    timings["body"] = time.perf_counter() - t0

    # Garment dynamics on top of skinning: the ground truth has it, the SMPL parameters do not.
    t0 = time.perf_counter()
    regions = garment_regions(rest_vertices, rest_joints, config.garment)
    offsets = np.concatenate(  # each clip starts at rest: a cut is a new recording
        [
            simulate_garment(skinned[a:b], regions.weight, config.fps, config.garment, regions.freq_scale)
            for a, b in _clips(config.num_frames, motion.cuts)
        ]
    )
    gt_vertices = skinned + offsets
    timings["garment"] = time.perf_counter() - t0

    faces, flipped = _outward_faces(
        rest_vertices, np.asarray(body.faces.cpu() if torch.is_tensor(body.faces) else body.faces)
    )
    uv = body.uv.cpu().numpy() if torch.is_tensor(body.uv) else np.asarray(body.uv)
    uv_faces = np.asarray(body.uv_faces.cpu() if torch.is_tensor(body.uv_faces) else body.uv_faces)
    if flipped:
        uv_faces = uv_faces[:, [0, 2, 1]]
        log.info("body faces are wound clockwise; flipped them for rendering")
    mesh = TexturedMesh.from_arrays(faces, uv, uv_faces, body.texture)

    schedule = render_schedule(config)
    num_views = sum(len(cams) for cams in schedule)
    writer.write_annots(out, cameras, config.num_frames)

    render_time = 0.0
    t_loop = time.perf_counter()
    pending: list[Future] = []
    bar = progress_bar(total=num_views, unit="view", desc="stg-synth", enabled=progress)
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="synth-writer") as pool:
        try:
            for frame, cams in enumerate(schedule):
                pending.append(pool.submit(writer.write_frame_smpl, out, frame, motion[frame]))
                pending.append(pool.submit(writer.write_frame_vertices, out, frame, gt_vertices[frame]))
                t0 = time.perf_counter()
                verts = torch.from_numpy(gt_vertices[frame])
                shade = light.vertex_shade(verts, mesh.faces, motion.Rh[frame], config.self_shadow)
                for k in cams:
                    result = render_mesh(
                        mesh,
                        verts,
                        cameras[k],
                        supersample=config.supersample,
                        vertex_shade=shade,
                        cull_backfaces=config.cull_backfaces,
                    )
                    depth = result.depth if config.write_depth else None
                    image = result.image
                    if k == 0 and config.exposure_jitter > 0:
                        image = apply_gain(image, gains[frame])
                    pending.append(pool.submit(writer.write_view, out, k, frame, image, result.mask, depth))
                    bar.update(1)
                render_time += time.perf_counter() - t0
                while len(pending) > MAX_PENDING_WRITES:
                    pending.pop(0).result()
            for job in pending:
                job.result()
        finally:
            bar.close()
    timings["render"] = render_time
    timings["render_and_write"] = time.perf_counter() - t_loop

    metadata = {
        "generator": "stg-synth",
        "stg_node_version": stg_node.__version__,
        "seed": int(config.seed),
        "motion": config.motion,
        "motion_segments": [
            {"name": seg.name, "start": seg.start, "stop": seg.stop} for seg in motion.segments
        ],
        "fps": float(config.fps),
        "num_frames": int(config.num_frames),
        "size": [int(config.size), int(config.size)],
        "image_format": "png",
        "supersample": int(config.supersample),
        "shading": _shading_record(light, config.self_shadow),
        "held_out": _held_out_record(config, motion, n_train),
        "world": {"up": [0.0, 0.0, 1.0], "floor_z": 0.0, "units": "metres"},
        "body": {
            "name": str(getattr(body, "name", type(body).__name__)),
            "num_vertices": int(rest_vertices.shape[0]),
            "num_faces": int(faces.shape[0]),
            "betas": betas.tolist(),
        },
        "garment": {
            **config.garment.to_dict(),
            "hem_vertices": int(regions.hem.sum()),
            "sleeve_vertices": int(regions.sleeves.sum()),
            "max_offset_written_m": float(np.linalg.norm(offsets, axis=-1).max()) if offsets.size else 0.0,
            "in_smpl_params": False,
            "in_new_vertices": True,
        },
        "cameras": [
            {"index": k, "name": cam.name, "role": "train" if k in config.train_cameras else "novel_view"}
            for k, cam in enumerate(cameras)
        ],
        "num_train_frames": n_train,
        "view_every": int(config.view_every),
        "splits": split_spec(config),
        "rendered": {
            cam.name: [frame for frame, cams in enumerate(schedule) if k in cams]
            for k, cam in enumerate(cameras)
        },
        "depth": {"written": bool(config.write_depth), "unit": "millimetre", "zero": "background"},
    }
    filmed = (config.camera_distance, config.fov_deg, config.exposure_jitter)
    if filmed != (DEFAULT_DISTANCE_M, None, 0.0):  # recorded when set (a default subject's file is as before)
        metadata["filming"] = {
            "camera_distance_m": float(config.camera_distance),
            "fov_deg": None if config.fov_deg is None else float(config.fov_deg),
            "exposure_jitter": float(config.exposure_jitter),
            "exposure_gains": gains.round(5).tolist() if config.exposure_jitter > 0 else None,
        }
    writer.write_metadata(out, metadata)
    timings["total"] = time.perf_counter() - t_start
    log.info(
        "wrote %d views of %d frames to %s in %.1f s (render %.1f s)",
        num_views,
        config.num_frames,
        out,
        timings["total"],
        render_time,
    )
    return SynthResult(out=out, metadata=metadata, num_views=num_views, timings=timings)
