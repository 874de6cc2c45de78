#!/usr/bin/env python3
"""Install the BlazePose pose networks for offline tracking (setup.sh runs this).

    python tools/install_pose_models.py [--dest DIR] [--wheel mediapipe-0.10.21-...whl] [--status]

Takes pose_detection.tflite and pose_landmark_full.tflite out of PyPI's mediapipe 0.10.21 wheel
(checksummed; nothing else is unpacked, mediapipe itself is not installed). See
stg_node/tracking/model_files.py and docs/TRACKING.md.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's stg_node first

from stg_node.logs import configure_logging  # noqa: E402
from stg_node.tracking.model_files import main  # noqa: E402

if __name__ == "__main__":
    configure_logging()
    sys.exit(main())
