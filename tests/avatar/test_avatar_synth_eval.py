"""Scoring a tracked run on a synthetic subject (stg_node.avatar.synth_eval): the world alignment
against a pinhole projection done by hand, the scale from depths, and the true-root diagnostic."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stg_node.avatar.synth_eval import (
    WorldAlignment,
    _joints,
    _root_at_truth,
    _swapped,
    similarity_alignment,
    tracked_alignment,
)
from stg_node.body import load_body_model
from stg_node.body.params import SmplParams
from stg_node.data.types import Camera


def _camera(R, t, f=500.0):
    K = np.array([[f, 0, 256.0], [0, f, 256.0], [0, 0, 1]])
    return Camera(K, np.asarray(R, np.float64), np.asarray(t, np.float64), 512, 512, "c")


def _project(camera: Camera, x: np.ndarray) -> np.ndarray:
    p = (camera.R @ x.T).T + camera.t.reshape(3)
    p = (camera.K @ p.T).T
    return p[:, :2] / p[:, 2:]


def test_a_camera_moved_into_the_runs_world_sees_the_same_picture():
    """x_run = s (R x_world + t): the held-out camera in the run's world projects x_run where the
    original projects x_world (any rotation, translation and scale)."""
    rng = np.random.default_rng(0)
    align = WorldAlignment(Rotation.random(random_state=1).as_matrix(), rng.normal(size=3), 0.7)
    held_out = _camera(Rotation.random(random_state=2).as_matrix(), np.array([0.1, -0.2, 4.0]))
    points = rng.normal(scale=0.5, size=(20, 3))
    in_run = align.scale * ((align.R @ points.T).T + align.t)
    expected = _project(held_out, points)
    np.testing.assert_allclose(_project(align.camera(held_out), in_run), expected, atol=1e-9)


def test_the_scale_is_the_median_depth_ratio():
    camera = _camera(np.eye(3), np.zeros(3))
    true = np.zeros((5, 24, 3))
    true[..., 2] = np.arange(2.0, 7.0)[:, None]
    run = true.copy()
    run[..., 2] *= 1.25
    run[0, :, 2] = 100.0  # one bad frame does not move a median
    assert tracked_alignment(camera, true, run).scale == pytest.approx(1.25)


def test_the_true_root_diagnostic_puts_the_tracked_pelvis_on_the_true_one_and_keeps_the_pose():
    body = load_body_model()
    rng = np.random.default_rng(3)
    truth = SmplParams(
        poses=rng.normal(scale=0.2, size=(24, 3)).astype(np.float32),
        Rh=np.array([0.1, 0.4, -0.2], np.float32),
        Th=np.array([0.3, -0.1, 2.0], np.float32),
        betas=np.zeros(10, np.float32),
    )
    tracked = SmplParams(
        poses=truth.poses + rng.normal(scale=0.05, size=(24, 3)).astype(np.float32),
        Rh=truth.Rh,
        Th=np.array([0.5, 0.2, 3.1], np.float32),  # the wrong depth and offset
        betas=np.full(10, 0.5, np.float32),  # another shape: another pelvis offset
    )
    align = WorldAlignment(Rotation.random(random_state=4).as_matrix(), np.array([0.0, 0.2, 3.0]), 1.1)
    moved = _root_at_truth(body, tracked, truth, align)
    pelvis = _joints(body, [moved])[0, 0]
    true_pelvis = _joints(body, [truth])[0, 0]
    np.testing.assert_allclose(pelvis, align.scale * (align.R @ true_pelvis + align.t), atol=1e-5)
    np.testing.assert_array_equal(moved.poses, tracked.poses)
    before = _joints(body, [tracked])[0]
    after = _joints(body, [moved])[0]
    np.testing.assert_allclose(after - after[0], before - before[0], atol=1e-5)  # a translation only


def _truth_and_tracked(seed: int):
    rng = np.random.default_rng(seed)
    truth = SmplParams(
        poses=rng.normal(scale=0.3, size=(24, 3)).astype(np.float32),
        Rh=np.array([0.2, -0.5, 0.1], np.float32),
        Th=np.array([0.1, 0.3, -0.4], np.float32),
        betas=np.zeros(10, np.float32),
    )
    tracked = SmplParams(
        poses=rng.normal(scale=0.3, size=(24, 3)).astype(np.float32),  # every joint wrong
        Rh=np.array([-0.3, 0.2, 0.0], np.float32),
        Th=np.array([0.4, -0.2, 3.3], np.float32),
        betas=np.zeros(10, np.float32),
    )
    align = WorldAlignment(Rotation.random(random_state=seed).as_matrix(), np.array([0.1, 0.2, 3.0]), 1.0)
    return truth, tracked, align


def test_the_true_pose_swap_at_the_true_root_is_the_true_body_in_the_runs_world():
    """swap="pose" with root="true" on the true shape: every joint lands where the alignment maps
    the true body's (a rigid map at scale 1: the same body, moved)."""
    body = load_body_model()
    truth, tracked, align = _truth_and_tracked(5)
    moved = _root_at_truth(body, _swapped(tracked, truth, align, "pose"), truth, align)
    expected = (align.R @ _joints(body, [truth])[0].T).T + align.t
    np.testing.assert_allclose(_joints(body, [moved])[0], expected, atol=1e-4)
    np.testing.assert_array_equal(moved.betas, tracked.betas)


