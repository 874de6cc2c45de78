"""The BlazePose network files: where they live, how setup installs them, and the error when they are missing.

The two TFLite networks (``pose_detection.tflite``, ``pose_landmark_full.tflite``; Apache-2.0,
Google) ship inside PyPI's ``mediapipe==0.10.21`` wheel. That wheel cannot be installed here (it
pins numpy<2 and pulls the non-headless OpenCV), so :func:`install` (run by setup.sh, or
``python tools/install_pose_models.py``) fetches the wheel with ``pip download --no-deps`` while
the registry is reachable, checks its SHA-256, reads just the two networks out of the zip (never
extracting anything else), checks theirs, and writes them plus ``manifest.json`` to

    $STG_POSE_MODELS, else $XDG_DATA_HOME/stg_node/pose, else ~/.local/share/stg_node/pose

Nothing downloads at run time: :func:`pose_model_paths` only looks there and raises
:class:`PoseModelError` naming the fix. Installing twice is a no-op (checksums are compared).
"""

from __future__ import annotations

import json
import logging
import sys
import tempfile
import zipfile
from pathlib import Path

from stg_node.offline_assets import DownloadError, pip_download, sha256_bytes, user_data_dir, write_atomic

log = logging.getLogger(__name__)

ENV_DIR = "STG_POSE_MODELS"
WHEEL_REQUIREMENT = "mediapipe==0.10.21"
# The cp311 manylinux x86_64 wheel; other platforms' wheels hold the same network files, so the
# members are checked by their own checksums and the wheel's digest only when it is this one.
WHEEL_NAME = "mediapipe-0.10.21-cp311-cp311-manylinux_2_28_x86_64.whl"
WHEEL_SHA256 = "05dc4a9e593655a79558d05d6227d31018c2537a4bd3362b51e230cf22aecfe3"
MODELS = {
    "detector": ("mediapipe/modules/pose_detection/pose_detection.tflite",
                 "9ba9dd3d42efaaba86b4ff0122b06f29c4122e756b329d89dca1e297fd8f866c"),
    "landmarker": ("mediapipe/modules/pose_landmark/pose_landmark_full.tflite",
                   "e9a5c5cb17f736fafd4c2ec1da3b3d331d6edbe8a0d32395855aeb2cdfd64b9f"),
}  # fmt: skip
INSTALL_COMMAND = "python tools/install_pose_models.py"


class PoseModelError(RuntimeError):
    """A pose network file is missing or unusable; the message says which and how to fix it."""


def models_dir() -> Path:
    return user_data_dir(ENV_DIR, "pose")


def model_path(role: str, directory: Path | None = None) -> Path:
    if role not in MODELS:
        raise ValueError(f"role must be one of {tuple(MODELS)}, got {role!r}")
    return (directory or models_dir()) / Path(MODELS[role][0]).name


def pose_model_paths(directory: Path | None = None, *, verify: bool = False) -> dict[str, Path]:
    """The installed network files by role; PoseModelError naming the fix when one is missing."""
    directory = directory or models_dir()
    paths = {}
    for role, (_, digest) in MODELS.items():
        path = model_path(role, directory)
        if not path.is_file():
            raise PoseModelError(
                f"BlazePose {role} network not installed ({path} missing). Install it with "
                f"`{INSTALL_COMMAND}` (setup.sh does this; it needs PyPI once), or set {ENV_DIR} to "
                "the folder holding pose_detection.tflite and pose_landmark_full.tflite, or pass your "
                "own ONNX pose model (--detector onnx --pose-model FILE)"
            )
        if verify and sha256_bytes(path.read_bytes()) != digest:
            raise PoseModelError(
                f"{path} does not match the pinned checksum; reinstall with `{INSTALL_COMMAND}`"
            )
        paths[role] = path
    return paths


def installed(directory: Path | None = None) -> bool:
    try:
        pose_model_paths(directory, verify=True)
    except PoseModelError:
        return False
    return True


def download_wheel(directory: Path) -> Path:
    """``pip download --no-deps`` the mediapipe wheel for this interpreter into ``directory``."""
    try:
        pip_download(WHEEL_REQUIREMENT, directory)
    except DownloadError as exc:
        raise PoseModelError(str(exc)) from exc
    wheels = sorted(directory.glob("mediapipe-0.10.21-*.whl"))
    if not wheels:
        raise PoseModelError(f"pip download {WHEEL_REQUIREMENT} left no wheel in {directory}")
    return wheels[0]


def install(directory: Path | None = None, wheel: Path | None = None) -> dict[str, Path]:
    """Install both networks (idempotent); returns their paths. Raises PoseModelError on failure."""
    directory = directory or models_dir()
    if installed(directory):
        log.info("BlazePose networks already installed in %s", directory)
        return pose_model_paths(directory)
    with tempfile.TemporaryDirectory() as tmp:
        if wheel is None:
            log.info("downloading %s (wheel, ~36 MB) for its two pose networks", WHEEL_REQUIREMENT)
            wheel = download_wheel(Path(tmp))
        wheel = Path(wheel)
        if wheel.name == WHEEL_NAME:
            digest = sha256_bytes(wheel.read_bytes())
            if digest != WHEEL_SHA256:
                raise PoseModelError(f"{wheel}: SHA-256 {digest} is not the pinned {WHEEL_SHA256}")
        directory.mkdir(parents=True, exist_ok=True)
        written = {}
        try:
            archive = zipfile.ZipFile(wheel)
        except (OSError, zipfile.BadZipFile) as exc:
            raise PoseModelError(f"{wheel} is not a readable wheel ({exc})") from exc
        with archive:
            for role, (member, member_sha) in MODELS.items():
                try:
                    blob = archive.read(member)  # in memory: nothing else is unpacked
                except KeyError:
                    raise PoseModelError(f"{wheel.name} has no {member}") from None
                if sha256_bytes(blob) != member_sha:
                    raise PoseModelError(f"{member} in {wheel.name}: checksum mismatch")
                written[role] = write_atomic(model_path(role, directory), blob)
    manifest = {
        "source": WHEEL_REQUIREMENT,
        "licence": "Apache-2.0 (MediaPipe)",
        "files": {role: {"path": p.name, "sha256": MODELS[role][1]} for role, p in written.items()},
    }
    (directory / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
    return written


def main(argv: list[str] | None = None) -> int:
    import argparse

    parser = argparse.ArgumentParser(description="Install the BlazePose pose networks for offline tracking.")
    parser.add_argument(
        "--dest", type=Path, default=None, help=f"folder (default: ${ENV_DIR} or the user data dir)"
    )
    parser.add_argument(
        "--wheel", type=Path, default=None, help="use an already downloaded mediapipe 0.10.21 wheel"
    )
    parser.add_argument(
        "--status", action="store_true", help="only report whether the networks are installed"
    )
    args = parser.parse_args(argv)
    directory = args.dest or models_dir()
    if args.status:
        try:
            paths = pose_model_paths(directory, verify=True)
        except PoseModelError as exc:
            print(f"pose networks: unavailable: {exc}")
            return 1
        for role, path in paths.items():
            print(f"pose {role}: installed at {path}")
        return 0
    try:
        written = install(directory, args.wheel)
    except (PoseModelError, OSError) as exc:
        print(f"pose networks NOT installed: {exc}", file=sys.stderr)
        return 1
    for role, path in written.items():
        print(f"pose {role} installed: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
