"""Dataset players: iterate timestamped frames of a recorded sequence, with its calibration
and, where the dataset has it, ground truth.

`open_dataset(path, format=None)` detects the layout from the folder (or a `synthetic:`
spec) and returns a `Dataset`.
"""
from __future__ import annotations

from .base import FORMATS, Dataset, open_dataset

__all__ = ["Dataset", "open_dataset", "FORMATS"]