def test_the_orientation_swap_turns_the_body_and_keeps_the_tracked_joint_rotations():
    body = load_body_model()
    truth, tracked, align = _truth_and_tracked(6)
    swapped = _swapped(tracked, truth, align, "orientation")
    np.testing.assert_array_equal(swapped.poses[1:], tracked.poses[1:])
    joints, true_joints = _joints(body, [swapped])[0], _joints(body, [truth])[0]
    for j in (1, 2, 3):  # hips and spine hang on the pelvis alone: placed by the orientation
        expected = align.R @ (true_joints[j] - true_joints[0])
        np.testing.assert_allclose(joints[j] - joints[0], expected, atol=1e-4)
    assert _swapped(tracked, truth, align, "none") is tracked


def test_the_similarity_alignment_recovers_a_known_similarity_and_moves_cameras_with_it():
    """Run joints made from true ones by a known x_run = s (R x + t) (plus noise): the fit finds s, R
    and t, and a held-out camera moved by it sees the run's joints where the original sees the
    true ones."""
    rng = np.random.default_rng(5)
    true = rng.normal(scale=0.4, size=(30, 24, 3)) + np.array([0.0, 0.0, 3.0])
    R = Rotation.from_euler("xyz", [5.0, -20.0, 3.0], degrees=True).as_matrix()
    t, s = np.array([0.1, -0.3, 0.5]), 1.15
    run = s * (true @ R.T + t) + rng.normal(scale=1e-4, size=true.shape)
    align = similarity_alignment(true, run)
    assert align.scale == pytest.approx(s, rel=1e-3)
    np.testing.assert_allclose(align.R, R, atol=1e-3)
    np.testing.assert_allclose(align.t, t, atol=1e-3)
    held_out = _camera(Rotation.random(random_state=6).as_matrix(), np.array([0.0, 0.1, 5.0]))
    np.testing.assert_allclose(
        _project(align.camera(held_out), run.reshape(-1, 3)),
        _project(held_out, true.reshape(-1, 3)),
        atol=0.1,
    )


def test_the_similarity_alignment_of_a_camera_frame_world_agrees_with_the_extrinsics():
    """A tracker that saw the truth exactly, in its camera's frame: the similarity is that camera's
    extrinsics and scale 1, as tracked_alignment says."""
    rng = np.random.default_rng(7)
    camera = _camera(Rotation.random(random_state=8).as_matrix(), np.array([0.2, 0.0, 4.0]))
    true = rng.normal(scale=0.4, size=(10, 24, 3))
    run = true @ camera.R.T + camera.t
    fitted, extrinsic = similarity_alignment(true, run), tracked_alignment(camera, true, run)
    assert fitted.scale == pytest.approx(extrinsic.scale, abs=1e-9)
    np.testing.assert_allclose(fitted.R, extrinsic.R, atol=1e-9)
    np.testing.assert_allclose(fitted.t, extrinsic.t, atol=1e-9)


