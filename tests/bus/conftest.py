"""Fixtures for the bus tests: unique short ipc paths, free tcp port ranges, brokers, contexts.

Every receive in these tests has a timeout; nothing here can hang a test run.
"""

from __future__ import annotations

import shutil
import tempfile

import pytest
import zmq
from bushelpers import free_base_port

from stg_node.bus import Broker


@pytest.fixture
def ipc_dir():
    # Short paths: a Unix socket path must stay under ~107 bytes, pytest's tmp_path may not.
    path = tempfile.mkdtemp(prefix="stgbus-")
    yield path
    shutil.rmtree(path, ignore_errors=True)


@pytest.fixture
def ipc_url(ipc_dir):
    return f"ipc://{ipc_dir}/bus"


@pytest.fixture
def tcp_url():
    return f"tcp://127.0.0.1:{free_base_port()}"


@pytest.fixture(params=["ipc", "tcp"])
def url(request, ipc_dir):
    if request.param == "ipc":
        return f"ipc://{ipc_dir}/bus"
    return f"tcp://127.0.0.1:{free_base_port()}"


@pytest.fixture
def ctx():
    context = zmq.Context()
    yield context
    context.destroy(linger=0)


@pytest.fixture
def broker(url):
    with Broker(url, status_period_s=0.2) as running:
        yield running
