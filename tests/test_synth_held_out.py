"""The benchmark's held-out conditions: lights fixed in the room, held-out motions and orientations,
the distances it reports (against scipy's rotations), and per-body-part scores."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from stg_node.data.synth.lighting import ROOM_LIGHT_DIRECTION, lighting
from stg_node.data.synth.motions import make_motion
from stg_node.data.synth.split_distances import heading_deg, held_out_distances

FPS = 30.0


def _yaw_deg(seq) -> np.ndarray:
    return heading_deg(Rotation.from_rotvec(seq.Rh.astype(np.float64)).as_matrix())


# --- distances ------------------------------------------------------------------------------------
def test_distances_match_rotations_built_by_scipy():
    """Three training frames and two held-out ones with known joint bends and known turns."""
    n = 5
    poses = np.zeros((n, 24, 3))
    Rh = np.zeros((n, 3))
    up = np.array([1.0, 0.0, 0.0]) * (np.pi / 2)  # SMPL y-up body standing in a z-up world
    for i in range(n):
        yaw = Rotation.from_euler("z", [0.0, 10.0, 20.0, 95.0, 15.0][i], degrees=True)
        Rh[i] = (yaw * Rotation.from_rotvec(up)).as_rotvec()
    poses[1, 18] = [0.0, -np.radians(40.0), 0.0]  # training frame 1: left elbow bent 40 deg
    poses[3, 18] = [0.0, -np.radians(70.0), 0.0]  # held out: 30 deg further than frame 1
    poses[4, 4] = [np.radians(23.0), 0.0, 0.0]  # held out: a knee bent 23 deg, else like frame 0
    out = held_out_distances(poses, Rh, range(3), [3, 4])
    bent, knee = out
    assert bent.nearest_pose_frame == 1 and knee.nearest_pose_frame == 0
    assert bent.pose_rms_deg == pytest.approx(30.0 / math.sqrt(23), rel=1e-6)
    assert knee.pose_rms_deg == pytest.approx(23.0 / math.sqrt(23), rel=1e-6)
    frob = np.linalg.norm(
        Rotation.from_rotvec(poses[3, 18]).as_matrix() - Rotation.from_rotvec(poses[1, 18]).as_matrix()
    )
    assert bent.pose_distance == pytest.approx(frob, rel=1e-6)
    # Orientation: 95 deg of yaw against training yaws 0, 10, 20 -> 75 deg from frame 2; 15 -> 5 deg.
    assert bent.nearest_orientation_frame == 2 and bent.orientation_deg == pytest.approx(75.0, abs=1e-6)
    assert knee.orientation_deg == pytest.approx(5.0, abs=1e-6)
    assert bent.yaw_deg == pytest.approx(95.0, abs=1e-6) and knee.yaw_deg == pytest.approx(15.0, abs=1e-6)
    # The most extrapolated joint: the elbow 30 deg beyond its nearest training bend (frame 1's, not
    # frame 0's straight one), the knee 23 deg beyond the straight knee every training frame had.
    assert bent.joint_max_name == "left_elbow" and bent.joint_max_deg == pytest.approx(30.0, abs=1e-6)
    assert knee.joint_max_name == "left_knee" and knee.joint_max_deg == pytest.approx(23.0, abs=1e-6)
    with pytest.raises(ValueError, match="training frame"):
        held_out_distances(poses, Rh, [], [3])


# --- held-out motions and orientations ----------------------------------------------------------
def test_training_orientations_stay_in_their_window_and_held_out_ones_are_turned():
    seq = make_motion("turn", 160, FPS, np.random.default_rng(2), 100, train_yaw_deg=60.0, test_yaw_deg=150.0)
    yaw = _yaw_deg(seq)
    assert np.abs(yaw[:100]).max() <= 30.0 + 1e-6  # the root's wobble is pitch and roll only
    assert np.ptp(yaw[:100]) > 40.0  # the window is swept, not one orientation
    tail = (yaw[100:] - 150.0 + 180.0) % 360.0 - 180.0
    assert np.abs(tail).max() <= 30.0 + 1e-6
    assert seq.cuts == (100,)
    assert np.linalg.norm(seq.Th[:, :2], axis=1).max() < 0.2  # no walking off: the subject stays put
    distances = held_out_distances(seq.poses, seq.Rh, range(100), range(100, 160))
    assert min(d.orientation_deg for d in distances) >= 150.0 - 60.0 - 1e-6


def test_held_out_motions_play_in_equal_parts_without_a_fade_across_a_cut():
    from stg_node.data.synth.motions import _blend_weights

    seq = make_motion(
        "turn",
        160,
        FPS,
        np.random.default_rng(3),
        100,
        test_motion="crouch,arms_up",
        train_yaw_deg=60.0,
        test_yaw_deg=150.0,
    )
    assert [(s.name, s.start, s.stop) for s in seq.segments] == [
        ("turn", 0, 100),
        ("crouch", 100, 130),
        ("arms_up", 130, 160),
    ]
    # A cut starts the held-out clip as its own motion; the parts after it still cross-fade.
    t = np.arange(160) / FPS
    starts = [0.0, 100 / FPS, 130 / FPS]
    cut = _blend_weights(t, starts, cut=100 / FPS)
    np.testing.assert_array_equal(cut[99], [1.0, 0.0, 0.0])
    np.testing.assert_array_equal(cut[100], [0.0, 1.0, 0.0])
    assert 0.0 < cut[130, 2] < 1.0 and 0.0 < cut[129, 2] < 1.0
    faded = _blend_weights(t, starts)
    assert 0.0 < faded[99, 1] < 1.0 and 0.0 < faded[100, 1] < 1.0
    continuous = make_motion("turn", 160, FPS, np.random.default_rng(3), 100, test_motion="crouch")
    assert continuous.cuts == () and [s.name for s in continuous.segments] == ["turn", "crouch"]


def test_crouch_arms_up_and_reach_do_what_their_names_say():
    crouch = make_motion("crouch", 150, FPS, np.random.default_rng(0))
    arms = make_motion("arms_up", 150, FPS, np.random.default_rng(0))
    from stg_node.data.synth.joint_limits import JOINT_INDEX

    assert crouch.euler_deg[:, JOINT_INDEX["left_knee"], 0].max() > 80.0  # a deep knee bend
    assert arms.euler_deg[:, JOINT_INDEX["left_shoulder"], 2].max() > 70.0  # the arm above the shoulder
    assert arms.euler_deg[:, JOINT_INDEX["right_shoulder"], 2].min() < -70.0  # mirrored side
    reach = make_motion("reach", 150, FPS, np.random.default_rng(0))
    folded = reach.euler_deg[:, JOINT_INDEX["left_elbow"], 1] < -130.0  # the elbow folded far
    assert folded.any() and (reach.euler_deg[folded, JOINT_INDEX["left_shoulder"], 2] > 60.0).all()
    assert reach.euler_deg[:, JOINT_INDEX["right_elbow"], 1].max() > 130.0  # mirrored side


def test_bad_held_out_options_are_clear_errors():
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="unknown test motion 'moonwalk'"):
        make_motion("turn", 30, FPS, rng, 20, test_motion="wave,moonwalk")
    with pytest.raises(ValueError, match="needs train_yaw_deg"):
        make_motion("turn", 30, FPS, rng, 20, test_yaw_deg=90.0)
    with pytest.raises(ValueError, match="train_yaw_deg"):
        make_motion("turn", 30, FPS, rng, 20, train_yaw_deg=400.0)


# --- lights ---------------------------------------------------------------------------------------
def _octahedron() -> tuple[torch.Tensor, torch.Tensor]:
    v = torch.tensor(
        [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=torch.float32
    )
    f = torch.tensor([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
    return v, f


def test_a_room_light_stays_in_the_world_and_a_body_light_turns_with_the_body():
    vertices, faces = _octahedron()  # vertex normals are the vertex directions
    half_turn = np.array([0.0, 0.0, np.pi])  # Rh: the body turned 180 deg about world up
    room = lighting("room").vertex_shade(vertices, faces, half_turn)
    expected = 0.3 + 0.7 * np.clip(vertices.numpy() @ np.asarray(ROOM_LIGHT_DIRECTION), 0.0, None)
    np.testing.assert_allclose(room.numpy(), expected, atol=1e-6)  # Rh does not enter
    body = lighting("lambert")
    turned = torch.as_tensor(Rotation.from_rotvec(half_turn).apply(vertices.numpy()), dtype=torch.float32)
    np.testing.assert_allclose(  # a turned body keeps its shading, vertex by vertex
        body.vertex_shade(turned, faces, half_turn).numpy(),
        body.vertex_shade(vertices, faces, np.zeros(3)).numpy(),
        atol=1e-6,
    )
    env = lighting("environment").vertex_shade(vertices, faces, half_turn)
    assert env.shape == (6, 3) and (env[:, 2] != env[:, 0]).any()  # coloured lights
    assert lighting("none").vertex_shade(vertices, faces, half_turn) is None
    with pytest.raises(ValueError, match="unknown shading"):
        lighting("disco")


# --- the generator --------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def turned(tmp_path_factory):
    from stg_node.data.synth.generate import SynthConfig, generate

    out = tmp_path_factory.mktemp("synth") / "turned"
    return generate(
        SynthConfig(
            out=out,
            seed=1,
            num_frames=10,
            size=64,
            motion="turn",
            num_novel_views=2,
            view_every=4,
            supersample=1,
            shading="room",
            test_motion="crouch",
            train_yaw_deg=60.0,
            test_yaw_deg=150.0,
        ),
        progress=False,
    )


def test_synth_json_records_the_light_and_every_held_out_frames_distances(turned):
    meta = json.loads((turned.out / "synth.json").read_text())
    assert meta["shading"]["mode"] == "room" and meta["shading"]["lights"][0]["frame"] == "world"
    held = meta["held_out"]
    assert held["cuts"] == [8] and held["test_motion"] == ["crouch"] and held["test_yaw_deg"] == 150.0
    assert [d["frame"] for d in held["distances"]] == [8, 9]
    assert all(d["orientation_deg"] > 80.0 for d in held["distances"])
    assert held["summary"]["frames"] == 2
    from stg_node.data.synth.split_distances import benchmark_condition

    condition = benchmark_condition(meta, [8])
    assert condition["shading"] == "room" and condition["held_out"]["frames"] == 1


def test_the_garment_restarts_at_a_cut(turned):
    """The clip after the cut starts at the garment's quasi-static equilibrium, as frame 0 does;
    simulated straight through, the 150 deg jump would fling the cloth out."""
    from stg_node.body import load_body_model
    from stg_node.body.motion import drive_body, load_smpl_params
    from stg_node.data.synth.garment import GarmentParams, garment_regions, simulate_garment
    from stg_node.data.synth.writer import read_frame_vertices

    body = load_body_model()
    params = load_smpl_params(turned.out / "new_params")
    with torch.no_grad():
        skinned = drive_body(body, params).vertices.numpy().astype(np.float64)
        betas = torch.as_tensor(np.asarray(params.betas, np.float32).reshape(-1, body.num_betas)[:1])
        zero = torch.zeros(1, 3)
        rest = body(betas=betas, poses=torch.zeros(1, 72), Rh=zero, Th=zero)
    regions = garment_regions(rest.vertices[0].numpy(), rest.joints[0].numpy(), GarmentParams())
    written = np.stack([read_frame_vertices(turned.out, f) for f in range(10)]) - skinned
    through = simulate_garment(skinned, regions.weight, FPS, GarmentParams(), regions.freq_scale)
    cloth = regions.weight > 0
    written_8 = np.linalg.norm(written[8, cloth], axis=1).max()
    through_8 = np.linalg.norm(through[8, cloth], axis=1).max()
    assert written_8 < 0.5 * through_8 and through_8 > 0.02
    np.testing.assert_allclose(written[:7], through[:7], atol=2e-4)  # before the cut (its last frame
    # differs: the frame after it enters its velocity and acceleration)


def test_body_part_labels_cover_the_mask_and_pool_like_one_psnr(turned):
    from stg_node.data.metrics.image import psnr
    from stg_node.data.synth.body_parts import PARTS, RegionScores, SynthPartLabeller
    from stg_node.data.synth.dataset import open_synth

    labeller = SynthPartLabeller(turned.out)
    sample = open_synth(turned.out, "train", size=64)[0]
    labels = labeller(sample.index, sample.camera)
    mask = sample.mask > 127
    covered = labels >= 0
    assert (covered & mask).sum() / max((covered | mask).sum(), 1) > 0.9  # same silhouette
    seen = {PARTS[i] for i in np.unique(labels[covered])}
    assert {"head", "torso", "arms", "legs"} <= seen
    # Pooled per part: the same as one PSNR over the concatenated pixels of that part.
    rng = np.random.default_rng(0)
    scores = RegionScores()
    preds, gts, masks = [], [], []
    for _ in range(3):
        gt = sample.image
        pred = np.clip(gt.astype(int) + rng.integers(-20, 21, gt.shape), 0, 255).astype(np.uint8)
        regions = labeller.regions(sample.index, sample.camera)
        scores.add(pred, gt, regions)
        preds.append(pred[regions["torso"]])
        gts.append(gt[regions["torso"]])
        masks.append(regions["torso"])
    expected = psnr(np.concatenate(preds)[None] / 255.0, np.concatenate(gts)[None] / 255.0)
    assert scores.psnr("torso") == pytest.approx(expected, rel=1e-9)
    assert scores.report()["torso"]["pixels"] == sum(int(m.sum()) for m in masks)


def test_true_flow_of_the_last_frame_before_a_cut_looks_back(turned):
    from stg_node.body import load_body_model
    from stg_node.data.synth.dataset import open_synth
    from stg_node.data.synth.true_flow import benchmark_true_flow, true_flow
    from stg_node.data.synth.writer import read_frame_vertices

    faces = load_body_model().faces.numpy()
    camera = open_synth(turned.out, "train", size=64)[0].camera
    got = benchmark_true_flow(turned.out, 7, camera, faces, 10, cuts=(8,))
    back = true_flow(read_frame_vertices(turned.out, 7), read_frame_vertices(turned.out, 6), faces, camera)
    np.testing.assert_array_equal(got.flow, back.flow)
    ahead = benchmark_true_flow(turned.out, 6, camera, faces, 10, cuts=(8,))
    forward = true_flow(read_frame_vertices(turned.out, 6), read_frame_vertices(turned.out, 7), faces, camera)
    np.testing.assert_array_equal(ahead.flow, forward.flow)
