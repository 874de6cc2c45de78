"""Datasets (ZJU-MoCap, THuman4.0, synthetic, own captures), optical flow and metrics.

``open_dataset(path, kind="auto", split="train", size=512)`` is the entry point for loaders
(:mod:`stg_node.data.factory`); :mod:`stg_node.data.flow` computes cached optical flow;
:mod:`stg_node.data.metrics` holds PSNR, SSIM and LPIPS. Names are imported on first use so
that ``import stg_node.data.types`` stays cheap.
"""

from __future__ import annotations

__all__ = ["open_dataset", "detect_layout", "DatasetError"]


def __getattr__(name):
    if name in ("open_dataset", "detect_layout"):
        from stg_node.data import factory

        return getattr(factory, name)
    if name == "DatasetError":
        from stg_node.data.errors import DatasetError

        return DatasetError
    raise AttributeError(f"module 'stg_node.data' has no attribute {name!r}")
