"""Rig calibration from board detections: intrinsics per camera, extrinsics, one joint refinement.

Input: for each synchronised instant and each camera, the board corners it identified (or
nothing). Steps:

1. **Intrinsics** per camera: ``cv2.calibrateCamera`` (Zhang's method, OpenCV's 5-coefficient
   lens model) on up to ``max_views`` of its detections, spread over the capture.
2. **Board poses**: ``cv2.solvePnP`` of every detection with its camera's intrinsics.
3. **Extrinsics**: camera pairs that saw the board at the same instant give their relative pose
   (one per shared instant; the chordal mean of the rotations and the median translation, after
   dropping instants that disagree); the rig's cameras are joined to the first through the pairs
   sharing the most instants (a spanning tree), so a camera that never sees the board together
   with the first still calibrates through a neighbour. Cameras the tree cannot reach are an
   error that names them.
4. **Bundle adjustment**: every camera's pose (the first held at the origin), intrinsics and
   distortion, and every instant's board pose, refined together by ``scipy.optimize
   .least_squares`` on the reprojection error of every corner in every view (soft-L1 loss, scale
   1 px, so a wrong corner does not drag the rest), with the Jacobian's sparsity given.

The world is the first camera's frame (``x_world = x_cam1``), unless ``origin="board"``: then it
is the board as it lay at the first instant a camera saw it, turned so that z points out of its
face (a board lying face up on the floor gives a z-up world on the floor, as ZJU-MoCap's).
"""

from __future__ import annotations

import logging
from collections import defaultdict
from dataclasses import dataclass, field

import cv2
import numpy as np

from stg_node.calibration.board import BoardDetection, BoardSpec
from stg_node.calibration.rig import Rig, RigCamera

log = logging.getLogger(__name__)

ORIGINS = ("camera", "board")
MIN_VIEWS = 4  # detections a camera needs for its intrinsics
VIEW_OUTLIER_FACTOR = 3.0  # a view whose error is this x the median view's is left out of the intrinsics
OUTLIER_FACTOR = 5.0  # a corner further off than this x its camera's median error is rejected ...
OUTLIER_MIN_PX = 1.0  # ... if it is also further off than this
MAX_ITERATIONS = 100  # Levenberg-Marquardt steps per bundle-adjustment pass
DIST_TERMS = 5  # k1, k2, p1, p2, k3
# The board's frame -> a world with z out of the board's face (rotation of pi about x).
FLIP_Z = np.diag([1.0, -1.0, -1.0])


class CalibrationError(ValueError):
    """The captures cannot calibrate the rig; the message names the camera and what it lacks."""


@dataclass(frozen=True)
class CameraReport:
    name: str
    views: int  # instants with a usable detection
    corners: int  # corners used
    rms_px: float  # RMS reprojection error after the joint refinement
    max_px: float  # the largest corner error
    intrinsics_rms_px: float  # RMS of the camera's own intrinsic calibration (step 1)
    rejected: int = 0  # corners left out as outliers


@dataclass(frozen=True)
class CalibrationResult:
    rig: Rig
    reports: tuple[CameraReport, ...]
    instants: int  # instants with at least one detection
    shared: dict = field(default_factory=dict)  # "a|b" -> instants both saw the board

    @property
    def rms_px(self) -> float:
        squares = sum(r.rms_px**2 * r.corners for r in self.reports)
        return float(np.sqrt(squares / max(1, sum(r.corners for r in self.reports))))


def _pose_matrix(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def _invert(T: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


def _rodrigues(vector: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(vector, dtype=np.float64).reshape(3, 1))[0]


def _vector(R: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(R, dtype=np.float64))[0].reshape(3)


def mean_rotation(rotations: list[np.ndarray]) -> np.ndarray:
    """The chordal L2 mean: the rotation nearest to the sum of the matrices."""
    u, _, vt = np.linalg.svd(np.sum(rotations, axis=0))
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    return u @ np.diag([1.0, 1.0, d]) @ vt


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    cosine = (np.trace(a.T @ b) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))))


