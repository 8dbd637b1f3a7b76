"""A sub-range of a dataset's frames (`mnemoslam run / stream --frames START:END`)."""
from __future__ import annotations

import numpy as np

from ..kernel.frames import DatasetError, Frame
from ..kernel.trajectory import Trajectory
from .base import Dataset


def parse_frames(text: str) -> tuple[int, int | None]:
    """`START:END` (END exclusive, either side may be empty: `300:`, `:500`) as (start, end or
    None). ValueError for anything else (negative numbers, END <= START, no colon)."""
    head, sep, tail = str(text).partition(":")
    try:
        if not sep:
            raise ValueError
        start = int(head) if head.strip() else 0
        end = int(tail) if tail.strip() else None
    except ValueError:
        raise ValueError(f"frames must be START:END (e.g. 0:500 or 300:), got {text!r}") from None
    if start < 0 or (end is not None and end <= start):
        raise ValueError(f"frames {text!r}: need 0 <= START < END")
    return start, end


class FrameRange(Dataset):
    """Frames `start` to `end` (exclusive; None: to the last) of `dataset`, each exactly as in
    the full run: the same frame (its index, stamp and, for the synthetic scene, noise), the
    same stamps. `ground_truth` is the dataset's over the range's stamps (half a frame interval
    either side), so a run's ATE is that of the sub-range. `origin(j)` is the dataset's index
    of frame j."""

    def __init__(self, dataset: Dataset, start: int = 0, end: int | None = None):
        n = len(dataset)
        end = n if end is None else min(int(end), n)
        if not 0 <= start < end:
            raise DatasetError(f"{dataset.name}: frames {start}:{end} are outside its {n} frames")
        self.dataset, self.start, self.end = dataset, int(start), int(end)
        self.name = f"{dataset.name}[{self.start}:{self.end}]"
        self.format = dataset.format
        self.calibration = dataset.calibration
        for attr in ("scene", "trajectory"):  # the synthetic scene's (floor plan, objects)
            if hasattr(dataset, attr):
                setattr(self, attr, getattr(dataset, attr))
        stamps = np.asarray(dataset.stamps, dtype=np.float64)
        self.stamps = stamps[self.start:self.end]
        gt = dataset.ground_truth
        self.ground_truth = None
        if gt is not None:
            dt = float(np.median(np.diff(stamps))) / 2 if n > 1 else 0.0
            keep = (gt.stamps >= self.stamps[0] - dt) & (gt.stamps <= self.stamps[-1] + dt)
            self.ground_truth = Trajectory(gt.stamps[keep], gt.poses[keep])

    def __len__(self) -> int:
        return self.end - self.start

    def origin(self, j: int) -> int:
        return self.start + int(j)

    def frame(self, j: int) -> Frame:
        if not 0 <= j < len(self):
            raise IndexError(f"{self.name}: frame {j} out of range 0..{len(self) - 1}")
        return self.dataset.frame(self.origin(j))


def frame_range(dataset: Dataset, frames: str | tuple[int, int | None] | None,
                max_frames: int | None = None) -> Dataset:
    """`dataset` cut to `frames` (START:END text or (start, end)) and then to at most
    `max_frames` frames; the dataset itself when neither is given."""
    if frames is None:
        return dataset
    start, end = parse_frames(frames) if isinstance(frames, str) else frames
    if max_frames is not None:
        end = start + max_frames if end is None else min(end, start + max_frames)
    return FrameRange(dataset, start, end)
