"""An older revision of this repository, exported once, so a benchmark times it beside today's code.

``export_revision(rev)`` writes the tracked files of git revision ``rev`` (``git archive``) into
``$STG_SPLAT_CACHE``'s parent (``~/.cache/stg_node/baselines/<commit>`` by default) and returns
that folder; a benchmark then runs its measuring child processes with ``--root`` pointing there,
alternating with children on today's tree, so both see the same load. The older tree builds its
own CPU kernels (a different source hash: a different cache entry), once.

``BASELINE_REV`` is the code before the live-rate work of issue 24 (fused skinning and colour
kernels, culling before colour, colour streams): the "today's code" of its benchmark figures.
"""

from __future__ import annotations

import io
import os
import subprocess
import tarfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BASELINE_REV = "6bbdca2"


def child_env(root: Path | str, **overrides: str) -> dict[str, str]:
    """The environment of a measuring child that must import ``root``'s stg_node: ``root`` goes
    first on PYTHONPATH and the caller's entries stay after it (packages installed there, gsplat
    on a GPU machine say, must stay importable in the child)."""
    path = os.pathsep.join(p for p in (str(root), os.environ.get("PYTHONPATH", "")) if p)
    return {**os.environ, **overrides, "PYTHONPATH": path}


def _git(*args: str) -> bytes:
    try:
        return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError) as exc:
        detail = getattr(exc, "stderr", b"") or b""
        raise SystemExit(
            f"git {' '.join(args)} failed in {ROOT}: {exc} {detail.decode(errors='replace')}"
        ) from exc


def export_revision(rev: str) -> Path:
    """The tracked files of ``rev`` in a folder of their own (written once per commit)."""
    from stg_node.splat.build import cache_root

    commit = _git("rev-parse", "--verify", f"{rev}^{{commit}}").decode().strip()
    target = cache_root().parent / "baselines" / commit[:12]
    done = target / ".exported"
    if not done.is_file():
        target.mkdir(parents=True, exist_ok=True)
        with tarfile.open(fileobj=io.BytesIO(_git("archive", "--format=tar", commit))) as tar:
            tar.extractall(target, filter="data")
        done.write_text(commit + "\n")
    return target