def project(points: np.ndarray, rvec, tvec, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """(N, 2) pixels of (N, 3) points under OpenCV's 5-coefficient model (vectorised; the tests
    check it against ``cv2.projectPoints``). ``rvec``/``tvec`` map the points into the camera."""
    R = _rodrigues(rvec)
    cam = points @ R.T + np.asarray(tvec).reshape(1, 3)
    z = np.where(np.abs(cam[:, 2]) < 1e-9, 1e-9, cam[:, 2])
    x, y = cam[:, 0] / z, cam[:, 1] / z
    k1, k2, p1, p2, k3 = (list(np.asarray(dist).reshape(-1)) + [0.0] * DIST_TERMS)[:DIST_TERMS]
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([K[0, 0] * xd + K[0, 1] * yd + K[0, 2], K[1, 1] * yd + K[1, 2]], axis=1)


def _intrinsics(name: str, detections: list[BoardDetection], image_size, max_views: int, k3: bool):
    """Zhang calibration of one camera on up to ``max_views`` detections spread over the capture;
    views it cannot explain (more than VIEW_OUTLIER_FACTOR x the median view error and more than
    1 px: a blurred or misdetected board) are dropped and the calibration repeated."""
    if len(detections) < MIN_VIEWS:
        raise CalibrationError(
            f"camera {name!r} saw the board at {len(detections)} instant(s); it needs at least {MIN_VIEWS} "
            "(hold the board in its view longer, at several angles and distances)"
        )
    chosen = detections
    if len(detections) > max_views:
        picks = np.linspace(0, len(detections) - 1, max_views).round().astype(int)
        chosen = [detections[i] for i in picks]
    flags = 0 if k3 else cv2.CALIB_FIX_K3
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-9)
    for _round in range(3):
        objects = [d.object_points.astype(np.float32) for d in chosen]
        images = [d.image_points.astype(np.float32).reshape(-1, 1, 2) for d in chosen]
        try:
            rms, K, dist, _, _, _, _, per_view = cv2.calibrateCameraExtended(
                objects, images, tuple(int(v) for v in image_size), None, None, flags=flags, criteria=criteria
            )
        except cv2.error as exc:
            raise CalibrationError(f"camera {name!r}: OpenCV's calibrateCamera failed ({exc})") from exc
        per_view = np.asarray(per_view).reshape(-1)
        good = per_view <= max(1.0, VIEW_OUTLIER_FACTOR * float(np.median(per_view)))
        if good.all() or good.sum() < MIN_VIEWS:
            break
        log.info(
            "camera %s: %d of %d views do not fit its lens; calibrating again without them",
            name,
            int((~good).sum()),
            len(chosen),
        )
        chosen = [d for d, g in zip(chosen, good, strict=True) if g]
    return float(rms), K, np.asarray(dist, dtype=np.float64).reshape(-1)[:DIST_TERMS]


def _board_pose(detection: BoardDetection, K, dist) -> np.ndarray | None:
    ok, rvec, tvec = cv2.solvePnP(
        detection.object_points, detection.image_points, K, dist, flags=cv2.SOLVEPNP_ITERATIVE
    )
    if not ok or tvec[2, 0] <= 0:
        return None
    return _pose_matrix(_rodrigues(rvec), tvec.reshape(3))


def _relative_pose(pairs: list[np.ndarray]) -> tuple[np.ndarray, int]:
    """Robust mean of per-instant relative poses (4x4): drop the ones that disagree, average the rest."""
    rotations = [T[:3, :3] for T in pairs]
    translations = np.array([T[:3, 3] for T in pairs])
    centre_R = mean_rotation(rotations)
    centre_t = np.median(translations, axis=0)
    angle = np.array([_angle_deg(R, centre_R) for R in rotations])
    offset = np.linalg.norm(translations - centre_t, axis=1)
    keep = (angle <= max(3.0, 3 * np.median(angle))) & (offset <= max(0.03, 3 * np.median(offset)))
    if keep.sum() == 0:
        keep[:] = True
    R = mean_rotation([r for r, k in zip(rotations, keep, strict=True) if k])
    return _pose_matrix(R, np.median(translations[keep], axis=0)), int(keep.sum())


def _spanning_tree(names: list[str], shared: dict[tuple[int, int], list[int]]) -> dict[int, int]:
    """Parent of each camera on the way to camera 0, joining through the pairs with the most
    shared instants first (maximum spanning tree, Prim's)."""
    parent = {0: -1}
    while len(parent) < len(names):
        best = None
        for (a, b), instants in shared.items():
            for inside, outside in ((a, b), (b, a)):
                if inside in parent and outside not in parent and (best is None or len(instants) > best[0]):
                    best = (len(instants), inside, outside)
        if best is None:
            lonely = [names[i] for i in range(len(names)) if i not in parent]
            raise CalibrationError(
                f"camera(s) {lonely} never saw the board at the same instant as {names[0]!r} or a camera "
                "joined to it: show the board so that neighbouring cameras see it together"
            )
        parent[best[2]] = best[1]
    return parent


