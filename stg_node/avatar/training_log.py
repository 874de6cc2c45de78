"""The training log (one JSON line per logged step) and the training-curves plot drawn from it."""

from __future__ import annotations

import json
import math
from dataclasses import asdict
from pathlib import Path


class TrainingLog:
    def __init__(self, path: Path, *, append: bool = False):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fh = open(self.path, "a" if append else "w")

    def write(self, result) -> None:
        record = asdict(result)
        record = {
            k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in record.items()
        }
        self._fh.write(json.dumps(record) + "\n")
        self._fh.flush()

    def close(self) -> None:
        self._fh.close()

    def records(self) -> list[dict]:
        out = []
        with open(self.path) as fh:
            for line in fh:
                try:
                    out.append(json.loads(line))
                except json.JSONDecodeError:  # a torn last line after a kill: skip it
                    continue
        return out

    def plot(self, path: Path) -> Path | None:
        """Loss terms, training PSNR and Gaussian count against iteration, as a PNG."""
        records = [r for r in self.records() if r.get("loss") is not None]
        if not records:
            return None
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        its = [r["iteration"] for r in records]
        fig, axes = plt.subplots(1, 3, figsize=(15, 4))
        ax = axes[0]
        ax.semilogy(its, [r["loss"] for r in records], label="total", lw=1.5)
        for name in sorted(records[-1].get("losses", {})):
            values = [r["losses"].get(name) for r in records]
            if any(v for v in values):
                ax.semilogy(its, [v if v else float("nan") for v in values], label=name, lw=0.8)
        ax.set_xlabel("iteration")
        ax.set_title("loss terms")
        ax.legend(fontsize=7)
        axes[1].plot(its, [r["psnr"] for r in records], lw=1)
        axes[1].set_xlabel("iteration")
        axes[1].set_title("training-view PSNR (crop, dB)")
        axes[2].plot(its, [r["num_gaussians"] for r in records], lw=1)
        axes[2].set_xlabel("iteration")
        axes[2].set_title("Gaussians")
        fig.tight_layout()
        fig.savefig(path, dpi=90)
        plt.close(fig)
        return Path(path)