def test_shrinking_for_the_far_subjects_resolution_averages_pixel_blocks():
    """resample=0.5 (bench_footage size): each output pixel is the mean of a 2 x 2 block (by hand);
    the mask keeps the blocks at least half covered."""
    from stg_node.avatar.synth_eval import _shrunk

    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (8, 6, 3)).astype(np.uint8)
    target = rng.random((8, 6, 3)).astype(np.float32)
    mask = np.zeros((8, 6), np.uint8)
    mask[0:2, 0:1] = 255  # half of the first block: kept
    mask[2:3, 2:3] = 255  # a quarter of another: dropped
    small_image, small_target, small_mask = _shrunk(0.5, image, target, mask)
    blocks = image.astype(np.float32).reshape(4, 2, 3, 2, 3).mean(axis=(1, 3)) / 255.0
    assert small_image.shape == (4, 3, 3) and np.allclose(small_image, blocks, atol=1e-6)
    assert np.allclose(small_target, target.reshape(4, 2, 3, 2, 3).mean(axis=(1, 3)), atol=1e-6)
    expected = np.zeros((4, 3), np.uint8)
    expected[0, 0] = 255
    assert np.array_equal(small_mask, expected)


def test_same_camera_scores_every_frame_after_the_training_range_on_the_training_camera(tmp_path):
    """``same_camera`` (stg-eval --split novel_pose on a video run): the generator's held-out frames,
    every one, seen by the training camera only; the benchmark's own split keeps other cameras."""
    from stg_node.avatar.data_spec import DataSpec
    from stg_node.avatar.synth_eval import _held_out_same_camera
    from stg_node.data.synth import SynthConfig, generate

    generate(
        SynthConfig(out=tmp_path, num_frames=10, size=32, num_novel_views=2, view_every=3), progress=False
    )
    train = DataSpec(str(tmp_path), "synthetic", None, None, 32).open("train")
    held_out = _held_out_same_camera(tmp_path, train, 32)
    views = [(sample.index, sample.camera.name) for sample in held_out]
    assert views == [(8, train.camera_names[0]), (9, train.camera_names[0])]  # 0.8 of 10 frames train
    benchmark = {
        sample.camera.name
        for sample in DataSpec(str(tmp_path), "synthetic", None, None, 32).open("novel_pose")
    }
    assert len(benchmark) > 1


