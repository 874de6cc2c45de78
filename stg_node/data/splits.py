"""Which cameras and frames make up a split (train / novel view / novel pose) for each dataset.

The ZJU-MoCap numbers reproduce 3DGS-Avatar's monocular protocol, read from its per-subject
configs (``configs/dataset/zjumocap_<subject>_mono.yaml`` in mikeqzy/3dgs-avatar-release):
train on camera 1 over ``train_frames``; novel-view test on every other camera every 30th frame
of the same range (``test_frames.view``). 3DGS-Avatar defines no novel-pose test for ZJU-MoCap;
ours takes every 30th frame after the training range on all cameras, and is empty for 392/393,
which 3DGS-Avatar trains on in full. docs/DATASETS.md holds the table.

Frame numbers are positions in the sequence (0 = the first frame that has images and SMPL
parameters), the same numbering 3DGS-Avatar's loader slices with.
"""

from __future__ import annotations

from dataclasses import dataclass

from stg_node.data.errors import DatasetError

SPLIT_NAMES = ("train", "novel_view", "novel_pose", "all")
TEST_STRIDE = 30  # every 30th frame for the test splits, as 3DGS-Avatar's test_frames


@dataclass(frozen=True)
class FrameRange:
    """``range(start, stop, step)`` over frame positions; ``stop=None`` means to the end."""

    start: int = 0
    stop: int | None = None
    step: int = 1

    def resolve(self, num_frames: int) -> list[int]:
        stop = num_frames if self.stop is None else min(self.stop, num_frames)
        return list(range(self.start, stop, self.step))


@dataclass(frozen=True)
class SplitSpec:
    """Cameras (by name; None = every camera but ``exclude``) and frames of one split."""

    name: str
    frames: FrameRange
    cameras: tuple[str, ...] | None = None
    exclude: tuple[str, ...] = ()
    note: str = ""

    def resolve(
        self, available_cameras: list[str], num_frames: int, *, where: str = ""
    ) -> tuple[list[str], list[int]]:
        if self.cameras is None:
            cams = [c for c in available_cameras if c not in self.exclude]
        else:
            missing = [c for c in self.cameras if c not in available_cameras]
            if missing:
                raise DatasetError(
                    where or None,
                    f"split {self.name!r} needs camera(s) {missing}",
                    f"one of the cameras present: {available_cameras}",
                )
            cams = list(self.cameras)
        frames = self.frames.resolve(num_frames)
        if not cams or not frames:
            detail = self.note or f"frames {self.frames} of {num_frames}, cameras {cams}"
            raise DatasetError(
                where or None,
                f"split {self.name!r} is empty: {detail}",
                "a split with at least one camera and one frame",
            )
        return cams, frames


@dataclass(frozen=True)
class MonocularProtocol:
    """A training camera and training frame range; the test splits follow from them."""

    train_camera: str
    train_frames: FrameRange
    source: str = ""

    def split(self, name: str) -> SplitSpec:
        start, stop = self.train_frames.start, self.train_frames.stop
        if name == "train":
            return SplitSpec("train", self.train_frames, cameras=(self.train_camera,))
        if name == "novel_view":
            return SplitSpec("novel_view", FrameRange(start, stop, TEST_STRIDE), exclude=(self.train_camera,))
        if name == "novel_pose":
            if stop is None:
                return SplitSpec(
                    "novel_pose",
                    FrameRange(0, 0),
                    note="the protocol trains on every frame, so no poses are held out",
                )
            return SplitSpec("novel_pose", FrameRange(stop, None, TEST_STRIDE))
        if name == "all":
            return SplitSpec("all", FrameRange())
        raise ValueError(f"unknown split {name!r}; use one of {SPLIT_NAMES}")


@dataclass(frozen=True)
class RigProtocol:
    """Several training cameras (a rig, docs/RIGS.md) over a frame range: novel view = every other
    camera every 30th training frame; novel pose = every 30th frame after the range, all cameras.
    The monocular protocol with a set of cameras in place of one."""

    train_cameras: tuple[str, ...]
    train_frames: FrameRange
    source: str = ""

    def split(self, name: str) -> SplitSpec:
        start, stop = self.train_frames.start, self.train_frames.stop
        if name == "train":
            return SplitSpec("train", self.train_frames, cameras=self.train_cameras)
        if name == "novel_view":
            return SplitSpec(
                "novel_view",
                FrameRange(start, stop, TEST_STRIDE),
                exclude=self.train_cameras,
                note=f"every camera trains ({', '.join(self.train_cameras)}): none is left for novel views",
            )
        return MonocularProtocol(self.train_cameras[0], self.train_frames, self.source).split(name)


_3DGS_AVATAR = "3DGS-Avatar configs/dataset/zjumocap_{}_mono.yaml"

# 3DGS-Avatar monocular protocol: train_views ['1'], train_frames [0, N, 1] (N = 0: all frames).
ZJU_MONO_PROTOCOLS: dict[str, MonocularProtocol] = {
    "377": MonocularProtocol("1", FrameRange(0, 570, 1), _3DGS_AVATAR.format(377)),
    "386": MonocularProtocol("1", FrameRange(0, 540, 1), _3DGS_AVATAR.format(386)),
    "387": MonocularProtocol("1", FrameRange(0, 540, 1), _3DGS_AVATAR.format(387)),
    "392": MonocularProtocol("1", FrameRange(0, None, 1), _3DGS_AVATAR.format(392)),
    "393": MonocularProtocol("1", FrameRange(0, None, 1), _3DGS_AVATAR.format(393)),
    "394": MonocularProtocol("1", FrameRange(0, 475, 1), _3DGS_AVATAR.format(394)),
}


def zju_protocol(subject: str | None, train_camera: str = "1") -> MonocularProtocol:
    """The protocol for a ZJU-MoCap subject ('377', 'CoreView_377', 'my_377'); others train on all frames."""
    key = None if subject is None else "".join(ch for ch in subject if ch.isdigit())[-3:]
    base = ZJU_MONO_PROTOCOLS.get(key or "")
    if base is None:
        return MonocularProtocol(train_camera, FrameRange(), "default: camera 1, every frame")
    if train_camera != base.train_camera:
        return MonocularProtocol(train_camera, base.train_frames, base.source + f" (camera {train_camera})")
    return base
