"""Datasets (ZJU-MoCap, THuman4.0, synthetic, own captures), optical flow and metrics."""