def test_bench_footage_gap_by_part_is_truth_minus_the_run_per_split_and_part():
    """tools/bench_footage.py closeup's gap: truth's PSNR minus the run's, overall and per part
    (only parts and splits both have); LPIPS the run's minus truth's (worse is positive)."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tools"))
    import bench_footage

    truth = {
        "held_out_same_camera": {"psnr": 28.0, "lpips": 0.03, "parts_psnr": {"arms": 14.0, "legs": 31.0}}
    }
    run = {
        "held_out_same_camera": {"psnr": 24.5, "lpips": 0.07, "parts_psnr": {"arms": 12.0}},
        "novel_view": {"psnr": 20.0, "lpips": 0.1, "parts_psnr": {}},
    }
    gap = bench_footage.gap_by_part(truth, run)
    assert list(gap) == ["held_out_same_camera"]
    assert gap["held_out_same_camera"]["psnr"] == pytest.approx(3.5)
    assert gap["held_out_same_camera"]["lpips"] == pytest.approx(0.04)
    assert gap["held_out_same_camera"]["parts"] == {"arms": pytest.approx(2.0)}


def _bench_footage():
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tools"))
    import bench_footage

    return bench_footage


def test_bench_footage_true_depth_slides_the_body_along_its_pelvis_ray():
    """decompose's true-depth variant: the pelvis lands at the asked depth on the same pixel, and the
    whole body moves by one translation (its pose and shape untouched)."""
    body = load_body_model()
    truth, tracked, _ = _truth_and_tracked(7)
    pelvis = _joints(body, [tracked])[0, 0]
    Th = _bench_footage().slid_to_depth(tracked.Th, pelvis, 2.5)
    moved = SmplParams(poses=tracked.poses, Rh=tracked.Rh, Th=Th.astype(np.float32), betas=tracked.betas)
    new_pelvis = _joints(body, [moved])[0, 0]
    assert new_pelvis[2] == pytest.approx(2.5, abs=1e-5)
    np.testing.assert_allclose(new_pelvis[:2] / new_pelvis[2], pelvis[:2] / pelvis[2], atol=1e-6)


def test_bench_footage_decomposition_adds_up_to_the_gap():
    """Each step's gain over the one before, plus what the truth run still scores above the last
    step, sums to the whole gap (overall and per part)."""
    steps = {
        "score": {"psnr": 24.0, "parts_psnr": {"arms": 12.0}},
        "true-root": {"psnr": 25.5, "parts_psnr": {"arms": 12.5}},
        "true-root-pose": {"psnr": 27.0, "parts_psnr": {"arms": 15.0}},
    }
    truth = {"psnr": 31.0, "parts_psnr": {"arms": 17.0}}
    result = _bench_footage().decomposition(truth, steps)
    assert result["gap_db"] == pytest.approx(7.0)
    assert list(result["gains"]) == ["true-root", "true-root-pose", "avatar"]
    assert result["gains"]["true-root"]["psnr"] == pytest.approx(1.5)
    assert result["gains"]["avatar"]["psnr"] == pytest.approx(4.0)
    assert sum(g["psnr"] for g in result["gains"].values()) == pytest.approx(result["gap_db"])
    assert sum(g["parts"]["arms"] for g in result["gains"].values()) == pytest.approx(5.0)


def test_an_unknown_swap_is_refused_before_anything_is_loaded(tmp_path):
    from stg_node.avatar.synth_eval import evaluate_on_synth

    with pytest.raises(ValueError, match="swap must be one of"):
        evaluate_on_synth(tmp_path / "no_run", tmp_path / "no_subject", swap="shape")


def test_bench_footage_chain_step_turns_only_that_chain_to_its_true_orientation_in_the_camera():
    """decompose's chain steps (true-arms, ...): the body model's own forward kinematics puts each
    joint of the chain at the true orientation in the camera's frame and every other joint at
    the tracked one (the local rotations re-solved below a changed parent)."""
    import torch

    body = load_body_model()
    truth, tracked, _ = _truth_and_tracked(11)

    def rows(params):
        poses = np.asarray(params.poses, np.float32).reshape(1, 72).copy()
        return {"poses": poses, "Rh": np.asarray(params.Rh, np.float32)[None],
                "Th": np.asarray(params.Th, np.float32)[None],
                "shapes": np.zeros((1, 10), np.float32)}  # fmt: skip

    def world_rotations(r):
        out = body(betas=torch.as_tensor(r["shapes"]), poses=torch.as_tensor(r["poses"]),
                   Rh=torch.as_tensor(r["Rh"]), Th=torch.as_tensor(r["Th"]))  # fmt: skip
        return out.bone_transforms[0, :, :3, :3].double().numpy()

    bench = _bench_footage()
    arms = bench.CHAINS["arms"]
    mixed = world_rotations(bench.chain_true_in_world(rows(tracked), rows(truth), arms))
    want_true, want_tracked = world_rotations(rows(truth)), world_rotations(rows(tracked))
    others = [j for j in range(24) if j not in arms]
    np.testing.assert_allclose(mixed[list(arms)], want_true[list(arms)], atol=1e-5)
    np.testing.assert_allclose(mixed[others], want_tracked[others], atol=1e-5)
    assert np.abs(want_true[list(arms)] - want_tracked[list(arms)]).max() > 0.1  # the swap did something


def test_bench_footage_limb_roots_take_the_donors_orientation_in_the_camera():
    """chains' "true torso world limbs": the hips' and shoulders' local rotations re-solved so that,
    under the base's torso, the body model's own forward kinematics puts them at the donor's
    orientation in the camera's frame; the torso itself stays the base's."""
    import torch

    body = load_body_model()
    truth, tracked, _ = _truth_and_tracked(12)

    def rows(params):
        return {"poses": np.asarray(params.poses, np.float64).reshape(1, 72).copy(),
                "Rh": np.asarray(params.Rh, np.float64)[None]}  # fmt: skip

    def world_rotations(r):
        out = body(betas=torch.zeros(1, 10), poses=torch.as_tensor(r["poses"], dtype=torch.float32),
                   Rh=torch.as_tensor(r["Rh"], dtype=torch.float32), Th=torch.zeros(1, 3))  # fmt: skip
        return out.bone_transforms[0, :, :3, :3].double().numpy()

    bench = _bench_footage()
    roots = list(bench.LIMB_ROOTS)
    base, donor = rows(truth), rows(tracked)
    turned = {"poses": base["poses"].reshape(1, 24, 3).copy(), "Rh": base["Rh"]}
    turned["poses"][:, roots] = bench.limb_roots_in_world(base, donor)
    turned["poses"] = turned["poses"].reshape(1, 72)
    got, want_donor, want_base = world_rotations(turned), world_rotations(donor), world_rotations(base)
    np.testing.assert_allclose(got[roots], want_donor[roots], atol=1e-5)
    torso = sorted({0, 3, 6, 9, 12, 13, 14, 15} - set(roots))
    np.testing.assert_allclose(got[torso], want_base[torso], atol=1e-5)
    assert np.abs(want_donor[roots] - want_base[roots]).max() > 0.05  # the turn did something


def test_bench_footage_twopass_step_replaces_only_the_training_frames_poses(tmp_path):
    """decompose's twopass step: the first rows (the frames twopass fitted) take its average, the
    frames after them keep the tracked poses; the images and camera are the tracked folder's."""
    tracked = tmp_path / "tracked"
    for sub in ("images", "masks"):
        (tracked / sub).mkdir(parents=True)
    (tracked / "cameras.json").write_text("{}")
    rng = np.random.default_rng(3)
    rows = {"poses": rng.normal(size=(5, 72)), "Rh": rng.normal(size=(5, 3)), "Th": rng.normal(size=(5, 3)),
            "shapes": np.zeros((5, 10)), "frames": np.arange(5)}  # fmt: skip
    np.savez(tracked / "poses.npz", **rows)
    bench = _bench_footage()
    with pytest.raises(FileNotFoundError, match="twopass"):
        bench.two_pass_folder(tracked, tmp_path / "missing.npz")
    average = rng.normal(size=(3, 78))
    np.savez(tmp_path / "two.npz", average=average)
    folder = bench.two_pass_folder(tracked, tmp_path / "two.npz")
    out = np.load(folder / "poses.npz")
    np.testing.assert_allclose(out["poses"][:3], average[:, :72])
    np.testing.assert_allclose(out["Rh"][:3], average[:, 72:75])
    np.testing.assert_allclose(out["Th"][:3], average[:, 75:])
    np.testing.assert_allclose(out["poses"][3:], rows["poses"][3:])
    assert (folder / "images").resolve() == (tracked / "images").resolve()


