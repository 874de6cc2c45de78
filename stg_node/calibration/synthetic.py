"""Synthetic ChArUco captures with known truth: a rig of cameras watching a board move.

What ``stg-calibrate`` is tested against (tests/calibration) and measured on
(tools/eval_calibration.py). Every image is rendered from the board's printable image by the
exact planar homography of its pose (supersampled, then area-averaged, so edges are
anti-aliased like a real sensor's), warped through the camera's lens distortion (OpenCV's
model, inverted per pixel with ``cv2.undistortPoints``), with sensor noise added. Nothing here
uses the calibration code, so agreement is evidence.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from stg_node.calibration.board import BoardSpec
from stg_node.calibration.rig import Rig, RigCamera

BACKGROUND = 128  # grey around the board
TEXTURE_PPM = 1000.0  # board texture resolution, pixels per metre (1 mm per pixel; about a supersample)


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera ``(R, t)`` of a camera at ``eye`` looking at ``target`` (OpenCV axes)."""
    eye = np.asarray(eye, dtype=np.float64)
    forward = np.asarray(target, dtype=np.float64) - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    R = np.stack([right, down, forward])
    return R, -R @ eye


def ring_rig(
    count: int,
    size: tuple[int, int] = (640, 480),
    radius: float = 2.5,
    height: float = 1.6,
    fov_deg: float = 60.0,
    distortion: bool = True,
    seed: int = 0,
    arc_deg: float = 360.0,
) -> Rig:
    """``count`` cameras on a ring around the origin (z up) looking at a point 1 m up, with a
    little variety in height, focal length, principal point and lens distortion (seeded);
    ``arc_deg`` < 360 spreads them over that arc in front of the origin (a rig on one side)."""
    rng = np.random.default_rng(seed)
    width, height_px = size
    cameras = []
    for k in range(count):
        if arc_deg >= 360.0:
            azimuth = 2 * np.pi * k / count + rng.uniform(-0.1, 0.1)
        else:
            span = np.radians(arc_deg)
            azimuth = -span / 2 + span * k / max(count - 1, 1) + rng.uniform(-0.05, 0.05)
        eye = np.array([radius * np.sin(azimuth), -radius * np.cos(azimuth), height + rng.uniform(-0.3, 0.3)])
        R, t = look_at(eye, (0.0, 0.0, 1.0))
        focal = (width / 2) / np.tan(np.radians(fov_deg + rng.uniform(-8, 8)) / 2)
        K = np.array(
            [
                [focal * rng.uniform(0.995, 1.005), 0.0, (width - 1) / 2 + rng.uniform(-12, 12)],
                [0.0, focal, (height_px - 1) / 2 + rng.uniform(-10, 10)],
                [0.0, 0.0, 1.0],
            ]
        )
        dist = (
            np.array(
                [
                    rng.uniform(-0.25, 0.05),
                    rng.uniform(-0.05, 0.1),
                    rng.uniform(-1e-3, 1e-3),
                    rng.uniform(-1e-3, 1e-3),
                    0.0,
                ]
            )
            if distortion
            else np.zeros(5)
        )
        cameras.append(RigCamera(f"cam{k + 1}", K, dist, R, t, (width, height_px)))
    return Rig(tuple(cameras))


def _rotation(axis_angle) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(axis_angle, dtype=np.float64).reshape(3, 1))[0]


def board_poses(
    count: int,
    spec: BoardSpec,
    seed: int = 0,
    centre=(0.0, 0.0, 1.0),
    spread_m: float = 0.4,
    rig: Rig | None = None,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """``count`` board-to-world poses ``(R, t)``: a person holding the board up near ``centre``,
    tilting it (up to ~30 degrees) and turning it: towards the middle of two neighbouring
    cameras of ``rig`` (as one does to calibrate a rig: each pair must see it together), or
    anywhere without a rig."""
    rng = np.random.default_rng(seed)
    width_m, height_m = spec.size_m
    azimuths = None
    if rig is not None and len(rig) > 1:
        centres = np.array([c.center for c in rig.cameras])
        azimuths = np.sort(np.arctan2(centres[:, 0] - centre[0], -(centres[:, 1] - centre[1])))
    poses = []
    for _ in range(count):
        if azimuths is None:
            yaw_angle = rng.uniform(-np.pi, np.pi)
        else:
            k = rng.integers(len(azimuths))
            a, b = azimuths[k], azimuths[(k + 1) % len(azimuths)]
            if (k + 1) % len(azimuths) == 0 and b < a:
                b += 2 * np.pi
            if b - a > np.pi:  # the gap behind an arc of cameras: face the pair's other side
                a, b = b, a + 2 * np.pi
            yaw_angle = 0.5 * (a + b) + rng.uniform(-0.25, 0.25)
        # Upright board whose face looks along -y (its z axis, into the board, along +y), turned
        # by the yaw (azimuth 0 looks at a camera on -y, counter-clockwise) and tilted.
        upright = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
        yaw = _rotation([0.0, 0.0, yaw_angle])
        tilt = _rotation([rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), 0.0])
        R = yaw @ tilt @ upright
        middle = np.array(centre) + rng.uniform(-spread_m, spread_m, 3) * np.array([1.0, 1.0, 0.6])
        t = middle - R @ np.array([width_m / 2, height_m / 2, 0.0])
        poses.append((R, t))
    return poses


