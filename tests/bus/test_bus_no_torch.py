"""The bus never imports torch: robot-side tools stay small and start fast."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

CHECK = textwrap.dedent(
    """
    import importlib, pkgutil, sys
    import numpy as np
    import stg_node.bus
    for info in pkgutil.iter_modules(stg_node.bus.__path__):
        importlib.import_module(f"stg_node.bus.{info.name}")
    import stg_node.bus.recording
    for info in pkgutil.iter_modules(stg_node.bus.recording.__path__):
        importlib.import_module(f"stg_node.bus.recording.{info.name}")
    for name in ("topic", "keys", "broker", "bus_options", "bag"):
        importlib.import_module(f"stg_node.cli.{name}")
    from stg_node.bus import Broker, BusConfig, Publisher, Subscriber, BodyPose
    # Exercise the whole path once, too: encode, send, receive, decode.
    with Broker("inproc://no-torch", status_period_s=0, context=None) as _:
        pass
    import zmq
    ctx = zmq.Context()
    cfg = BusConfig(url="inproc://no-torch-2")
    with Publisher(cfg, context=ctx, bind=True) as pub, Subscriber(cfg, [BodyPose], context=ctx) as sub:
        assert pub.wait_for_subscribers("body/pose")
        z = np.zeros(3, np.float32)
        pub.publish(BodyPose(poses=np.zeros((24, 3), np.float32), Rh=z, Th=z, betas=np.zeros(10, np.float32)))
        assert sub.recv(timeout=30) is not None
    ctx.term()
    heavy = sorted(m for m in ("torch", "cv2", "kornia", "trimesh") if m in sys.modules)
    print("heavy:", heavy)
    """
)


def test_bus_and_its_tools_import_no_torch():
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    result = subprocess.run(
        [sys.executable, "-c", CHECK], cwd=ROOT, env=env, capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip().splitlines()[-1] == "heavy: []"
