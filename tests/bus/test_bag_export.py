"""stg-bag info and export: counts and rates; images to MP4 (read back by OpenCV) and PNG (exact);
Foxglove view channels decoded by the mcap protobuf decoder from the schemas in the file."""

from __future__ import annotations

import io
import json

import cv2
import numpy as np
import pytest
from baghelpers import encoded_stream, image_frames, raw_frames
from bushelpers import sample_messages
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from scipy.spatial.transform import Rotation

from stg_node.body.smpl_io import SMPL_PARENTS
from stg_node.bus import BodyPose, Frame, encode
from stg_node.bus.foxglove_views import quaternion_xyzw
from stg_node.bus.recording import BagReader, BagWriter, bag_info
from stg_node.cli import bag as bag_cli

RNG = np.random.default_rng(3)


def _frames_bag(path, images, fps=10.0):
    rotations = Rotation.random(len(images), random_state=1).as_matrix()
    truth = []
    with BagWriter(path) as bag:
        for i, image in enumerate(images):
            frame = Frame(
                index=i,
                image=image,
                mask=(image[..., 0] > 128).astype(np.uint8) * 255,
                K=np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]]),
                R=rotations[i],
                t=RNG.normal(size=3),
            )
            stamp = 10**18 + int(i * 1e9 / fps)
            bag.write_frames(
                raw_frames(encode(frame, topic="camera/frame", seq=i, src="cam", stamp_ns=stamp)), stamp
            )
            truth.append(frame)
    return truth


def test_info_reports_topics_counts_rates_and_sizes(tmp_path):
    stream = encoded_stream(11, step_ns=10**8)  # every type, 0.1 s apart
    path = tmp_path / "s.mcap"
    with BagWriter(path) as bag:
        for t, frames in stream:
            bag.write_frames(frames, t)
    out = io.StringIO()
    assert bag_cli.main(["info", "--json", str(path)], out=out) == 0
    info = json.loads(out.getvalue())
    assert info["messages"] == len(stream) and not info["truncated"]
    assert info["duration_s"] == pytest.approx((stream[-1][0] - stream[0][0]) / 1e9)
    pose_times = [t for t, f in stream if f[0] == b"body/pose"]
    pose = next(t for t in info["topics"] if t["topic"] == "body/pose")
    assert pose["type"] == "BodyPose" and pose["messages"] == 11
    assert pose["rate_hz"] == pytest.approx(10 / ((pose_times[-1] - pose_times[0]) / 1e9))  # its own span
    assert pose["bytes"] == sum(len(b"".join(f[1:])) for _t, f in stream if f[0] == b"body/pose")
    out = io.StringIO()
    bag_cli.main(["info", str(path)], out=out)
    assert "body/pose        BodyPose          11" in out.getvalue()


def test_export_mp4_reads_back_with_opencv(tmp_path):
    images = image_frames(12)
    _frames_bag(tmp_path / "f.mcap", images)
    out = io.StringIO()
    video = tmp_path / "out.mp4"
    assert (
        bag_cli.main(
            ["export", str(tmp_path / "f.mcap"), "--topic", "camera/frame", "-o", str(video)], out=out
        )
        == 0
    )
    assert "wrote 12 frames" in out.getvalue() and "10.00 fps" in out.getvalue()
    capture = cv2.VideoCapture(str(video))
    fps = capture.get(cv2.CAP_PROP_FPS)
    got = []
    while True:
        ok, bgr = capture.read()
        if not ok:
            break
        got.append(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
    capture.release()
    assert len(got) == 12
    assert fps == pytest.approx(10.0)
    for a, b in zip(got, images, strict=True):
        assert a.shape == b.shape
        assert np.abs(a.astype(int) - b.astype(int)).mean() < 12  # lossy codec, smooth images


def test_export_png_folder_is_exact(tmp_path):
    images = image_frames(5)
    truth = _frames_bag(tmp_path / "f.mcap", images)
    folder = tmp_path / "pngs"
    assert (
        bag_cli.main(["export", str(tmp_path / "f.mcap"), "--topic", "camera/frame", "-o", str(folder)]) == 0
    )
    files = sorted(folder.glob("*.png"))
    assert len(files) == 5
    for path, image in zip(files, images, strict=True):
        np.testing.assert_array_equal(cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB), image)
    masks = tmp_path / "masks"
    assert (
        bag_cli.main(
            [
                "export",
                str(tmp_path / "f.mcap"),
                "--topic",
                "camera/frame",
                "--array",
                "mask",
                "--png",
                "-o",
                str(masks),
            ]
        )
        == 0
    )
    np.testing.assert_array_equal(cv2.imread(str(sorted(masks.glob("*.png"))[2]))[..., 0], truth[2].mask)


