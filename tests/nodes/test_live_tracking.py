"""The tracker node's built-in estimator (stg_node.nodes.live_tracking): options checked like node
parameters, one Tracker per camera, the tracker's own lag never taken for a cut, a real cut is."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from nodehelpers import ROOT

from stg_node.bus import Frame
from stg_node.nodes.live_tracking import LiveTrackingParams, TrackingEstimator, motion_time
from stg_node.nodes.params import ParamError, params_markdown
from stg_node.tracking import TrackOptions, fitting
from tests.tracking.trackhelpers import needs_blazepose


def test_options_are_the_track_options_a_live_camera_leaves_open():
    ours = {f.name for f in dataclasses.fields(LiveTrackingParams)}
    library = {f.name for f in dataclasses.fields(TrackOptions)}
    assert ours - {"max_gap_s", "silhouette_weight"} <= library  # same names, same meaning
    assert not ours & {"intrinsics", "fov_deg", "fps"}  # the camera comes with every frame
    for options, words in (
        ({"max_side": 10}, "max_side"),
        ({"detector": "onnx"}, "pose_model"),
        ({"mask": "plate"}, "plate"),
        ({"fov_deg": 60}, "unknown parameter"),
    ):
        with pytest.raises(ParamError, match=words):
            TrackingEstimator(**options)
    assert params_markdown(LiveTrackingParams) in (ROOT / "docs" / "NODES.md").read_text()


def _frames(clip, count: int):
    from stg_node.data.io import read_image

    calibration = json.loads(clip.calibration.read_text())
    for i in range(count):
        image = read_image(clip.subject / "Camera_B1" / f"{i:06d}.png")
        frame = Frame(index=i, time=i / 30, image=image, K=np.array(calibration["K"]),
                      R=np.array(calibration["R"]), t=np.array(calibration["t"]))  # fmt: skip
        yield frame


@needs_blazepose
def test_lag_is_not_a_cut_but_a_new_camera_or_an_index_going_back_is(clip, monkeypatch):
    starts = []
    real = fitting.SmplFitter._initialise

    def counting(self, *args, **kwargs):
        starts.append(self)
        return real(self, *args, **kwargs)

    monkeypatch.setattr(fitting.SmplFitter, "_initialise", counting)
    estimator = TrackingEstimator(max_side=256)
    frames = list(_frames(clip, 4))
    for k, frame in enumerate(frames[:3]):
        frame.header.stamp_ns = int((1000 + 1.2 * k) * 1e9)  # the tracker fell 1.2 s behind each time
        assert estimator.estimate(frame).confidence > 0.5
    assert len(starts) == 1  # tracked on from the last fit, not started afresh every time
    tracker = estimator.tracker
    np.testing.assert_array_equal(tracker.intrinsics.K, frames[0].K)

    frames[3].index = 1  # a video that starts over
    frames[3].header.stamp_ns = int(1004 * 1e9)
    estimator.estimate(frames[3])
    assert len(starts) == 2 and estimator.tracker is tracker

    small = Frame(index=5, time=0.2, image=np.ascontiguousarray(frames[3].image[::2, ::2]),
                  K=frames[3].K * [[0.5], [0.5], [1.0]], R=frames[3].R, t=frames[3].t)  # fmt: skip
    small.header.stamp_ns = int(1005 * 1e9)
    estimator.estimate(small)
    assert estimator.tracker is not tracker and estimator.tracker.intrinsics.width == clip.size // 2
    bad = Frame(index=6, time=0.3, image=small.image, K=np.diag([-1.0, 1.0, 1.0]), R=small.R, t=small.t)
    with pytest.raises(ValueError, match="pinhole"):
        estimator.estimate(bad)


def test_the_motion_clock_is_the_frames_time_and_the_stamp_only_where_time_is_unset():
    image = np.zeros((4, 4, 3), np.uint8)
    camera = {"K": np.eye(3), "R": np.eye(3), "t": np.zeros(3)}
    stamp_ns = 2_000_500_000_000
    frame = Frame(index=3, time=0.1, image=image, **camera)
    frame.header.stamp_ns = stamp_ns
    assert motion_time(frame) == pytest.approx(0.1)  # not when it was published
    unset = Frame(index=3, time=0.0, image=image, **camera)
    unset.header.stamp_ns = stamp_ns
    assert motion_time(unset) == pytest.approx(2000.5)
    first = Frame(index=0, time=0.0, image=image, **camera)
    first.header.stamp_ns = stamp_ns
    assert motion_time(first) == 0.0  # the first frame of a sequence is at 0


@needs_blazepose
def test_poses_do_not_depend_on_when_frames_were_published(clip):
    """A file replayed as fast as the tracker takes it: publish stamps follow the machine's load.
    The poses follow the frames' times only (they were load-dependent when the stamps were used)."""
    runs = []
    for spacing_s in (0.005, 1.7):  # an idle machine, and one that fell far behind
        estimator = TrackingEstimator(max_side=256)
        poses = []
        for k, frame in enumerate(_frames(clip, 4)):
            frame.header.stamp_ns = int((1000 + spacing_s * k) * 1e9)
            estimate = estimator.estimate(frame)
            poses.append(np.concatenate([estimate.smpl.poses.ravel(), estimate.smpl.Th.ravel()]))
        runs.append(np.stack(poses))
    np.testing.assert_array_equal(runs[0], runs[1])
