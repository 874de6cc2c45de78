"""model.normal_sign = "auto" (normal_trial.py): the light's contrast against closed forms, and the
trainer's decision at normal_decide_iter (outward normals only under a light with contrast)."""

from __future__ import annotations

import math

import pytest
import torch

from stg_node.avatar.normal_trial import choose, light_contrast, sphere_directions
from stg_node.avatar.shading import Shading


def _shading_with(ambient: float, lamp: float, direction=(0.3, -0.5, 0.8)) -> Shading:
    """A distant-light Shading whose softplus parameters give ``ambient`` and one lamp ``lamp``."""
    shading = Shading("distant", light_count=1)
    inverse_softplus = lambda v: math.log(math.expm1(v))  # noqa: E731
    with torch.no_grad():
        shading.light.ambient.fill_(inverse_softplus(ambient))
        shading.light.colors.fill_(inverse_softplus(lamp))
        shading.light.directions.copy_(torch.tensor([direction]))
    return shading


def test_sphere_directions_are_even():
    d = sphere_directions(4096).double()
    assert torch.allclose(d.norm(dim=1), torch.ones(4096, dtype=torch.float64), atol=1e-6)
    # Moments of the uniform distribution on the sphere: E[x] = 0, E[x x^T] = I / 3.
    assert d.mean(dim=0).abs().max() < 1e-3
    assert torch.allclose(d.T @ d / 4096, torch.eye(3, dtype=torch.float64) / 3, atol=2e-3)


@pytest.mark.parametrize("ambient,lamp", [(0.3, 0.7), (1.0, 0.1), (0.05, 2.0)])
def test_contrast_of_one_lamp_matches_the_closed_form(ambient, lamp):
    """E(n) = a + c max(0, n.d): with x = n.d uniform on [-1, 1], max(0, x) has mean 1/4 and second
    moment 1/6, so std / mean = c sqrt(5/48) / (a + c/4) whatever the direction."""
    expected = lamp * math.sqrt(5.0 / 48.0) / (ambient + lamp / 4.0)
    for direction in ((0.3, -0.5, 0.8), (0.0, 0.0, -1.0)):
        assert light_contrast(_shading_with(ambient, lamp, direction)) == pytest.approx(expected, rel=0.01)


def test_uniform_light_has_no_contrast_in_either_light_model():
    assert light_contrast(Shading("sh")) == pytest.approx(0.0, abs=1e-6)  # SHLight starts uniform
    assert light_contrast(_shading_with(1.0, 1e-6)) == pytest.approx(0.0, abs=1e-5)


def test_choose_says_why():
    sign, why = choose(0.48, 0.25)
    assert sign == "outward" and "0.48" in why and ">= 0.25" in why
    sign, why = choose(0.1, 0.25)
    assert sign == "camera" and "0.10" in why and "< 0.25" in why


def test_the_default_decides_the_sign():
    """The presets train with "auto" (a new default: it fails where they keep the camera's sign)."""
    from stg_node.avatar import PRESETS, preset
    from stg_node.avatar.config import ModelConfig, TrainConfig

    assert ModelConfig().normal_sign == "auto"
    assert all(preset(name).model.normal_sign == "auto" for name in PRESETS)
    assert TrainConfig().normal_decide_iter > 0 and 0 < TrainConfig().normal_min_contrast < 1


@pytest.mark.parametrize("threshold,expected", [(0.0, "outward"), (10.0, "camera")])
def test_trainer_decides_at_normal_decide_iter(tiny_frames, monkeypatch, tmp_path, threshold, expected):
    """Camera normals until the decision, then the chosen sign, in the steps, the config, the
    published model, the summary and a resumed checkpoint."""
    from avatar_helpers import small_config, spy_normal_signs

    from stg_node.avatar.snapshot import model_from_snapshot
    from stg_node.avatar.trainer import Trainer

    seen = spy_normal_signs(monkeypatch)
    config = small_config(iterations=6, normal_decide_iter=3, normal_min_contrast=threshold)
    trainer = Trainer(config, seed=0)
    trainer.add_frames(tiny_frames[:2])
    assert trainer.normal_sign_report()["chose"] == "camera"
    assert "not decided yet" in trainer.normal_sign_report()["why"]
    per_step = []
    for _ in range(5):
        seen.clear()
        trainer.step()
        per_step.append(set(seen))
    assert per_step[:3] == [{False}] * 3  # iterations 0-2: the camera's sign
    assert per_step[3:] == [{expected == "outward"}] * 2
    report = trainer.normal_sign_report()
    assert report["chose"] == expected and report["iteration"] == 3
    assert report["evidence"]["light_contrast"] == pytest.approx(
        light_contrast(trainer.model.shading), abs=0.05
    )
    assert trainer.config.model.normal_sign == expected
    assert model_from_snapshot(trainer.snapshot()).config.normal_sign == expected
    path = trainer.save(tmp_path / "ckpt.stgsnap")
    resumed = Trainer.load(path)
    assert resumed.config.model.normal_sign == expected
    assert resumed.normal_sign_report() == report


def test_no_decision_without_shading_or_with_a_fixed_sign(tiny_frames):
    from avatar_helpers import small_config

    from stg_node.avatar.trainer import Trainer

    for changes, chose in (({"model.shading": False}, "auto"), ({"model.normal_sign": "camera"}, "camera")):
        trainer = Trainer(small_config(iterations=3, normal_decide_iter=1, **changes), seed=0)
        trainer.add_frames(tiny_frames[:2])
        for _ in range(3):
            trainer.step()
        assert trainer.config.model.normal_sign == chose
        assert "normal_sign.contrast" not in trainer.notes


def test_the_seen_contrast_ignores_a_lamp_only_unseen_normals_receive():
    """One camera along +z and a lamp straight behind the subject: over the whole sphere the light
    has contrast, over the normals the camera faces (all lit by the ambient alone) it has none."""
    from stg_node.avatar.shading import Shading

    shading = Shading(light_count=1)
    shading.add_view(torch.tensor([0.0, 0.0, 1.0]))
    with torch.no_grad():
        shading.light.directions.copy_(torch.tensor([[0.0, 0.0, -1.0]]))
        shading.light.colors.fill_(2.0)
    assert light_contrast(shading) > 0.3
    assert light_contrast(shading, seen_only=True) < 0.02
