"""The CPU kernels as they were at an older git revision, built beside today's, for same-run baselines.

``baseline_kernels("6bbdca2")`` extracts ``stg_node/splat/csrc`` at that revision (``git show``),
builds it into the kernel cache under its own hash (once) and loads it; its operators live in
their own namespace, so both builds run in one process. Time the old ones inside
``stg_node.splat.build.kernels_override(old)`` (with ``stg_node.avatar.kernels.reference()`` when
the old build predates the avatar kernels).
"""

from __future__ import annotations

import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CSRC = "stg_node/splat/csrc"


def baseline_kernels(rev: str):
    """Build (or reuse) and load the kernels of git revision ``rev``; SystemExit naming the problem."""
    from stg_node.splat import build

    try:
        listing = subprocess.run(
            ["git", "ls-tree", "--name-only", f"{rev}:{CSRC}"], cwd=ROOT, capture_output=True, text=True, check=True
        ).stdout.split()
    except (OSError, subprocess.CalledProcessError) as exc:
        raise SystemExit(f"cannot read {CSRC} at git revision {rev!r} in {ROOT}: {exc}") from exc
    commit = subprocess.run(
        ["git", "rev-parse", "--short=12", rev], cwd=ROOT, capture_output=True, text=True, check=True
    ).stdout.strip()
    source_dir = build.cache_root() / f"baseline_sources_{commit}"
    source_dir.mkdir(parents=True, exist_ok=True)
    for name in listing:
        blob = subprocess.run(["git", "show", f"{rev}:{CSRC}/{name}"], cwd=ROOT, capture_output=True, check=True)
        target = source_dir / name
        if not target.is_file() or target.read_bytes() != blob.stdout:
            target.write_bytes(blob.stdout)
    sources = tuple(sorted(n for n in listing if n.endswith(".cpp") and n != "splat_bindings.cpp"))
    sources = (*sources, "splat_bindings.cpp")
    headers = tuple(sorted(n for n in listing if n.endswith(".h")))
    return build.build_extension(source_dir=source_dir, sources=sources, headers=headers)
