"""Fixtures of the rig tests: the node tests' private bus and broker."""

from __future__ import annotations

import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
for folder in (HERE.parent / "nodes", HERE.parent):
    if str(folder) not in sys.path:
        sys.path.insert(0, str(folder))

from tests.nodes.conftest import broker, bus_url  # noqa: E402,F401  (the node tests' fixtures)