_MAPS: dict = {}


def _distortion_map(camera: RigCamera, supersample: int) -> tuple[np.ndarray, np.ndarray]:
    """For each pixel of the distorted (supersampled) image, where it lies in the pinhole one."""
    key = (camera.K.tobytes(), camera.dist.tobytes(), camera.image_size, supersample)
    if key not in _MAPS:
        s = supersample
        K_ss = _supersampled(camera.K, s)
        width, height = camera.image_size[0] * s, camera.image_size[1] * s
        cols, rows = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
        distorted = np.stack([cols, rows], axis=-1).reshape(-1, 1, 2)
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-6)
        ideal = cv2.undistortPoints(distorted, K_ss, camera.dist, P=K_ss, criteria=criteria)
        ideal = ideal.reshape(height, width, 2).astype(np.float32)
        _MAPS.clear()  # one camera at a time is enough; the maps are large
        _MAPS[key] = (np.ascontiguousarray(ideal[..., 0]), np.ascontiguousarray(ideal[..., 1]))
    return _MAPS[key]


def _supersampled(K: np.ndarray, s: int) -> np.ndarray:
    """``K`` for an image ``s`` times larger (pixel-centre convention: c' = (c + 0.5) s - 0.5)."""
    out = K.copy()
    out[:2, :2] *= s
    out[:2, 2] = (K[:2, 2] + 0.5) * s - 0.5
    return out


def close_up_poses(
    camera: RigCamera, count: int, spec: BoardSpec, rng: np.random.Generator, distance_m=(0.7, 1.4)
) -> list[tuple[np.ndarray, np.ndarray]]:
    """``count`` board poses close in front of one camera, anywhere in its picture, tilted up to
    ~45 degrees: the part of a capture that pins down the camera's focal length and lens."""
    poses = []
    width, height = camera.image_size
    K_inv = np.linalg.inv(camera.K)
    world_from_camera = camera.R.T
    centre_board = np.array([spec.size_m[0] / 2, spec.size_m[1] / 2, 0.0])
    for _ in range(count):
        pixel = np.array([rng.uniform(0.15, 0.85) * width, rng.uniform(0.15, 0.85) * height, 1.0])
        ray = K_inv @ pixel
        ray /= np.linalg.norm(ray)
        depth = rng.uniform(*distance_m)
        # Facing the camera (board z along the ray, board x along the camera's x), then tilted.
        z = ray
        x = np.cross([0.0, 1.0, 0.0], z)
        x /= np.linalg.norm(x)
        facing = np.column_stack([x, np.cross(z, x), z])
        tilt = _rotation([rng.uniform(-0.7, 0.7), rng.uniform(-0.7, 0.7), rng.uniform(-0.5, 0.5)])
        R_cb = facing @ tilt
        t_cb = ray * depth - R_cb @ centre_board
        poses.append((world_from_camera @ R_cb, world_from_camera @ (t_cb - camera.t)))
    return poses