def calibrate_rig(
    names: list[str],
    image_sizes: list[tuple[int, int]],
    detections: list[list[BoardDetection | None]],
    spec: BoardSpec,
    *,
    origin: str = "camera",
    max_intrinsic_views: int = 40,
    refine_intrinsics: bool = True,
    k3: bool = False,
    joint_refinement: bool = True,
) -> CalibrationResult:
    """Calibrate from ``detections[instant][camera]`` (None where a camera saw no board).

    ``k3``: fit the third radial coefficient too (wide-angle lenses); by default it is held at 0,
    as for most webcam and machine-vision lenses, where fitting it trades a better fit at the
    image corners for worse extrinsics (synthetic truth: camera centres 3-4 cm off instead of
    under 1 cm when the board never reached the corners). ``joint_refinement=False`` stops after
    step 3 (each camera's own intrinsics, extrinsics chained through shared sightings): the
    baseline tools/eval_calibration.py measures the bundle adjustment against."""
    if origin not in ORIGINS:
        raise ValueError(f"origin must be one of {ORIGINS}, got {origin!r}")
    count = len(names)
    if count < 1 or len(image_sizes) != count:
        raise ValueError("need one image size per camera name")
    if any(len(row) != count for row in detections):
        raise ValueError("each instant needs one detection slot per camera")
    per_camera = [
        [(i, row[v]) for i, row in enumerate(detections) if row[v] is not None] for v in range(count)
    ]

    # 1. intrinsics
    intrinsics = []
    for v, name in enumerate(names):
        rms, K, dist = _intrinsics(
            name, [d for _, d in per_camera[v]], image_sizes[v], max_intrinsic_views, k3
        )
        log.info("camera %s: %d views, intrinsic RMS %.3f px", name, len(per_camera[v]), rms)
        intrinsics.append((rms, K, dist))

    # 2. board poses per camera and instant (board -> camera)
    poses: dict[tuple[int, int], np.ndarray] = {}
    for v in range(count):
        _, K, dist = intrinsics[v]
        for i, detection in per_camera[v]:
            T = _board_pose(detection, K, dist)
            if T is not None:
                poses[(v, i)] = T

    # 3. extrinsics through a spanning tree of camera pairs
    seen_by: dict[int, list[int]] = defaultdict(list)
    for v, i in poses:
        seen_by[i].append(v)
    shared: dict[tuple[int, int], list[int]] = defaultdict(list)
    for i, cams in seen_by.items():
        for a in cams:
            for b in cams:
                if a < b:
                    shared[(a, b)].append(i)
    parent = _spanning_tree(names, shared)
    camera_from_world = {0: np.eye(4)}  # world = camera 0 for now
    order = sorted(parent, key=lambda v: _depth(parent, v))
    for v in order[1:]:
        p = parent[v]
        key = (min(v, p), max(v, p))
        # T_v<-p at instant i = T_v<-board (i) @ inverse(T_p<-board (i))
        relative = [poses[(v, i)] @ _invert(poses[(p, i)]) for i in shared[key]]
        T_vp, used = _relative_pose(relative)
        camera_from_world[v] = T_vp @ camera_from_world[p]
        log.info(
            "camera %s joined through %s over %d of %d shared instants",
            names[v],
            names[p],
            used,
            len(relative),
        )

    # board -> world per instant (from the camera with the most corners that saw it)
    board_in_world: dict[int, np.ndarray] = {}
    for i, cams in seen_by.items():
        v = max(cams, key=lambda c: len(detections[i][c]))
        board_in_world[i] = _invert(camera_from_world[v]) @ poses[(v, i)]

    # 4. bundle adjustment
    cameras, board_in_world, residuals, rejected = _bundle_adjust(
        names,
        intrinsics,
        camera_from_world,
        board_in_world,
        detections,
        refine_intrinsics,
        k3,
        MAX_ITERATIONS if joint_refinement else 0,
    )

    # world frame
    if origin == "board":
        first = min(board_in_world)
        world_from_board = _pose_matrix(FLIP_Z, np.zeros(3))
        old_from_new = board_in_world[first] @ _invert(world_from_board)  # new world -> old world
        cameras = [(K, dist, T @ old_from_new) for K, dist, T in cameras]

    rig_cameras = []
    reports = []
    for v, name in enumerate(names):
        K, dist, T = cameras[v]
        errors = residuals[v]
        rig_cameras.append(
            RigCamera(name, K, dist, T[:3, :3], T[:3, 3], tuple(int(x) for x in image_sizes[v]))
        )
        rms = float(np.sqrt(np.mean(errors**2))) if errors.size else float("nan")
        reports.append(
            CameraReport(
                name,
                len(per_camera[v]),
                int(errors.size),
                rms,
                float(errors.max()) if errors.size else float("nan"),
                intrinsics[v][0],
                rejected[v],
            )
        )
    calibration = {
        "method": "ChArUco, OpenCV calibrateCamera per camera, joint bundle adjustment",
        "board": spec.to_json(),
        "origin": "first camera" if origin == "camera" else "board at its first sighting, z out of its face",
        "instants": len(seen_by),
        "cameras": {
            r.name: {
                "views": r.views,
                "corners": r.corners,
                "rejected": r.rejected,
                "rms_px": round(r.rms_px, 4),
                "max_px": round(r.max_px, 4),
            }
            for r in reports
        },
    }
    return CalibrationResult(
        Rig(tuple(rig_cameras), calibration),
        tuple(reports),
        len(seen_by),
        {f"{names[a]}|{names[b]}": len(v) for (a, b), v in shared.items()},
    )


