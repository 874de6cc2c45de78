"""Frames of several cameras paired by time stamp (stg_node.tracking.sync): files and live frames."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from stg_node.tracking.sync import (
    StampMatcher,
    UnsynchronisedError,
    match_frames,
    match_sources,
    open_sources,
    synced_frames,
)


def _video(path, count, fps, colour_step):
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (64, 48))
    for i in range(count):
        writer.write(np.full((48, 64, 3), (i * colour_step) % 256, np.uint8))
    writer.release()
    return path


def test_equal_rates_pair_frame_by_frame_with_the_skew_recorded():
    a = np.arange(100) / 30.0
    b = a + 0.004  # 4 ms later, well inside half a frame
    match = match_frames([a, b], ["front", "side"])
    assert len(match) == 100
    np.testing.assert_array_equal(match.indices[:, 0], match.indices[:, 1])
    assert match.max_skew_s == pytest.approx(0.004)


def test_the_slower_camera_leads_and_the_faster_one_gives_its_nearest_frames():
    fast = np.arange(200) / 60.0
    slow = np.arange(100) / 30.0
    match = match_frames([fast, slow], ["fast", "slow"])
    assert match.leader == 1
    np.testing.assert_array_equal(match.indices[:, 0], 2 * np.arange(100))
    assert match.dropped == {"fast": 100}


def test_a_late_start_leaves_out_the_instants_before_it():
    a = np.arange(90) / 30.0
    b = np.arange(60) / 30.0 + 1.0  # the side camera starts a second later
    match = match_frames([a, b], ["front", "side"])
    assert match.times[0] == pytest.approx(1.0) and match.times[-1] == pytest.approx(89 / 30)
    assert len(match) == 60


def test_a_camera_that_stalled_is_an_error_saying_where_and_by_how_much():
    a = np.arange(300) / 30.0
    b = np.delete(a, np.arange(150, 160)) + 0.002  # a third of a second lost at 5 s
    with pytest.raises(UnsynchronisedError) as err:
        match_frames([a, b], ["front", "side"])
    text = str(err.value)
    assert "'side' is not synchronised with 'front'" in text
    assert "-31.3 ms away at 5.00 s (tolerance 16.7 ms)" in text
    assert "168.7 ms at worst, at 10 of 300 instants" in text
    assert "STEM.timestamps.txt" in text
    assert len(match_frames([a, b], ["front", "side"], max_skew_s=0.2)) == 300


def test_capture_times_beside_a_video_replace_its_container_times(tmp_path):
    video = _video(tmp_path / "side.avi", 6, 30.0, 10)
    (tmp_path / "side.timestamps.txt").write_text("# timestamp format v2\n0\n33.3\n66.7\n200\n233.3\n266.7\n")
    from stg_node.tracking.sync import read_timestamps

    times = read_timestamps(open_sources([video])[0])
    np.testing.assert_allclose(times, [0, 0.0333, 0.0667, 0.2, 0.2333, 0.2667], atol=1e-4)
    (tmp_path / "side.timestamps.txt").write_text("0\nsoon\n")
    with pytest.raises(UnsynchronisedError, match="timestamps.txt:2: 'soon'"):
        read_timestamps(open_sources([video])[0])


def test_recordings_that_never_overlap_are_an_error():
    with pytest.raises(UnsynchronisedError, match="do not overlap"):
        match_frames([np.arange(10) / 30.0, np.arange(10) / 30.0 + 5.0], ["a", "b"])


def test_video_files_are_decoded_once_in_step(tmp_path):
    a = _video(tmp_path / "a.avi", 21, 30.0, 10)
    b = _video(tmp_path / "b.avi", 12, 15.0, 20)  # half the rate: every other frame of a
    sources = open_sources([a, b])
    match = match_sources(sources, ["a", "b"])
    assert match.leader == 1 and len(match) == 11  # a ends at 20/30 s: b's frames 0..10 (10/15 s)
    sets = list(synced_frames(sources, match))
    assert [s.frames[0].index for s in sets] == list(range(0, 21, 2))
    assert [s.frames[1].index for s in sets] == list(range(11))
    # The images are the ones the indices name (grey level = index x step).
    assert abs(int(sets[3].frames[0].image[0, 0, 0]) - 60) <= 3
    assert abs(int(sets[3].frames[1].image[0, 0, 0]) - 60) <= 3


def test_live_frames_come_out_as_sets_whose_stamps_agree():
    matcher = StampMatcher(["a", "b", "c"], tolerance_ns=10_000_000)
    ms = 1_000_000
    assert matcher.push("a", 1000 * ms, "a0") is None
    assert matcher.push("b", 1003 * ms, "b0") is None
    stamp, items = matcher.push("c", 998 * ms, "c0")
    assert items == {"a": "a0", "b": "b0", "c": "c0"} and stamp == 1003 * ms
    # The next instant: c is 40 ms late, too far from a1 and b1 (tolerance 10 ms) ...
    assert matcher.push("a", 1033 * ms, "a1") is None
    assert matcher.push("b", 1034 * ms, "b1") is None
    assert matcher.push("c", 1073 * ms, "c1") is None
    # ... but a and b's next frames are near it: that set goes out, a1 and b1 never do.
    assert matcher.push("a", 1066 * ms, "a2") is None
    stamp, items = matcher.push("b", 1068 * ms, "b2")
    assert items == {"a": "a2", "b": "b2", "c": "c1"} and stamp == 1073 * ms
    # Nothing is handed out twice: the frames used and the older ones are gone.
    assert matcher.push("a", 1100 * ms, "a3") is None
    assert matcher.push("b", 1101 * ms, "b3") is None
    with pytest.raises(KeyError):
        matcher.push("d", 0, None)