def test_bench_footage_toward_truth_moves_every_rotation_that_fraction_of_its_arc():
    """decompose's toward-N steps: each local rotation and the global orientation turned N % of
    the way to the truth along the shortest arc (the angle left is (1 - N) of the angle between
    them, about the same axis), position and shape in a straight line; 0 and 1 are the ends."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(5)
    tracked = {"poses": rng.normal(0, 0.4, (3, 72)), "Rh": rng.normal(0, 0.4, (3, 3)),
               "Th": rng.normal(size=(3, 3)), "shapes": rng.normal(size=(3, 10))}  # fmt: skip
    truth = {k: v + rng.normal(0, 0.3, v.shape) for k, v in tracked.items()}
    bench = _bench_footage()

    def gap_deg(a, b):
        return np.degrees(
            (
                Rotation.from_rotvec(a.reshape(-1, 3)).inv() * Rotation.from_rotvec(b.reshape(-1, 3))
            ).magnitude()
        )

    full = gap_deg(tracked["poses"], truth["poses"])
    for alpha in (0.0, 0.25, 1.0):
        moved = bench.toward_truth(tracked, truth, alpha)
        np.testing.assert_allclose(gap_deg(moved["poses"], truth["poses"]), (1 - alpha) * full, atol=1e-6)
        np.testing.assert_allclose(gap_deg(moved["poses"], tracked["poses"]), alpha * full, atol=1e-6)
        np.testing.assert_allclose(gap_deg(moved["Rh"], truth["Rh"]),
                                   (1 - alpha) * gap_deg(tracked["Rh"], truth["Rh"]), atol=1e-6)  # fmt: skip
        np.testing.assert_allclose(moved["Th"], tracked["Th"] + alpha * (truth["Th"] - tracked["Th"]))
    assert full.mean() > 10.0  # the test moved something
    joints = bench.toward_truth(tracked, truth, 0.5, which="joints")  # the joints alone
    np.testing.assert_allclose(gap_deg(joints["poses"], truth["poses"]), 0.5 * full, atol=1e-6)
    for key in ("Rh", "Th", "shapes"):
        np.testing.assert_array_equal(joints[key], tracked[key])
    placed = bench.toward_truth(tracked, truth, 0.5, which="body")  # everything but the joints
    np.testing.assert_array_equal(placed["poses"], tracked["poses"])
    np.testing.assert_allclose(placed["shapes"], 0.5 * (tracked["shapes"] + truth["shapes"]))


def test_bench_footage_flipped_bone_keeps_its_childs_pixel_and_turns_only_that_bone():
    """order's diagnostic flip: the child joint stays on its pixel at the other depth of the same
    bone length, and every other joint keeps its orientation in the camera's frame."""
    import torch

    body = load_body_model()
    rng = np.random.default_rng(2)
    rows = {"poses": rng.normal(0, 0.3, (1, 72)), "Rh": np.array([[np.pi, 0.0, 0.0]]),
            "Th": np.array([[0.0, 0.2, 3.0]]), "shapes": np.zeros((1, 10))}  # fmt: skip
    rows["poses"][0, :3] = 0.0
    bench = _bench_footage()
    bone = (16, 18)
    out = bench.with_bones_flipped(rows, {bone: np.array([True])})

    def forward(r):
        t = {k: torch.as_tensor(np.asarray(v), dtype=torch.float32) for k, v in r.items()}
        res = body(betas=t["shapes"], poses=t["poses"], Rh=t["Rh"], Th=t["Th"])
        return res.joints[0].double().numpy(), res.bone_transforms[0, :, :3, :3].double().numpy()

    (j0, g0), (j1, g1) = forward(rows), forward(out)
    p, q = j0[bone[0]], j0[bone[1]]
    ray = q / np.linalg.norm(q)
    np.testing.assert_allclose(j1[bone[1]], (2 * ray @ p - np.linalg.norm(q)) * ray, atol=2e-4)
    others = [k for k in range(24) if k != bone[0]]
    np.testing.assert_allclose(g1[others], g0[others], atol=1e-4)
    assert np.abs(g1[bone[0]] - g0[bone[0]]).max() > 0.05


