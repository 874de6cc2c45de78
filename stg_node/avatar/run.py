"""A training run's folder: what ``stg-train`` writes and the other commands read.

RUN_DIR/config.json        the TrainConfig, the data spec, body model, seed, backend, versions
RUN_DIR/checkpoint.stgsnap the latest checkpoint (a GaussianSnapshot file, atomic; --resume reads it)
RUN_DIR/avatar.stgsnap     the final published model (no training state)
RUN_DIR/train_log.jsonl    one line per logged step (loss terms, PSNR, Gaussians, it/s, time)
RUN_DIR/summary.json       the end of training: time, iterations, Gaussians, motion, size
RUN_DIR/training_curves.png loss and PSNR against iteration
RUN_DIR/cache/flow/        optical flow cache (content-keyed)
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

from stg_node.avatar.config import TrainConfig
from stg_node.avatar.data_spec import DataSpec


@dataclass(frozen=True)
class RunDir:
    path: Path

    @property
    def config(self) -> Path:
        return self.path / "config.json"

    @property
    def checkpoint(self) -> Path:
        return self.path / "checkpoint.stgsnap"

    @property
    def avatar(self) -> Path:
        return self.path / "avatar.stgsnap"

    @property
    def log(self) -> Path:
        return self.path / "train_log.jsonl"

    @property
    def summary(self) -> Path:
        return self.path / "summary.json"

    @property
    def curves(self) -> Path:
        return self.path / "training_curves.png"

    @property
    def flow_cache(self) -> Path:
        return self.path / "cache" / "flow"

    def write_config(self, record: dict) -> None:
        self.path.mkdir(parents=True, exist_ok=True)
        write_json(self.config, record)

    def read_config(self) -> dict:
        if not self.config.is_file():
            raise FileNotFoundError(
                f"{self.path} is not a training run (no config.json); run stg-train first"
            )
        return json.loads(self.config.read_text())

    def data_spec(self) -> DataSpec:
        return DataSpec.from_dict(self.read_config()["data"])

    def train_config(self) -> TrainConfig:
        return TrainConfig.from_dict(self.read_config()["config"])

    def model_file(self) -> Path:
        """The model to render: the final avatar, else the latest checkpoint."""
        for path in (self.avatar, self.checkpoint):
            if path.is_file():
                return path
        raise FileNotFoundError(f"{self.path} holds no model yet (no avatar.stgsnap or checkpoint.stgsnap)")


def write_json(path: Path, obj) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(obj, indent=1, default=float))
    os.replace(tmp, path)
