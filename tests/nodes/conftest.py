"""Fixtures for the node and launch tests: a private ipc bus with a broker, nodes run in threads."""

from __future__ import annotations

import shutil
import tempfile

import pytest

from stg_node.bus import Broker


@pytest.fixture
def bus_url():
    # Short paths: a Unix socket path must stay under ~107 bytes, pytest's tmp_path may not.
    folder = tempfile.mkdtemp(prefix="stgnode-")
    yield f"ipc://{folder}/bus"
    shutil.rmtree(folder, ignore_errors=True)


@pytest.fixture
def broker(bus_url):
    with Broker(bus_url, status_period_s=0.2) as running:
        yield running


@pytest.fixture(scope="session")
def clip(tmp_path_factory):
    """A 20-frame MJPG video (16 frames of a synthetic subject, 4 black) with its camera and truth."""
    from fixtures.videos import synthetic_clip

    return synthetic_clip(tmp_path_factory.mktemp("live") / "clip")