def test_bench_footage_in_camera_frame_moves_every_joint_by_the_cameras_transform():
    """decompose's rig step puts a world-frame fit in the training camera's frame: the body model
    run on the returned rows puts every joint at R X + t of the world joints (the root's pose row
    zero, its rotation in Rh, as the tracker writes it)."""
    body = load_body_model()
    rng = np.random.default_rng(5)
    world = SmplParams(poses=rng.normal(0, 0.3, 72).astype(np.float32),
                       Rh=np.array([0.4, -1.1, 0.2], np.float32), Th=np.array([0.3, -0.1, 0.8], np.float32),
                       betas=rng.normal(0, 1, 10).astype(np.float32))  # fmt: skip
    R = Rotation.from_rotvec([0.2, 2.5, -0.3]).as_matrix()
    t = np.array([0.1, 0.4, 3.2])
    poses, Rh, Th = _bench_footage().in_camera_frame(body, world, R, t)
    assert np.all(poses[:3] == 0.0)
    placed = SmplParams(poses=poses.astype(np.float32), Rh=Rh.astype(np.float32), Th=Th.astype(np.float32),
                        betas=world.betas)  # fmt: skip
    np.testing.assert_allclose(_joints(body, [placed])[0], _joints(body, [world])[0] @ R.T + t, atol=2e-5)