def _depth(parent: dict[int, int], v: int) -> int:
    depth = 0
    while parent[v] != -1:
        v, depth = parent[v], depth + 1
    return depth


def _rotations(vectors: np.ndarray) -> np.ndarray:
    """(N, 3) axis-angle -> (N, 3, 3) rotation matrices (Rodrigues, vectorised)."""
    vectors = np.asarray(vectors, dtype=np.float64).reshape(-1, 3)
    theta = np.linalg.norm(vectors, axis=1)
    safe = np.where(theta < 1e-12, 1.0, theta)
    k = vectors / safe[:, None]
    kx, ky, kz = k[:, 0], k[:, 1], k[:, 2]
    zero = np.zeros_like(kx)
    cross = np.stack([zero, -kz, ky, kz, zero, -kx, -ky, kx, zero], axis=1).reshape(-1, 3, 3)
    sin, cos = np.sin(theta)[:, None, None], np.cos(theta)[:, None, None]
    out = np.eye(3)[None] + sin * cross + (1 - cos) * (cross @ cross)
    small = theta < 1e-12
    out[small] = np.eye(3)
    return out


def _project_batch(cam_points: np.ndarray, K4: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Per-point projection: cam_points (M, 3), K4 (M, 4) = fx, fy, cx, cy, dist (M, 5)."""
    z = np.where(np.abs(cam_points[:, 2]) < 1e-9, 1e-9, cam_points[:, 2])
    x, y = cam_points[:, 0] / z, cam_points[:, 1] / z
    k1, k2, p1, p2, k3 = dist.T
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([K4[:, 0] * xd + K4[:, 2], K4[:, 1] * yd + K4[:, 3]], axis=1)


class _Problem:
    """The bundle-adjustment problem in arrays: every corner of every view, with the indices of
    its camera and board pose; parameters as a (C, 15) camera table (pose 6, fx fy cx cy, 5
    distortion terms) and a (B, 6) board table (pose, board -> world)."""

    def __init__(
        self, obj, img, cam_of, board_of, cameras: np.ndarray, boards: np.ndarray, free_cam: np.ndarray
    ):
        self.obj, self.img, self.cam_of, self.board_of = obj, img, cam_of, board_of
        self.cameras, self.boards = cameras, boards
        self.free_cam = free_cam  # (C, 15) bool: which camera parameters move

    def residuals(self, cameras: np.ndarray, boards: np.ndarray) -> np.ndarray:
        """(M, 2) predicted minus detected pixels."""
        cam_R, board_R = _rotations(cameras[:, :3]), _rotations(boards[:, :3])
        world = np.einsum("mij,mj->mi", board_R[self.board_of], self.obj) + boards[self.board_of, 3:]
        cam = np.einsum("mij,mj->mi", cam_R[self.cam_of], world) + cameras[self.cam_of, 3:6]
        c = cameras[self.cam_of]
        return _project_batch(cam, c[:, 6:10], c[:, 10:15]) - self.img


def _levenberg_marquardt(
    problem: _Problem, iterations: int, keep: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Robust (Cauchy, 1 px) Levenberg-Marquardt with the board poses eliminated (Schur complement).

    The Jacobian is taken by forward differences, all cameras' (or all boards') k-th parameter
    perturbed at once (a corner depends on one camera and one board only), so a full Jacobian
    costs 15 + 6 vectorised evaluations; the reduced camera system is small (15 x cameras).
    """
    cams, boards = problem.cameras.copy(), problem.boards.copy()
    C, B = cams.shape[0], boards.shape[0]
    P = cams.shape[1]  # parameters per camera
    cam_of, board_of = problem.cam_of[keep], problem.board_of[keep]
    sub = _Problem(problem.obj[keep], problem.img[keep], cam_of, board_of, cams, boards, problem.free_cam)
    free = problem.free_cam.astype(np.float64)
    damping = 1e-3

    def cost(r):
        return float(np.sum(np.log1p(np.sum(r * r, axis=1))))  # Cauchy, scale 1 px

    r = sub.residuals(cams, boards)
    current = cost(r)
    for _ in range(iterations):
        eps_c = 1e-6 * np.maximum(1.0, np.abs(cams))
        eps_b = 1e-6 * np.maximum(1.0, np.abs(boards))
        J_c = np.zeros((len(r), 2, P))
        for k in range(P):
            if not problem.free_cam[:, k].any():
                continue
            moved = cams.copy()
            moved[:, k] += eps_c[:, k] * problem.free_cam[:, k]
            J_c[:, :, k] = (sub.residuals(moved, boards) - r) / eps_c[cam_of, k][:, None]
        J_c *= free[cam_of][:, None, :]
        J_b = np.zeros((len(r), 2, 6))
        for k in range(6):
            moved = boards.copy()
            moved[:, k] += eps_b[:, k]
            J_b[:, :, k] = (sub.residuals(cams, moved) - r) / eps_b[board_of, k][:, None]
        # IRLS weights of the Cauchy loss.
        w = 1.0 / (1.0 + np.sum(r * r, axis=1))
        U = np.zeros((C, P, P))
        V = np.zeros((B, 6, 6))
        W = np.zeros((C, B, P, 6))
        g_c = np.zeros((C, P))
        g_b = np.zeros((B, 6))
        np.add.at(U, cam_of, np.einsum("m,mik,mil->mkl", w, J_c, J_c))
        np.add.at(V, board_of, np.einsum("m,mik,mil->mkl", w, J_b, J_b))
        np.add.at(W, (cam_of, board_of), np.einsum("m,mik,mil->mkl", w, J_c, J_b))
        np.add.at(g_c, cam_of, np.einsum("m,mik,mi->mk", w, J_c, r))
        np.add.at(g_b, board_of, np.einsum("m,mik,mi->mk", w, J_b, r))
        fixed = ~problem.free_cam
        while True:
            U_d = U + damping * np.einsum("ckk->ck", U)[:, :, None] * np.eye(P) + 1e-9 * np.eye(P)
            U_d[fixed] = 0.0
            for c in range(C):
                U_d[c][fixed[c], fixed[c]] = 1.0
            V_d = V + damping * np.einsum("bkk->bk", V)[:, :, None] * np.eye(6) + 1e-9 * np.eye(6)
            V_inv = np.linalg.inv(V_d)
            # Reduced camera system: (U - W V^-1 W^T) dc = -(g_c - W V^-1 g_b)
            WV = np.einsum("cbkl,blm->cbkm", W, V_inv)
            S = np.zeros((C * P, C * P))
            for a in range(C):
                S[a * P : (a + 1) * P, a * P : (a + 1) * P] += U_d[a]
                for b in range(C):
                    S[a * P : (a + 1) * P, b * P : (b + 1) * P] -= np.einsum("jkl,jml->km", WV[a], W[b])
            rhs = -(g_c - np.einsum("cbkl,bl->ck", WV, g_b)).reshape(-1)
            rhs[fixed.reshape(-1)] = 0.0
            try:
                d_c = np.linalg.solve(S, rhs).reshape(C, P)
            except np.linalg.LinAlgError:
                damping *= 10.0
                continue
            d_c[fixed] = 0.0
            d_b = -np.einsum("bkl,bl->bk", V_inv, g_b + np.einsum("cbkl,ck->bl", W, d_c))
            trial_c, trial_b = cams + d_c, boards + d_b
            trial_r = sub.residuals(trial_c, trial_b)
            trial = cost(trial_r) if np.all(np.isfinite(trial_r)) else np.inf
            if trial < current:
                improvement = (current - trial) / max(current, 1e-12)
                cams, boards, r, current = trial_c, trial_b, trial_r, trial
                damping = max(damping / 3.0, 1e-9)
                break
            damping *= 10.0
            if damping > 1e8:
                return cams, boards
        if improvement < 1e-10:
            break
    return cams, boards


def _bundle_adjust(
    names, intrinsics, camera_from_world, board_in_world, detections, refine_intrinsics, k3, iterations
):
    """Joint refinement (module docstring, step 4). Returns [(K, dist, T_cam<-world)], the board
    poses, each camera's per-corner reprojection errors (px) and its count of rejected corners."""
    count = len(names)
    instants = sorted(board_in_world)
    slot = {i: k for k, i in enumerate(instants)}
    cameras = np.zeros((count, 6 + 4 + DIST_TERMS))
    free = np.ones_like(cameras, dtype=bool)
    for v in range(count):
        _, K, dist = intrinsics[v]
        T = camera_from_world[v]
        cameras[v, :6] = [*_vector(T[:3, :3]), *T[:3, 3]]
        cameras[v, 6:10] = [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]
        cameras[v, 10:] = np.pad(dist, (0, DIST_TERMS - dist.size))[:DIST_TERMS]
    free[0, :6] = False  # the first camera is the origin
    if not refine_intrinsics:
        free[:, 6:] = False
    if not k3:
        free[:, 14] = False
        cameras[:, 14] = 0.0
    boards = np.array([[*_vector(board_in_world[i][:3, :3]), *board_in_world[i][:3, 3]] for i in instants])
    obj, img, cam_of, board_of = [], [], [], []
    for i in instants:
        for v in range(count):
            d = detections[i][v]
            if d is not None:
                obj.append(d.object_points)
                img.append(d.image_points)
                cam_of.append(np.full(len(d), v))
                board_of.append(np.full(len(d), slot[i]))
    problem = _Problem(
        np.concatenate(obj),
        np.concatenate(img),
        np.concatenate(cam_of),
        np.concatenate(board_of),
        cameras,
        boards,
        free,
    )
    # Two passes: the second without the corners the first could not explain (a corner the
    # detector put on a marker's edge, a reflection): more than OUTLIER_FACTOR x the camera's
    # median error and more than OUTLIER_MIN_PX.
    everything = np.ones(len(problem.obj), bool)
    cameras, boards = _levenberg_marquardt(problem, iterations, everything)
    errors = np.linalg.norm(problem.residuals(cameras, boards), axis=1)
    keep = everything.copy()
    for v in range(count):
        mine = problem.cam_of == v
        if mine.any():
            limit = max(OUTLIER_MIN_PX, OUTLIER_FACTOR * float(np.median(errors[mine])))
            keep &= ~mine | (errors <= limit)
    if not keep.all():
        problem.cameras, problem.boards = cameras, boards
        cameras, boards = _levenberg_marquardt(problem, iterations, keep)
    errors = np.linalg.norm(problem.residuals(cameras, boards), axis=1)
    if not (np.all(np.isfinite(cameras)) and np.all(np.isfinite(errors))):
        raise CalibrationError("the joint refinement diverged (non-finite parameters); check the board size")
    rejected = [int((~keep & (problem.cam_of == v)).sum()) for v in range(count)]
    out = []
    for v in range(count):
        fx, fy, cx, cy = cameras[v, 6:10]
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        out.append((K, cameras[v, 10:].copy(), _pose_matrix(_rodrigues(cameras[v, :3]), cameras[v, 3:6])))
    board_poses = {i: _pose_matrix(_rodrigues(boards[slot[i], :3]), boards[slot[i], 3:]) for i in instants}
    residuals = [errors[keep & (problem.cam_of == v)] for v in range(count)]
    kept = errors[keep]
    log.info(
        "bundle adjustment: %d corners (%d rejected), %d cameras, %d board poses, RMS %.3f px",
        kept.size,
        sum(rejected),
        count,
        len(instants),
        float(np.sqrt(np.mean(kept**2))),
    )
    return out, board_poses, residuals, rejected
