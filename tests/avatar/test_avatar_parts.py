"""Smaller parts against closed forms: SH basis, the novel-pose time code, Adam row surgery, the
proximal step, the colour MLP's size, frame crops."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from stg_node.avatar.color import ColorMLP, sh_basis
from stg_node.avatar.config import ModelConfig
from stg_node.avatar.frames import crop_box
from stg_node.avatar.gaussians import GaussianTable
from stg_node.avatar.optim import TableOptimizer
from stg_node.avatar.presets import PRESETS, preset
from stg_node.avatar.timecode import FADE_END, HYSTERESIS, PoseTimeIndex, pose_key


def test_sh_basis_is_orthonormal_on_the_sphere():
    """The real SH basis (3DGS's signs) integrates to the identity: a Monte-Carlo check of all 16."""
    gen = torch.Generator().manual_seed(0)
    d = torch.randn(400_000, 3, generator=gen, dtype=torch.float64)
    d = d / d.norm(dim=1, keepdim=True)
    Y = sh_basis(3, d)
    gram = 4 * math.pi * (Y.T @ Y) / d.shape[0]
    assert torch.allclose(gram, torch.eye(16, dtype=torch.float64), atol=0.02)
    # Band 1 is proportional to (-y, z, -x): 3DGS's convention.
    one = torch.tensor([[0.0, 1.0, 0.0]], dtype=torch.float64)
    assert sh_basis(1, one)[0, 1] < 0 and abs(float(sh_basis(1, one)[0, 2])) < 1e-12


def test_colour_mlp_stays_light_in_every_preset():
    for name in PRESETS:
        cfg = preset(name).model
        mlp = ColorMLP(cfg, torch.tensor([[-1.0, -1, -1], [1, 1, 1]]))
        assert mlp.num_parameters() < 800_000, name
        out = mlp(
            torch.zeros(5, 3),
            torch.zeros(5, cfg.feature_dim),
            torch.zeros(1, 207),
            torch.tensor([[0.0, 0, 1]]).expand(5, 3),
            cfg.sh_degree,
        )
        assert out.shape == (5, 3) and bool(((out >= 0) & (out <= 1)).all())


def _pose(angle: float) -> np.ndarray:
    p = np.zeros((24, 3), np.float32)
    p[16, 2] = angle  # left shoulder
    return p


def test_novel_pose_takes_the_time_of_the_nearest_training_pose_and_holds_it():
    index = PoseTimeIndex()
    for i, angle in enumerate(np.linspace(0, 1.5, 16)):
        index.add(_pose(angle), float(i))
    t, k = index.time_for(_pose(0.1))  # closest to angle 0.1 -> key 1 (0.1)
    assert k == 1 and t == 1.0
    # Root orientation and translation are ignored: a turned body is the same pose.
    turned = _pose(0.1)
    turned[0] = [0.3, 2.0, -0.5]
    assert index.time_for(turned)[1] == 1
    # Hysteresis: slightly nearer to key 2 than key 1 keeps key 1 when key 1 was the last choice.
    between = _pose(0.1 + 0.5 * 0.1 * (1 + HYSTERESIS / 4))
    assert index.time_for(between)[1] == 2
    assert index.time_for(between, previous=1)[1] == 1
    assert index.time_for(_pose(1.5), previous=1)[1] == 15


def test_pose_index_thins_itself_to_its_capacity():
    index = PoseTimeIndex(capacity=8)
    for i in range(100):
        index.add(_pose(i / 100), float(i))
    assert len(index) <= 8 + 1
    assert index.times[0] == 0.0 and index.times[-1] == 99.0


def test_row_surgery_keeps_adam_state_aligned():
    table = GaussianTable({"means": torch.arange(12.0).reshape(4, 3), "opacity_logits": torch.zeros(4)})
    opt = TableOptimizer(table, {"means": 0.1, "opacity_logits": 0.1}, {})
    table["means"].grad = torch.ones(4, 3)
    table["opacity_logits"].grad = torch.arange(4.0)
    opt.step()
    m_before = opt.adam.state[table["means"]]["exp_avg"].clone()
    opt.keep(torch.tensor([True, False, True, True]))
    assert table.num == 3
    assert torch.equal(opt.adam.state[table["means"]]["exp_avg"], m_before[[0, 2, 3]])
    opt.append({"means": torch.full((2, 3), 7.0), "opacity_logits": torch.zeros(2)})
    state = opt.adam.state[table["means"]]
    assert table.num == 5 and torch.equal(state["exp_avg"][3:], torch.zeros(2, 3))
    assert torch.equal(table["means"][3:], torch.full((2, 3), 7.0))
    # The optimiser still steps the new parameter objects.
    table["means"].grad = torch.ones(5, 3)
    table["opacity_logits"].grad = torch.ones(5)
    before = table["means"].detach().clone()
    opt.step()
    assert not torch.equal(before, table["means"])


def test_proximal_step_is_the_soft_threshold():
    table = GaussianTable(
        {
            "means": torch.zeros(3, 3),
            "motion": torch.tensor([[[0.5, -0.05, 0.0]], [[0.09, 0.0, -2.0]], [[0.0] * 3]]),
        }
    )
    opt = TableOptimizer(table, {"means": 0.0, "motion": 0.1}, {})
    opt.set_schedule(0.0, 1.0, 1.0)
    opt.soft_threshold("motion", 1.0)  # threshold = lr x 1 = 0.1
    expected = torch.tensor([[[0.4, 0.0, 0.0]], [[0.0, 0.0, -1.9]], [[0.0] * 3]])
    assert torch.allclose(table["motion"], expected)
    assert table.motion_active().tolist() == [True, True, False]


def test_freeze_rows_zeroes_the_gradient_of_masked_or_listed_rows_only():
    table = GaussianTable({"means": torch.zeros(4, 3), "motion": torch.zeros(4, 2, 3)})
    opt = TableOptimizer(table, {"means": 0.1, "motion": 0.1}, {})
    for rows in (torch.tensor([True, False, True, False]), torch.tensor([0, 2])):
        grad = torch.arange(24.0).reshape(4, 2, 3) + 1
        table["motion"].grad = grad.clone()
        opt.freeze_rows("motion", rows)
        assert torch.equal(table["motion"].grad[[0, 2]], torch.zeros(2, 2, 3))
        assert torch.equal(table["motion"].grad[[1, 3]], grad[[1, 3]])
    opt.freeze_rows("means", torch.tensor([True, True, False, False]))  # no gradient yet: nothing to do
    assert table["means"].grad is None


@pytest.mark.parametrize(
    "mask_box, margin, expected",
    [((10, 20, 30, 40), 5, (5, 15, 40, 33)), ((0, 0, 8, 8), 16, (0, 0, 24, 24)), (None, 5, (0, 0, 64, 48))],
)
def test_crop_is_the_mask_box_plus_margin_inside_the_image(mask_box, margin, expected):
    mask = np.zeros((48, 64), np.uint8)
    if mask_box:
        x, y, w, h = mask_box
        mask[y : y + h, x : x + w] = 255
    assert crop_box(mask if mask_box else None, 64, 48, margin) == expected


def test_model_config_refuses_nonsense():
    with pytest.raises(ValueError, match="color"):
        ModelConfig(color="rainbow").validate()
    with pytest.raises(ValueError, match="num_gaussians"):
        ModelConfig(num_gaussians=10, max_gaussians=5).validate()
    with pytest.raises(ValueError, match="unknown preset"):
        preset("turbo")


def test_temporal_split_spreads_copies_of_an_always_on_gaussian_over_the_training_time(tiny_frames):
    """Spacetime densification: a dynamic Gaussian present at all times becomes copies on short
    windows, centred evenly over the frames' time range, each crossing its neighbour at ~half opacity
    (per-Gaussian polynomials: shared bases are not split in time)."""
    from avatar_helpers import small_config

    from stg_node.avatar.trainer import Trainer

    trainer = Trainer(small_config(**{"model.motion_basis": 0}), seed=0)
    trainer.add_frames(tiny_frames)
    model, d = trainer.model, trainer.densifier
    rows = torch.tensor([3, 7])
    model.table["motion_gate"].data[rows] = 1.0
    hot = torch.zeros(model.table.num, dtype=torch.bool)
    hot[rows] = True
    time_range = trainer.time_range()
    sources, new = d._temporal_split_rows(model, time_range, hot, torch.ones(model.table.num), room=1000)
    times = sorted(model.time_axis(f.frame.time) for f in trainer.store.frames)
    span = times[-1] - times[0]
    k = new["means"].shape[0] // 2
    assert sorted(sources.tolist()) == [3, 7] and 2 <= k <= d.config.temporal_split_max
    centres = new["t_center"][:k]
    spacing = span / k
    expected = times[0] + (torch.arange(k) + 0.5) * spacing
    assert torch.allclose(centres, expected.float(), atol=1e-5)
    scale = new["t_log_scale"][:k].exp()
    assert torch.allclose(scale, torch.full((k,), max(0.6 * spacing, d.config.min_time_scale)), rtol=1e-5)
    assert torch.equal(new["means"][:k], model.table["means"][3].expand(k, 3))
    # No room, no split; room for one Gaussian's copies only, only the first (by gradient) is split.
    grads = torch.ones(model.table.num)
    assert d._temporal_split_rows(model, time_range, hot, grads, room=0) is None
    assert d._temporal_split_rows(model, time_range, hot, grads, room=k - 1) is None  # not even one whole set
    grads[7] = 2.0
    sources, new = d._temporal_split_rows(model, time_range, hot, grads, room=k)
    assert sources.tolist() == [7] and new["means"].shape[0] == k
    # Not dynamic, no split.
    model.table["motion_gate"].data[rows] = 0.0
    assert d._temporal_split_rows(model, time_range, hot, torch.ones(model.table.num), room=1000) is None


def test_rigidity_pulls_a_dynamic_gaussian_towards_its_neighbours_motion():
    from stg_node.avatar.rigidity import NeighbourGraph

    means = torch.tensor([[0.0, 0, 0], [0.01, 0, 0], [0.02, 0, 0], [1.0, 0, 0], [1.01, 0, 0]])
    table = GaussianTable(
        {
            "means": means,
            "motion_gate": torch.tensor([1.0, 0, 0, 0, 0]),
            "t_center": torch.zeros(5),
        }
    )
    graph = NeighbourGraph(k=2)
    offsets = torch.zeros(5, 3)
    offsets[0] = torch.tensor([0.03, 0.0, -0.01])  # 3 cm and 1 cm away from its static neighbours
    loss = graph.loss(table, offsets, None)
    assert graph.rows.tolist() == [0] and sorted(graph.neighbours[0].tolist()) == [1, 2]
    assert float(loss) == pytest.approx(4.0)  # |3| + |1| cm, for each of the two neighbours
    # Presence weights: a neighbour absent at this instant does not count.
    temporal = torch.tensor([1.0, 1.0, 0.0, 1.0, 1.0])
    offsets[2] = torch.tensor([5.0, 0, 0])
    assert float(graph.loss(table, offsets, temporal)) == pytest.approx(4.0)
    # The graph follows the table: new dynamic rows are picked up.
    table["motion_gate"].data[3] = 1.0
    graph.loss(table, offsets, None)
    assert graph.rows.tolist() == [0, 3] and 4 in graph.neighbours[1].tolist()


def test_the_rigidity_graph_is_rebuilt_after_a_prune_and_an_append_of_as_many_rows():
    """A prune followed by an append leaves the row count and the number of dynamic rows as they
    were (and a new tensor may even sit where the old one was freed): the graph must still see
    that the rows changed, and its neighbours must be those of the new rows (brute force here)."""
    from stg_node.avatar.rigidity import NeighbourGraph

    means = torch.tensor([[0.0, 0, 0], [0.01, 0, 0], [0.5, 0, 0], [1.0, 0, 0], [1.02, 0, 0]])
    gate = torch.tensor([1.0, 0, 0, 1.0, 0])
    table = GaussianTable({"means": means, "motion_gate": gate, "t_center": torch.zeros(5)})
    opt = TableOptimizer(table, {"means": 0.1, "t_center": 0.0}, {})
    graph = NeighbourGraph(k=1)
    offsets = torch.zeros(5, 3)
    graph.loss(table, offsets, None)
    graph.loss(table, offsets, None)
    assert graph.builds == 1  # nothing changed: built once
    assert graph.neighbours[:, 0].tolist() == [1, 4]
    # Prune row 1 (row 0's neighbour), then append a row beside row 0: still 5 rows, 2 dynamic.
    opt.keep(torch.tensor([True, False, True, True, True]))
    opt.append(
        {"means": torch.tensor([[0.02, 0, 0]]), "motion_gate": torch.zeros(1), "t_center": torch.zeros(1)}
    )
    assert table.num == 5 and int(table.motion_gate().sum()) == 2
    graph.loss(table, offsets, None)
    assert graph.builds == 2
    points = table["means"].detach()
    dist = torch.cdist(points[graph.rows], points)
    dist[torch.arange(len(graph.rows)), graph.rows] = float("inf")
    assert graph.rows.tolist() == [0, 2]
    assert graph.neighbours[:, 0].tolist() == dist.argmin(dim=1).tolist() == [4, 3]  # 0 -> 0.02, 1.0 -> 1.02
    # A gate edited in place (as densification does) with the same count also rebuilds it.
    table["motion_gate"].data[:] = torch.tensor([0.0, 1.0, 1.0, 0.0, 0.0])
    graph.loss(table, offsets, None)
    assert graph.builds == 3 and graph.rows.tolist() == [1, 2]


def test_the_render_time_skin_weights_follow_a_prune_and_an_append_of_as_many_rows(tiny_frames):
    """A render without gradients reuses the blended skinning weights while the table is unchanged;
    a prune followed by an append (same row count, the new row's correction different) must not
    serve the old rows' weights: checked against the weights computed afresh."""
    from test_avatar_trainer import small_config

    from stg_node.avatar.trainer import Trainer

    trainer = Trainer(small_config(iterations=2), seed=0)
    trainer.add_frames(tiny_frames[:2])
    trainer.step()
    model, opt = trainer.model, trainer.optimizer
    for row in range(3):
        with torch.no_grad():
            before = model._render_skin_weights()
            assert model._render_skin_weights() is before  # unchanged table: reused
        keep = torch.ones(model.table.num, dtype=torch.bool)
        keep[row] = False
        opt.keep(keep)
        new = {name: model.table[name].detach()[:1].clone() for name in model.table.names()}
        new["skin_delta"] = new["skin_delta"] + torch.linspace(-2.0, 2.0, new["skin_delta"].shape[1])
        opt.append(new)
        with torch.no_grad():
            got, truth = model._render_skin_weights(), model.skin_weights()
        assert got.shape == before.shape and torch.equal(got, truth)
        assert not torch.allclose(got[-1], truth[0])  # the appended row is not a copy of row 0's weights


def test_the_pose_index_reaches_as_far_as_consecutive_training_poses_are_apart():
    """Closed form: two rotations about one axis differ by 2 sqrt(2) |sin(d/2)| (Frobenius); keys added
    out of time order are measured in time order."""
    index = PoseTimeIndex()
    angles = [0.0, 0.1, 0.2, 0.4, 0.5]  # a step of 0.2 between the times 2 and 3
    for i in (3, 0, 4, 1, 2):
        index.add(_pose(angles[i]), float(i))
    assert index.reach() == pytest.approx(2 * math.sqrt(2) * math.sin(0.1), rel=1e-5)
    assert index.within_reach(_pose(0.65)) and index.within_reach(_pose(0.3))
    assert not index.within_reach(_pose(0.75))  # 0.25 beyond the last key: farther than any step
    index.add(_pose(0.75), 5.0)  # a step of 0.25 after the last time: the reach (kept between calls) follows
    assert index.reach() == pytest.approx(2 * math.sqrt(2) * math.sin(0.125), rel=1e-5)
    index.retain(np.asarray([0.0, 1.0, 2.0], np.float32))  # and the retained keys' steps of 0.1 only
    assert index.reach() == pytest.approx(2 * math.sqrt(2) * math.sin(0.05), rel=1e-5)
    single = PoseTimeIndex()
    single.add(_pose(0.0), 0.0)
    assert single.reach() == 0.0 and single.within_reach(_pose(1.0))  # no measure of a step: today's rule


def _chord(delta: float) -> float:
    """Frobenius distance between two rotations about one axis ``delta`` apart (closed form)."""
    return 2 * math.sqrt(2) * abs(math.sin(delta / 2))


def _walk(angles, times=None) -> PoseTimeIndex:
    index = PoseTimeIndex()
    for i, angle in enumerate(angles):
        index.add(_pose(angle), float(i if times is None else times[i]))
    return index


def test_the_reach_ignores_the_trackers_glitches_jumps_and_the_step_across_skipped_frames():
    """A walk of 0.1 rad a frame. One frame flipped by 1.2 rad (a one-frame glitch), a flip by 1.2 rad
    that stays for three frames (two jumps), and a run of skipped frames (times 10 -> 14: a 0.4 rad
    step) would each set the reach to their step's chord. None is the motion's step: the reach stays
    the 0.1 rad chord, and a pose three steps off every training pose is out of it."""
    walk = [0.1 * i for i in range(20)]
    assert _walk(walk).reach() == pytest.approx(_chord(0.1), rel=1e-5)

    glitch = _walk([a + (1.2 if i == 7 else 0.0) for i, a in enumerate(walk)])
    assert glitch.reach() == pytest.approx(_chord(0.1), rel=1e-5)
    elsewhere = _pose(0.7)
    elsewhere[17, 2] = 0.3  # the other shoulder raised: 3 steps off every training pose, < the flip
    assert not glitch.within_reach(elsewhere)

    flipped = _walk([a + (1.2 if 7 <= i < 10 else 0.0) for i, a in enumerate(walk)])
    assert flipped.reach() == pytest.approx(_chord(0.1), rel=1e-5)

    times = [*range(10), *range(14, 24)]
    skipped = _walk([0.1 * t for t in times], times)
    assert skipped.reach() == pytest.approx(_chord(0.1), rel=1e-5)


def test_the_reach_keeps_real_motion_that_speeds_up_and_starts_from_rest():
    """Steps five times the walk's over a run of frames (a kick), and a start from standing still:
    the motion's own steps grow with their neighbours, so they are kept (the reach is the kick's)."""
    angles, angle = [], 0.0
    for i in range(30):
        angles.append(angle)
        angle += 0.5 if 10 <= i < 14 else (0.0 if i < 5 else 0.1)
    assert _walk(angles).reach() == pytest.approx(_chord(0.5), rel=1e-5)


def test_the_pose_distances_kept_between_time_and_trust_follow_the_pose_and_the_keys():
    """A render without a time asks for a pose's time and then its trust; the distances kept between
    the two calls must be those of the pose asked and the keys of now (a stale answer would give the
    old instant or the old fade)."""
    index = PoseTimeIndex()
    for i, angle in enumerate([0.0, 0.1, 0.2]):
        index.add(_pose(angle), float(i))
    far = _pose(0.9)
    assert index.time_for(far) == (2.0, 2) and index.trust(far) == 0.0
    assert index.distances(far) is index.distances(far.astype(np.float64))  # same pose: kept
    assert index.time_for(_pose(0.0)) == (0.0, 0)  # another pose: measured again
    index.add(far, 3.0)  # the pose becomes a key: its distance 0, its own instant
    assert index.distances(far)[-1] == 0.0
    assert index.time_for(far) == (3.0, 3) and index.trust(far) == 1.0
    index.retain(np.asarray([0.0, 1.0], np.float32))  # and gone again
    assert index.distances(far).shape == (2,) and index.time_for(far) == (1.0, 1)
    index.set(index.keys[:1].copy(), index.times[:1].copy())
    assert index.time_for(far) == (0.0, 0)
    truth = np.linalg.norm(index.keys - pose_key(far), axis=1)
    np.testing.assert_array_equal(index.distances(far), truth)


def test_an_instants_trust_fades_from_the_reach_to_twice_it_as_a_smoothstep_of_the_distance():
    """Closed form on the keys above (reach r = 2 sqrt(2) sin 0.1; the last key at 0.5 rad): a pose at
    0.5 + a lies 2 sqrt(2) sin(a / 2) from it, and its trust is 1 - 3x^2 + 2x^3 with x = (d - r) / r,
    1 within the reach and 0 from twice it on."""
    assert FADE_END == 2.0
    index = PoseTimeIndex()
    for i, angle in enumerate([0.0, 0.1, 0.2, 0.4, 0.5]):
        index.add(_pose(angle), float(i))
    r = 2 * math.sqrt(2) * math.sin(0.1)

    def beyond(d):  # the pose d (Frobenius) past the last key
        return _pose(0.5 + 2 * math.asin(d / (2 * math.sqrt(2))))

    assert index.trust(_pose(0.3)) == 1.0 and index.trust(beyond(0.999 * r)) == 1.0
    for x in (0.25, 0.5, 0.75):
        assert index.trust(beyond((1 + x) * r)) == pytest.approx(1 - 3 * x**2 + 2 * x**3, abs=1e-4)
    assert index.trust(beyond(1.001 * r)) > 0.999 and index.trust(beyond(1.999 * r)) < 1e-5  # no step
    assert index.trust(beyond(2.001 * r)) == 0.0 and index.trust(_pose(1.5)) == 0.0
    assert not index.within_reach(beyond(1.25 * r))
    same = PoseTimeIndex()  # training poses all alike: no width to fade over
    same.add(_pose(0.0), 0.0)
    same.add(_pose(0.0), 1.0)
    assert same.trust(_pose(0.0)) == 1.0 and same.trust(_pose(0.1)) == 0.0
