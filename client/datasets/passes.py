"""A dataset played back and forth: long runs from any sequence (`mnemoslam run --passes N`)."""
from __future__ import annotations

import numpy as np

from ..kernel.frames import Frame
from ..kernel.trajectory import Trajectory
from ._io import sample_poses
from .base import Dataset


class Passes(Dataset):
    """`dataset` played forward, backward, forward, … `passes` times in all. The turning frame
    is not repeated: pass 1 is frames 0…n-1, pass 2 n-2…0, pass 3 1…n-1, and so on. Pass 1
    keeps the dataset's stamps; later frames continue at its frame rate (the median interval),
    so stamps keep increasing. `ground_truth` is the dataset's at the played frames, stamped
    like them; `origin(j)` is the dataset's index of played frame j."""

    def __init__(self, dataset: Dataset, passes: int):
        if isinstance(passes, bool) or not isinstance(passes, int) or passes < 1:
            raise ValueError(f"passes must be a positive integer, got {passes!r}")
        n = len(dataset)
        self.dataset, self.passes = dataset, passes
        self.name = dataset.name if passes == 1 else f"{dataset.name}x{passes}"
        self.format = dataset.format
        self.calibration = dataset.calibration
        order = [np.arange(n)]
        for p in range(1, passes if n > 1 else 1):
            order.append(np.arange(n - 2, -1, -1) if p % 2 else np.arange(1, n))
        self._order = np.concatenate(order)
        stamps = np.asarray(dataset.stamps, dtype=np.float64)
        dt = float(np.median(np.diff(stamps))) if n > 1 else 0.0
        self.stamps = (np.concatenate([stamps, stamps[-1] + dt * np.arange(1, len(self._order) - n + 1)])
                       if n else stamps)
        self.ground_truth = None
        if dataset.ground_truth is not None:
            known = sample_poses(dataset.ground_truth, stamps)  # the frames that have a ground-truth pose
            index = np.searchsorted(stamps, known.stamps)
            pose_of = np.full(n, -1)
            pose_of[index] = np.arange(len(index))
            k = pose_of[self._order]
            self.ground_truth = Trajectory(self.stamps[k >= 0], known.poses[k[k >= 0]])

    def __len__(self) -> int:
        return len(self._order)

    def origin(self, j: int) -> int:
        return int(self._order[j])

    def frame(self, j: int) -> Frame:
        if not 0 <= j < len(self):
            raise IndexError(f"{self.name}: frame {j} out of range 0..{len(self) - 1}")
        f = self.dataset.frame(self.origin(j))
        f.index, f.stamp = j, float(self.stamps[j])
        return f
