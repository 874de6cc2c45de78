"""stg-synth end to end on a tiny run: a complete, consistent ZJU-MoCap layout, bit-identical per seed."""

from __future__ import annotations

import hashlib
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from stg_node.body import load_body_model
from stg_node.data.synth import writer
from stg_node.data.synth.generate import SynthConfig, generate, render_schedule, split_spec

TINY = dict(num_frames=6, size=64, motion="dance", num_novel_views=2, view_every=3, write_depth=True)


@pytest.fixture(scope="module")
def body():
    return load_body_model()


@pytest.fixture(scope="module")
def tiny(tmp_path_factory, body):
    out = tmp_path_factory.mktemp("synth") / "tiny"
    result = generate(SynthConfig(out=out, seed=5, **TINY), body=body, progress=False)
    return result


def _digest(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def test_layout_is_complete_and_in_zju_conventions(tiny, body):
    out = tiny.out
    annots = np.load(out / "annots.npy", allow_pickle=True).item()
    cams = annots["cams"]
    assert set(cams) == {"K", "D", "R", "T"}
    assert all(len(cams[key]) == 3 for key in cams)
    for K, D, R, T in zip(cams["K"], cams["D"], cams["R"], cams["T"], strict=True):
        assert K.shape == (3, 3) and D.shape == (5, 1) and R.shape == (3, 3) and T.shape == (3, 1)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
        centre_mm = -R.T @ T[:, 0]
        assert 2500 < np.linalg.norm(centre_mm[:2]) < 4500  # cameras ~3.5 m away, T in millimetres
    assert len(annots["ims"]) == 6
    assert annots["ims"][4]["ims"] == ["Camera_B1/000004.png", "Camera_B2/000004.png", "Camera_B3/000004.png"]

    meta = writer.read_metadata(out)
    for cam in meta["cameras"]:
        for frame in range(6):
            rel = writer.image_relpath(cam["index"], frame)
            rendered = frame in meta["rendered"][cam["name"]]
            assert (out / rel).is_file() == rendered, rel
            assert (out / "mask" / rel).is_file() == rendered
            assert (out / "mask_cihp" / rel).is_file() == rendered
            assert (out / "depth" / rel).is_file() == rendered
    assert meta["rendered"]["Camera_B1"] == list(range(6))
    assert meta["rendered"]["Camera_B2"] == [0, 3, 5]  # every 3rd frame of 0-4 (train), then of 5-5

    for frame in range(6):
        params = np.load(out / "new_params" / f"{frame}.npy", allow_pickle=True).item()
        assert set(params) == {"poses", "Rh", "Th", "shapes"}
        assert params["poses"].shape == (1, 72) and params["poses"].dtype == np.float32
        assert params["Rh"].shape == (1, 3) and params["Th"].shape == (1, 3)
        assert params["shapes"].shape == (1, body.num_betas)
        vertices = np.load(out / "new_vertices" / f"{frame}.npy")
        assert vertices.shape == (body.num_vertices, 3) and vertices.dtype == np.float32
        assert abs(vertices[:, 2].min()) < 0.1  # feet on the floor (garment may lift the lowest point a bit)


def test_images_masks_and_depth_agree(tiny):
    out = tiny.out
    for rel in ("Camera_B1/000002.png", "Camera_B3/000003.png"):
        image = cv2.imread(str(out / rel), cv2.IMREAD_UNCHANGED)
        mask = cv2.imread(str(out / "mask" / rel), cv2.IMREAD_UNCHANGED)
        depth = cv2.imread(str(out / "depth" / rel), cv2.IMREAD_UNCHANGED)
        assert image.shape == (64, 64, 3) and mask.shape == (64, 64) and depth.dtype == np.uint16
        assert set(np.unique(mask)) <= {0, 255}
        assert 100 < (mask == 255).sum() < 64 * 64 / 2
        assert (image[mask == 0] == 0).all()  # black background outside the mask
        assert (depth[mask == 255] > 2000).all() and (depth[mask == 255] < 5000).all()  # millimetres


def test_projected_ground_truth_vertices_land_inside_the_masks(tiny):
    """Independent check of the camera conventions: OpenCV's projectPoints with K, R, T / 1000."""
    out = tiny.out
    annots = np.load(out / "annots.npy", allow_pickle=True).item()
    cams = annots["cams"]
    meta = writer.read_metadata(out)
    checked = 0
    for cam in meta["cameras"]:
        k = cam["index"]
        for frame in meta["rendered"][cam["name"]]:
            vertices = np.load(out / "new_vertices" / f"{frame}.npy").astype(np.float64)
            rvec = cv2.Rodrigues(cams["R"][k])[0]
            pixels, _ = cv2.projectPoints(vertices, rvec, cams["T"][k] / 1000.0, cams["K"][k], cams["D"][k])
            pixels = np.round(pixels[:, 0]).astype(int)
            mask = cv2.imread(str(out / "mask" / annots["ims"][frame]["ims"][k]), cv2.IMREAD_GRAYSCALE)
            grown = cv2.dilate(mask, np.ones((3, 3), np.uint8))  # silhouette-edge vertices: coverage < 1/2
            inside = (pixels >= 0).all(1) & (pixels < 64).all(1)
            assert inside.all(), f"{cam['name']} frame {frame}: vertices outside the image"
            assert (grown[pixels[:, 1], pixels[:, 0]] == 255).all(), f"{cam['name']} frame {frame}"
            checked += 1
    assert checked == 6 + 2 * 3


def test_smpl_params_explain_the_body_but_not_the_garment(tiny, body):
    out = tiny.out
    meta = writer.read_metadata(out)
    assert meta["garment"]["in_smpl_params"] is False
    moved = []
    for frame in range(6):
        params = np.load(out / "new_params" / f"{frame}.npy", allow_pickle=True).item()
        with torch.no_grad():
            skinned = (
                body(
                    betas=torch.as_tensor(params["shapes"]),
                    poses=torch.as_tensor(params["poses"]),
                    Rh=torch.as_tensor(params["Rh"]),
                    Th=torch.as_tensor(params["Th"]),
                )
                .vertices[0]
                .numpy()
            )
        gt = np.load(out / "new_vertices" / f"{frame}.npy")
        moved.append(np.linalg.norm(gt - skinned, axis=1))
    moved = np.stack(moved)
    garment = moved.max(axis=0) > 1e-4
    # Only the hem and sleeves move, and they do move (a fast dance).
    assert 0 < garment.sum() <= meta["garment"]["hem_vertices"] + meta["garment"]["sleeve_vertices"]
    assert moved.max() > 0.01
    assert moved[:, ~garment].max() < 1e-4


def test_splits_follow_the_protocol():
    config = SynthConfig(out=Path("unused"), num_frames=300, num_novel_views=8, view_every=30)
    splits = split_spec(config)
    assert splits["train"] == [{"cameras": [0], "frames": list(range(240))}]
    assert splits["novel_view"] == [{"cameras": list(range(1, 9)), "frames": list(range(0, 240, 30))}]
    assert splits["novel_pose"][0] == {"cameras": [0], "frames": list(range(240, 300))}
    assert splits["novel_pose"][1] == {"cameras": list(range(1, 9)), "frames": [240, 270]}
    schedule = render_schedule(config)
    assert sum(len(c) for c in schedule) == 300 + 10 * 8
    # Every (camera, frame) of every split is rendered.
    for groups in splits.values():
        for group in groups:
            for frame in group["frames"]:
                assert set(group["cameras"]) <= set(schedule[frame])


def test_same_seed_gives_bit_identical_files_other_seed_does_not(tiny, body, tmp_path):
    again = generate(SynthConfig(out=tmp_path / "again", seed=5, **TINY), body=body, progress=False)
    assert _digest(again.out) == _digest(tiny.out)
    other = generate(SynthConfig(out=tmp_path / "other", seed=6, **TINY), body=body, progress=False)
    first = cv2.imread(str(tiny.out / "Camera_B1/000003.png"))
    assert not np.array_equal(first, cv2.imread(str(other.out / "Camera_B1/000003.png")))


def test_refuses_a_non_empty_output_folder_unless_told(tmp_path, body):
    (tmp_path / "keep.txt").write_text("mine")
    config = SynthConfig(out=tmp_path, seed=1, num_frames=1, size=16, num_novel_views=0)
    with pytest.raises(FileExistsError, match="not empty"):
        generate(config, body=body, progress=False)
    generate(
        SynthConfig(out=tmp_path, seed=1, num_frames=1, size=16, num_novel_views=0, overwrite=True),
        body=body,
        progress=False,
    )
    assert (tmp_path / "keep.txt").read_text() == "mine"  # --overwrite only replaces what stg-synth writes
    assert (tmp_path / "Camera_B1" / "000000.png").is_file()


def test_cli_writes_a_benchmark_and_reports_bad_arguments(tmp_path, capsys):
    from stg_node.cli.synth import main

    out = tmp_path / "cli"
    assert main(["--out", str(out), "--frames", "2", "--size", "32", "--views", "1", "--no-progress"]) == 0
    assert (out / "annots.npy").is_file() and (out / "Camera_B2" / "000000.png").is_file()
    assert main(["--out", str(out), "--frames", "2", "--size", "32", "--no-progress"]) == 2  # not empty
    assert main(["--out", str(tmp_path / "x"), "--frames", "0", "--no-progress"]) == 2
    assert main(["--out", str(tmp_path / "y"), "--motion", "moonwalk"]) == 2  # argparse: a usage error
    assert "moonwalk" in capsys.readouterr().err


def test_cli_offers_every_motion_including_the_still_subject(tmp_path, capsys):
    from stg_node.cli.synth import build_parser, main

    help_text = build_parser().format_help()
    for motion in ("mixed", "turn", "walk", "wave", "dance", "still"):
        assert motion in help_text
    out = tmp_path / "still"
    argv = ["--out", str(out), "--frames", "3", "--size", "32", "--views", "0", "--motion", "still"]
    assert main([*argv, "--no-progress"]) == 0
    meta = writer.read_metadata(out)
    assert meta["motion"] == "still" and [s["name"] for s in meta["motion_segments"]] == ["still", "still"]


def test_metadata_reader_rejects_foreign_folders(tmp_path):
    with pytest.raises(FileNotFoundError, match="synth.json"):
        writer.read_metadata(tmp_path)
    (tmp_path / "synth.json").write_text('{"format": "other"}')
    with pytest.raises(ValueError, match="format"):
        writer.read_metadata(tmp_path)


def test_written_images_are_the_rasterized_ground_truth_vertices(tiny, body):
    """Re-render a view from the written files (vertices, cameras, Rh); compare with the PNG (RGB order)."""
    from stg_node.data.synth.generate import _lambert_shade
    from stg_node.data.synth.mesh_raster import TexturedMesh, render_mesh
    from stg_node.data.types import Camera

    out = tiny.out
    annots = np.load(out / "annots.npy", allow_pickle=True).item()
    cams = annots["cams"]
    frame, k = 3, 2
    vertices = torch.from_numpy(np.load(out / "new_vertices" / f"{frame}.npy"))
    params = np.load(out / "new_params" / f"{frame}.npy", allow_pickle=True).item()
    mesh = TexturedMesh.from_arrays(body.faces.numpy(), body.uv.numpy(), body.uv_faces.numpy(), body.texture)
    camera = Camera(K=cams["K"][k], R=cams["R"][k], t=cams["T"][k][:, 0] / 1000.0, width=64, height=64)
    shade = _lambert_shade(vertices, mesh.faces, params["Rh"][0])
    expected = render_mesh(mesh, vertices, camera, supersample=2, vertex_shade=shade, cull_backfaces=True)
    written = cv2.cvtColor(cv2.imread(str(out / annots["ims"][frame]["ims"][k])), cv2.COLOR_BGR2RGB)
    assert np.abs(written.astype(int) - expected.image.astype(int)).max() <= 1
    assert (expected.image.reshape(-1, 3).std(0) > 1).all()  # a real image, not a blank


def test_the_zju_loader_reads_it_back_with_the_written_cameras_poses_and_splits(tiny):
    """stg-synth output through the project's ZJU-MoCap loader (the trainer's code path)."""
    from stg_node.data.synth import open_synth

    out = tiny.out
    meta = writer.read_metadata(out)
    annots = np.load(out / "annots.npy", allow_pickle=True).item()
    expected = {
        name: sorted(
            (frame, f"{cam + 1}") for group in groups for cam in group["cameras"] for frame in group["frames"]
        )
        for name, groups in meta["splits"].items()
    }
    for split in ("train", "novel_view", "novel_pose"):
        dataset = open_synth(out, split, size=None, check=True)
        got = sorted((view.frame, view.camera) for view in dataset.views)
        if (
            split == "novel_pose"
        ):  # the loader's stride on all cameras; the metadata adds camera 1's every frame
            assert set(got) <= set(expected[split]) and {c for _, c in got} == {"1", "2", "3"}
            assert got == sorted((f, c) for f in range(5, 6, 3) for c in "123")
        else:
            assert got == expected[split]
        assert dataset.fps == 30.0
    dataset = open_synth(out, "novel_view", size=None)
    sample = dataset[len(dataset) - 1]
    k = int(sample.camera.name) - 1
    np.testing.assert_allclose(sample.camera.K, annots["cams"]["K"][k], atol=1e-9)
    np.testing.assert_allclose(sample.camera.R, annots["cams"]["R"][k], atol=1e-9)
    np.testing.assert_allclose(sample.camera.t, annots["cams"]["T"][k][:, 0] / 1000.0, atol=1e-9)
    params = np.load(out / "new_params" / f"{sample.index}.npy", allow_pickle=True).item()
    np.testing.assert_allclose(sample.smpl.poses.reshape(-1), params["poses"][0], atol=1e-7)
    np.testing.assert_allclose(sample.smpl.Th, params["Th"][0], atol=1e-7)
    rel = annots["ims"][sample.index]["ims"][k]
    written = cv2.cvtColor(cv2.imread(str(out / rel)), cv2.COLOR_BGR2RGB)
    np.testing.assert_array_equal(sample.image, written)
    np.testing.assert_array_equal(sample.mask > 0, cv2.imread(str(out / "mask" / rel), 0) > 0)
    assert sample.time == pytest.approx(sample.index / 30.0)


def test_an_untextured_body_is_refused_with_a_clear_error(tmp_path, body):
    class Untextured:
        name = "smpl:SMPL_NEUTRAL.pkl"
        uv = None
        texture = None

    with pytest.raises(ValueError, match="no uv/uv_faces/texture"):
        generate(SynthConfig(out=tmp_path / "x", num_frames=1, size=16), body=Untextured(), progress=False)
    assert not (tmp_path / "x").exists()


def _tool(name):
    import importlib.util
    import sys

    path = Path(__file__).resolve().parents[1] / "tools" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def test_montage_tool_tiles_frames_views_and_garment(tiny, tmp_path):
    out = tmp_path / "montage.png"
    assert _tool("synth_montage").main(["--from", str(tiny.out), "--out", str(out), "--tile", "48"]) == 0
    montage = cv2.imread(str(out))
    segments = len(writer.read_metadata(tiny.out)["motion_segments"])
    assert montage.shape == (3 * 48, segments * 48, 3)
    assert montage[2 * 48 + 16 :].max() > 100  # the garment row shows motion


def test_benchmark_tool_runs_a_small_workload(capsys):
    # Runs and reports; the time itself is the benchmark's business, not a test's (exit 1 = target missed).
    assert _tool("bench_synth").main(["--frames", "3", "--size", "32", "--views", "1"]) in (0, 1)
    printed = capsys.readouterr().out
    assert "ratio total / baseline" in printed
    assert "5 views rendered" in printed  # camera 1 on frames 0-2, camera 2 on 0 (train) and 2 (held out)


def test_back_face_culling_does_not_change_the_body_render(tiny, body):
    """The generator culls back faces; on the closed, outward-wound body that must be invisible."""
    from stg_node.data.synth.generate import _outward_faces
    from stg_node.data.synth.mesh_raster import TexturedMesh, render_mesh
    from stg_node.data.types import Camera

    with torch.no_grad():
        rest = body(poses=torch.zeros(1, 72)).vertices[0].numpy()
    faces, flipped = _outward_faces(rest, body.faces.numpy())
    assert not flipped  # the open body is wound counter-clockwise outwards
    annots = np.load(tiny.out / "annots.npy", allow_pickle=True).item()
    cams = annots["cams"]
    mesh = TexturedMesh.from_arrays(faces, body.uv.numpy(), body.uv_faces.numpy(), body.texture)
    vertices = np.load(tiny.out / "new_vertices" / "3.npy")
    for k in range(3):
        camera = Camera(K=cams["K"][k], R=cams["R"][k], t=cams["T"][k][:, 0] / 1000.0, width=64, height=64)
        culled = render_mesh(mesh, vertices, camera, cull_backfaces=True)
        full = render_mesh(mesh, vertices, camera, cull_backfaces=False)
        np.testing.assert_array_equal(culled.mask, full.mask)
        np.testing.assert_array_equal(culled.image, full.image)