def test_export_errors_are_clear(tmp_path, capsys):
    _frames_bag(tmp_path / "f.mcap", image_frames(2))
    assert (
        bag_cli.main(
            ["export", str(tmp_path / "f.mcap"), "--topic", "avatar/image", "-o", str(tmp_path / "o.mp4")]
        )
        == 1
    )
    assert "topic 'avatar/image' is not in the recording (topics: camera/frame)" in capsys.readouterr().err
    assert bag_cli.main(["export", str(tmp_path / "f.mcap"), "-o", str(tmp_path / "o.mp4")]) == 2


@pytest.mark.parametrize("image_format", ["raw", "jpeg"])
def test_foxglove_view_channels_decode_with_the_schemas_in_the_file(tmp_path, image_format):
    images = image_frames(4)
    truth = _frames_bag(tmp_path / "f.mcap", images)
    pose = sample_messages()["BodyPose"]
    pose_with_joints = BodyPose(
        poses=pose.poses,
        Rh=pose.Rh,
        Th=pose.Th,
        betas=pose.betas,
        joints=RNG.normal(size=(24, 3)).astype(np.float32),
    )
    metrics = sample_messages()["TrainerMetrics"]  # loss is NaN
    extra = tmp_path / "g.mcap"
    with BagWriter(extra) as bag:
        for i, msg in enumerate((pose_with_joints, metrics)):
            frames = encode(msg, topic=msg.SPEC.topic, seq=0, src="x", stamp_ns=10**18 + i)
            bag.write_frames(raw_frames(frames), 10**18 + i)
    view = tmp_path / "view.mcap"
    argv = [
        "export",
        str(tmp_path / "f.mcap"),
        str(extra),
        "--foxglove",
        "-o",
        str(view),
        "--image-format",
        image_format,
    ]
    assert bag_cli.main(argv) == 0

    decoded: dict[str, list] = {}
    originals = []
    with open(view, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, message in reader.iter_messages():
            if channel.message_encoding == "stg-bus":
                originals.append(message.data)
            elif channel.message_encoding == "protobuf":
                proto = DecoderFactory().decoder_for("protobuf", schema)(message.data)
                decoded.setdefault(channel.topic, []).append((schema.name, proto))
            else:
                assert channel.message_encoding == "json" and schema.encoding == "jsonschema"
                decoded.setdefault(channel.topic, []).append((schema.name, json.loads(message.data)))
    assert originals == [m.data for m in BagReader([tmp_path / "f.mcap", extra]).messages()]
    info = bag_info(BagReader(view))  # stg-bag info measures the view file itself
    counts = {t.topic: t.messages for t in info.topics}
    assert counts["camera/frame"] == 4 and counts["view/camera/frame/image"] == 4
    assert counts["view/trainer/metrics/fields"] == 1 and info.messages == sum(counts.values())

    names = {topic: {n for n, _ in items} for topic, items in decoded.items()}
    assert names["view/camera/frame/image"] == {
        "foxglove.RawImage" if image_format == "raw" else "foxglove.CompressedImage"
    }
    assert names["view/camera/frame/mask"] == {"foxglove.RawImage"}
    assert names["view/camera/frame/calibration"] == {"foxglove.CameraCalibration"}
    assert names["view/camera/frame/tf"] == {"foxglove.FrameTransform"}
    assert names["view/body/pose/root"] == {"foxglove.PoseInFrame"}
    assert names["view/body/pose/joints"] == {"foxglove.PosesInFrame"}
    assert names["view/body/pose/skeleton"] == {"foxglove.SceneUpdate"}
    for i, (_n, image) in enumerate(decoded["view/camera/frame/image"]):
        if image_format == "raw":
            assert (image.width, image.height, image.encoding, image.step) == (64, 48, "rgb8", 192)
            assert image.data == images[i].tobytes()
        else:
            assert image.format == "jpeg"
            rgb = cv2.cvtColor(
                cv2.imdecode(np.frombuffer(image.data, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB
            )
            assert np.abs(rgb.astype(int) - images[i].astype(int)).mean() < 6
        assert image.timestamp.seconds == 10**9 and image.frame_id == "camera/frame/camera"
    for (_n, tf), frame in zip(decoded["view/camera/frame/tf"], truth, strict=True):
        np.testing.assert_allclose(
            [tf.translation.x, tf.translation.y, tf.translation.z], -frame.R.T @ frame.t, atol=1e-9
        )
        q = np.array([tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w])
        want = Rotation.from_matrix(frame.R.T).as_quat()
        assert min(np.abs(q - want).max(), np.abs(q + want).max()) < 1e-9
    _n, cal = decoded["view/camera/frame/calibration"][0]
    assert list(cal.K) == truth[0].K.reshape(-1).tolist() and (cal.width, cal.height) == (64, 48)
    _n, root = decoded["view/body/pose/root"][0]
    q = np.array(
        [root.pose.orientation.x, root.pose.orientation.y, root.pose.orientation.z, root.pose.orientation.w]
    )
    want = Rotation.from_rotvec(pose.Rh.astype(np.float64)).as_quat()
    assert min(np.abs(q - want).max(), np.abs(q + want).max()) < 1e-6
    _n, joints = decoded["view/body/pose/joints"][0]
    np.testing.assert_allclose(
        [[p.position.x, p.position.y, p.position.z] for p in joints.poses], pose_with_joints.joints, atol=1e-6
    )
    _n, scene = decoded["view/body/pose/skeleton"][0]
    (entity,) = scene.entities
    joints = pose_with_joints.joints
    spheres = [[s.pose.position.x, s.pose.position.y, s.pose.position.z] for s in entity.spheres]
    np.testing.assert_allclose(spheres, joints, atol=1e-6)
    bones = np.array([[p.x, p.y, p.z] for p in entity.lines[0].points]).reshape(-1, 2, 3)
    np.testing.assert_allclose(
        bones, [[joints[p], joints[c]] for c, p in enumerate(SMPL_PARENTS) if p >= 0], atol=1e-6
    )
    assert entity.frame_id == "world" and entity.id == "body"
    _n, fields = decoded["view/trainer/metrics/fields"][0]
    assert (
        fields["loss"] is None and fields["losses"] == {"l1": 0.1, "ssim": 0.2} and fields["iteration"] == 100
    )


def test_quaternion_matches_scipy_on_random_and_edge_rotations():
    rotations = list(Rotation.random(200, random_state=7).as_matrix())
    rotations += [np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1]), np.eye(3)]
    for matrix in rotations:
        q = np.array(quaternion_xyzw(matrix))
        want = Rotation.from_matrix(matrix).as_quat()
        assert min(np.abs(q - want).max(), np.abs(q + want).max()) < 1e-9


def test_a_point_cloud_decodes_with_the_schema_it_carries():
    """foxglove_views.point_cloud read back through protobuf (from the message's own schema) and
    numpy (from the fields it declares)."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    from stg_node.bus.foxglove_views import point_cloud

    positions = RNG.normal(size=(50, 3)).astype(np.float32)
    colors = RNG.integers(0, 256, size=(50, 3), dtype=np.uint8)
    alpha = RNG.random(50)
    msg = point_cloud(positions, colors, 1_700_000_000 * 10**9 + 7, alpha=alpha)
    schema = msg.get_schema()
    pool = descriptor_pool.DescriptorPool()
    for file in descriptor_pb2.FileDescriptorSet.FromString(schema.data).file:
        pool.Add(file)
    cloud = message_factory.GetMessageClass(pool.FindMessageTypeByName(schema.name)).FromString(msg.encode())
    assert (cloud.timestamp.seconds, cloud.timestamp.nanos, cloud.frame_id) == (1_700_000_000, 7, "world")
    offsets = {f.name: f.offset for f in cloud.fields}
    data = np.frombuffer(cloud.data, np.uint8).reshape(50, cloud.point_stride)
    xyz = np.stack([data[:, offsets[a] : offsets[a] + 4].copy().view("<f4")[:, 0] for a in "xyz"], axis=1)
    np.testing.assert_array_equal(xyz, positions)
    np.testing.assert_array_equal(data[:, [offsets["red"], offsets["green"], offsets["blue"]]], colors)
    np.testing.assert_array_equal(data[:, offsets["alpha"]], np.rint(alpha * 255).astype(np.uint8))
