"""A video's ``--train-frames A:B`` counts the video's frames, not the tracked folder's positions: the
folder holds only the frames the tracker was sure of, under their own frame numbers. Its novel-pose
split is every tracked frame from B on."""

from __future__ import annotations

import numpy as np
import pytest
from fixtures.datasets import write_folder

from stg_node.avatar.data_spec import DataSpec
from stg_node.data.errors import DatasetError

SKIPPED = (3, 4, 7, 40)  # the tracker was unsure of these


@pytest.fixture(scope="module")
def tracked(tmp_path_factory):
    """A 45-frame tracked folder as video_to_folder writes it: the confident frames' images under
    their frame numbers and one pose row per kept frame, with its number."""
    root = tmp_path_factory.mktemp("video_data")
    write_folder(root, num_frames=45)
    for frame in SKIPPED:
        (root / "images" / "front" / f"{frame:06d}.png").unlink()
        (root / "masks" / "front" / f"{frame:06d}.png").unlink()
    with np.load(root / "poses.npz") as npz:
        data = dict(npz)
    kept = np.array([f for f in range(45) if f not in SKIPPED])
    for key in ("poses", "Rh", "Th"):
        data[key] = data[key][kept]
    np.savez(root / "poses.npz", frames=kept, **data)
    return root


def test_a_videos_training_range_is_its_own_frame_numbers(tracked):
    spec = DataSpec(str(tracked), "video", (0, 10), size=64)
    assert spec.open("train").frames == [0, 1, 2, 5, 6, 8, 9]
    # every kept frame from frame 10 on (a clip's held-out tail, not every 30th frame of it)
    assert spec.open("novel_pose").frames == [f for f in range(10, 45) if f not in SKIPPED]
    # The same folder as a plain folder dataset keeps positions (a folder may start at any number).
    assert DataSpec(str(tracked), "folder", (0, 10), size=64).open("train").frames == [
        0, 1, 2, 5, 6, 8, 9, 10, 11, 12
    ]  # fmt: skip


def test_a_range_the_tracker_kept_nothing_of_is_refused_with_what_it_kept(tracked):
    with pytest.raises(DatasetError, match=r"no tracked frame in --train-frames 3:5 .*0\.\.44"):
        DataSpec(str(tracked), "video", (3, 5), size=64).open("train")
