"""Datasets (placeholder, filled below)."""

from mslam_ref.datasets.frame import Frame, FrameSequence

__all__ = ["Frame", "FrameSequence"]
