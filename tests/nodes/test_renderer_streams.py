"""The renderer node's colour streams through the adapter: live views name their stream, one-shots
do not, and an avatar implementation without streams (the tests' fake, older packages) still
renders."""

from __future__ import annotations

import types

import numpy as np

from stg_node.nodes.avatar_adapter import RendererAdapter


class _Out:
    image = np.zeros((2, 2, 3), np.uint8)
    alpha = np.zeros((2, 2), np.uint8)
    depth = None
    render_ms = 1.0


class WithStreams:
    def __init__(self):
        self.calls = []

    def render(self, camera, smpl, time=None, *, background=(0, 0, 0), stream=None):
        self.calls.append(stream)
        return _Out()


class WithoutStreams:
    def __init__(self):
        self.calls = 0

    def render(self, camera, smpl, time=None, *, background=(0, 0, 0)):
        self.calls += 1
        return _Out()


def test_streams_reach_an_avatar_that_takes_them_and_one_shots_stay_exact():
    renderer = WithStreams()
    adapter = RendererAdapter(renderer, version=1)
    adapter.render(None, None, stream="view:phone")
    adapter.render(None, None)  # a one-shot request
    assert renderer.calls == ["view:phone", None]


def test_an_avatar_without_streams_still_renders():
    renderer = WithoutStreams()
    adapter = RendererAdapter(renderer, version=1)
    out = adapter.render(None, None, stream="view:phone")
    assert renderer.calls == 1 and out.image.shape == (2, 2, 3)


def test_the_refresh_setting_reaches_only_renderers_that_take_it(monkeypatch):
    seen = {}

    class Taking:
        @classmethod
        def from_snapshot(cls, msg, device="cpu", backend="auto", color_refresh_every=1):
            seen["refresh"] = color_refresh_every
            return WithStreams()

    class Older:
        @classmethod
        def from_snapshot(cls, msg, device="cpu", backend="auto"):
            seen["older"] = True
            return WithoutStreams()

    msg = types.SimpleNamespace(model_version=3)
    for cls in (Taking, Older):
        module = types.SimpleNamespace(AvatarRenderer=cls)
        monkeypatch.setattr("stg_node.nodes.avatar_adapter.avatar_module", lambda name, m=module: m)
        adapter = RendererAdapter.from_snapshot(msg, color_refresh_every=3)
        assert adapter.version == 3
    assert seen == {"refresh": 3, "older": True}
