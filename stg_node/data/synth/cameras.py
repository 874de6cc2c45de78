"""The synthetic benchmark's camera rig: one fixed monocular training camera and a ring of held-out views.

World frame as in ZJU-MoCap: z up, floor at z = 0, the subject starts facing -y. Camera 0
(``Camera_B1``) is the training camera, straight in front of the subject (azimuth 0, on
the -y axis). The held-out cameras stand on a ring around the subject at evenly spaced
azimuths, each jittered (seeded) in azimuth, distance, height and principal point the way a
real capture dome is never perfectly regular. All cameras look at a point at the height of
the subject's centre, have square pixels, no distortion (``D = 0``) and a focal length that
frames a ``view_height_m`` tall slice of the world at the subject's distance, or, given a field
of view, that field of view (``stg-synth --fov``). The ring's distance is ``stg-synth
--distance`` (default 3.5 m): closer, with a fixed field of view, films the subject larger.
"""

from __future__ import annotations

import numpy as np

from stg_node.data.types import Camera

DEFAULT_DISTANCE_M = 3.5
DEFAULT_HEIGHT_M = 1.3
TARGET = np.array([0.0, 0.0, 0.9])  # about the subject's centre
VIEW_HEIGHT_M = 2.4  # world height framed at the subject's distance
WORLD_UP = np.array([0.0, 0.0, 1.0])


def camera_name(index: int) -> str:
    """ZJU-MoCap's folder name of camera ``index`` (0-based): Camera_B1, Camera_B2, ..."""
    return f"Camera_B{index + 1}"


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = WORLD_UP) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera ``(R, t)`` (OpenCV axes) of a camera at ``eye`` looking at ``target``."""
    eye = np.asarray(eye, dtype=np.float64)
    forward = np.asarray(target, dtype=np.float64) - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-9:
        raise ValueError("camera looks straight along the up axis; choose another up vector")
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    R = np.stack([right, down, forward])  # rows: camera x, y, z axes in world coordinates
    return R, -R @ eye


def ring_camera(
    index: int,
    azimuth_rad: float,
    size: int,
    *,
    distance: float = DEFAULT_DISTANCE_M,
    height: float = DEFAULT_HEIGHT_M,
    principal_offset: tuple[float, float] = (0.0, 0.0),
    fov_deg: float | None = None,
) -> Camera:
    """A camera on the ring at ``azimuth_rad`` (0 = in front of the subject, on -y; counter-clockwise);
    ``fov_deg``: its field of view (square images: horizontal = vertical), else the framing rule."""
    eye = np.array([distance * np.sin(azimuth_rad), -distance * np.cos(azimuth_rad), height])
    R, t = look_at(eye, TARGET)
    range_to_target = float(np.linalg.norm(TARGET - eye))
    if fov_deg is not None:
        focal = (size / 2.0) / np.tan(np.radians(fov_deg) / 2.0)
    else:
        focal = size * range_to_target / VIEW_HEIGHT_M
    K = np.array(
        [
            [focal, 0.0, (size - 1) / 2.0 + principal_offset[0]],
            [0.0, focal, (size - 1) / 2.0 + principal_offset[1]],
            [0.0, 0.0, 1.0],
        ]
    )
    return Camera(K=K, R=R, t=t, width=size, height=size, name=camera_name(index))


def make_rig(
    size: int,
    num_novel_views: int,
    rng: np.random.Generator,
    *,
    distance: float = DEFAULT_DISTANCE_M,
    fov_deg: float | None = None,
) -> list[Camera]:
    """Camera 0 = the training camera, then ``num_novel_views`` held-out cameras around the subject,
    all ``distance`` metres away (the held-out ones jittered) with field of view ``fov_deg`` (None:
    each frames ``VIEW_HEIGHT_M`` at the subject)."""
    if size < 8:
        raise ValueError(f"image size must be at least 8 pixels, got {size}")
    if num_novel_views < 0:
        raise ValueError(f"num_novel_views must be >= 0, got {num_novel_views}")
    cameras = [ring_camera(0, 0.0, size, distance=distance, fov_deg=fov_deg)]
    spacing = 2 * np.pi / (num_novel_views + 1)
    for k in range(1, num_novel_views + 1):
        jitter = rng.uniform(-1.0, 1.0, size=5)
        cameras.append(
            ring_camera(
                k,
                k * spacing + 0.15 * spacing * jitter[0],
                size,
                distance=distance + 0.3 * jitter[1],
                height=DEFAULT_HEIGHT_M + 0.4 * jitter[2],
                principal_offset=(0.015 * size * jitter[3], 0.015 * size * jitter[4]),
                fov_deg=fov_deg,
            )
        )
    return cameras
