"""``KEY=VALUE`` settings on top of a preset (``stg-train --set``): applied where named, type-checked,
and refused with the known names when misspelt."""

from __future__ import annotations

import json

import pytest

from stg_node.avatar.config import apply_settings
from stg_node.avatar.presets import preset
from stg_node.cli import train as train_cli


def test_settings_reach_the_named_fields_and_nothing_else():
    base = preset("fast")
    out = apply_settings(
        base,
        ["model.spacetime=false", "model.max_gaussians=4000", "loss.ssim=0.3", "iterations=7"],
    )
    assert out.model.spacetime is False and out.model.max_gaussians == 4000
    assert out.loss.ssim == 0.3 and isinstance(out.loss.ssim, float)
    assert out.iterations == 7
    # everything else is the preset's
    assert (
        out.replace(
            **{
                "model.spacetime": base.model.spacetime,
                "model.max_gaussians": base.model.max_gaussians,
                "loss.ssim": base.loss.ssim,
                "iterations": base.iterations,
            }
        )
        == base
    )
    assert apply_settings(base, []) == base


def test_an_int_is_accepted_for_a_float_and_a_string_setting_takes_a_string():
    out = apply_settings(preset("fast"), ["loss.ssim=1", "model.color=sh"])
    assert out.loss.ssim == 1.0 and isinstance(out.loss.ssim, float)
    assert out.model.color == "sh"


@pytest.mark.parametrize("word", ["off", "on", "auto"])
def test_a_string_setting_takes_a_word_yaml_would_read_as_a_boolean(word):
    # YAML 1.1 reads on/off as booleans: `--set nonrigid=off` means the mode, not False
    out = apply_settings(preset("fast"), [f"nonrigid={word}"])
    assert out.nonrigid == word
    out.validate()
    with pytest.raises(ValueError, match="nonrigid must be one of"):
        apply_settings(preset("fast"), ["nonrigid=yes"]).validate()  # the word, refused by the mode's check


@pytest.mark.parametrize(
    ("item", "words"),
    [
        ("model.spacetim=false", ["unknown setting", "model.spacetime"]),
        ("modle.spacetime=false", ["unknown setting", "model"]),
        ("model=1", ["is a group", "model.num_gaussians"]),
        ("iterations.x=1", ["has no fields"]),
        ("model.spacetime=3", ["expected bool"]),
        ("model.max_gaussians=1.5", ["expected int"]),
        ("model.max_gaussians=true", ["expected int"]),
        ("model.color=4", ["expected str"]),
        ("model.spacetime", ["KEY=VALUE"]),
        ("=3", ["KEY=VALUE"]),
    ],
)
def test_bad_settings_are_refused_with_what_was_expected(item, words):
    with pytest.raises(ValueError) as err:
        apply_settings(preset("fast"), [item])
    for word in words:
        assert word in str(err.value)


def test_stg_train_set_lands_in_the_run_and_is_refused_on_resume(tiny_synth, tmp_path):
    out = tmp_path / "run"
    args = ["--data", str(tiny_synth), "--out", str(out), "--format", "synthetic", "--preset", "fast"]
    args += ["--size", "64", "--no-progress", "--iters", "2"]
    assert train_cli.main([*args, "--set", "model.spacetime=false", "--set", "model.color=sh"]) == 0
    config = json.loads((out / "config.json").read_text())["config"]
    assert config["model"]["spacetime"] is False and config["model"]["color"] == "sh"
    assert train_cli.main([*args, "--resume", "--set", "model.color=mlp"]) == 2
    assert train_cli.main([*args, "--set", "model.nope=1"]) == 2