def render_board(
    camera: RigCamera,
    board_R: np.ndarray,
    board_t: np.ndarray,
    texture: np.ndarray,
    texture_ppm: float,
    *,
    supersample: int = 4,
    noise_std: float = 2.0,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """The grey uint8 image ``camera`` sees of a board at pose ``(board_R, board_t)`` (board to world)."""
    width, height = camera.image_size
    s = supersample
    K_ss = _supersampled(camera.K, s)
    R_cb = camera.R @ board_R
    t_cb = camera.R @ board_t + camera.t
    plane_to_image = K_ss @ np.column_stack([R_cb[:, 0], R_cb[:, 1], t_cb])
    texel_to_plane = np.array(
        [[1 / texture_ppm, 0, 0.5 / texture_ppm], [0, 1 / texture_ppm, 0.5 / texture_ppm], [0, 0, 1]]
    )
    homography = plane_to_image @ texel_to_plane
    size_ss = (width * s, height * s)
    if t_cb[2] <= 0 or np.linalg.det(R_cb) <= 0:
        pinhole = np.full(size_ss[::-1], BACKGROUND, np.uint8)
    else:
        pinhole = cv2.warpPerspective(
            texture,
            homography,
            size_ss,
            flags=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=BACKGROUND,
        )
        # A board seen from behind shows its grey back, not a mirrored pattern.
        if float(R_cb[:, 2] @ t_cb) < 0:
            pinhole[:] = BACKGROUND
    if np.any(camera.dist):
        map_x, map_y = _distortion_map(camera, s)
        pinhole = cv2.remap(
            pinhole, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=BACKGROUND
        )
    image = cv2.resize(pinhole, (width, height), interpolation=cv2.INTER_AREA).astype(np.float64)
    if noise_std > 0:
        image += (rng or np.random.default_rng(0)).normal(0.0, noise_std, image.shape)
    return np.clip(np.round(image), 0, 255).astype(np.uint8)


@dataclass(frozen=True)
class SyntheticCapture:
    """A rig, the board, and what each camera saw at each instant (truth included)."""

    rig: Rig
    spec: BoardSpec
    poses: list[tuple[np.ndarray, np.ndarray]]  # board-to-world per instant
    images: list[list[np.ndarray]]  # [instant][camera] grey uint8

    def write(self, folder) -> list:
        """One image folder per camera (``folder/NAME/000000.png`` ...); returns the folders."""
        from pathlib import Path

        folder = Path(folder)
        out = []
        for v, camera in enumerate(self.rig.cameras):
            path = folder / camera.name
            path.mkdir(parents=True, exist_ok=True)
            for i, views in enumerate(self.images):
                if not cv2.imwrite(str(path / f"{i:06d}.png"), views[v]):
                    raise OSError(f"could not write {path / f'{i:06d}.png'}")
            out.append(path)
        return out


def synthetic_capture(
    rig: Rig,
    spec: BoardSpec,
    count: int,
    seed: int = 0,
    noise_std: float = 2.0,
    supersample: int = 4,
    close_ups: int = 0,
) -> SyntheticCapture:
    """Render a capture: ``close_ups`` instants with the board close in front of each camera in
    turn (what a user does first, for the lenses), then ``count`` instants of the board moving
    in the middle of the rig, seen by several cameras at once (for the extrinsics)."""
    texture = spec.image(TEXTURE_PPM)
    rng = np.random.default_rng(seed + 1)
    poses = []
    for camera in rig.cameras:
        poses += close_up_poses(camera, close_ups, spec, rng)
    poses += board_poses(count, spec, seed, rig=rig)
    images: list[list] = [[None] * len(rig) for _ in poses]
    for v, camera in enumerate(rig.cameras):  # camera by camera: its distortion map is reused
        for i, (R, t) in enumerate(poses):
            images[i][v] = render_board(
                camera, R, t, texture, TEXTURE_PPM, supersample=supersample, noise_std=noise_std, rng=rng
            )
    return SyntheticCapture(rig, spec, poses, images)


def _rotation_error_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(a.T @ b) - 1) / 2, -1, 1))))


def rig_errors(estimated: Rig, truth: Rig) -> list[tuple[float, float]]:
    """(camera centre error in metres, rotation error in degrees) per camera, after the rigid motion
    that best aligns the estimated rig with the truth: the world frame is a choice (the first
    camera's, the board's); the rig's shape and size are what a calibration finds. Scale is not
    aligned (the board fixes it). The alignment's rotation is the chordal mean of the cameras'
    orientation differences, its translation the mean centre difference."""
    from stg_node.calibration.solve import mean_rotation

    # world_truth = A @ world_estimated + b; each camera's orientation gives A = R_true^T R_est.
    A = mean_rotation([tru.R.T @ est.R for est, tru in zip(estimated.cameras, truth.cameras, strict=True)])
    centres = np.array([c.center for c in estimated.cameras]) @ A.T
    true_centres = np.array([c.center for c in truth.cameras])
    centres = centres + (true_centres - centres).mean(axis=0)
    return [
        (float(np.linalg.norm(centre - tru.center)), _rotation_error_deg(est.R @ A.T, tru.R))
        for est, tru, centre in zip(estimated.cameras, truth.cameras, centres, strict=True)
    ]
