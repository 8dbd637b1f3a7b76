"""KITTI odometry player: a sequence folder with rectified grey stereo `image_0/` (left) and
`image_1/` (right) PNGs, `calib.txt` (P0, P1 projection matrices), optional `times.txt`
(else 10 Hz from 0), and ground truth at `<root>/poses/<name>.txt` (for
`<root>/sequences/<name>`) or `poses.txt` in the sequence folder.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..kernel.frames import Calibration, DatasetError, Frame
from ..kernel.trajectory import read_kitti_poses
from ._io import check_index, frame_count, image_size, numbers, pinhole, read_grey, read_rows
from .base import Dataset


def read_calib(path: Path) -> dict[str, np.ndarray]:
    """calib.txt 'KEY: numbers' lines; entries of 12 numbers become 3x4 matrices."""
    calib = {}
    for row in read_rows(path, 2):
        v = numbers(path, row[1:])
        calib[row[0].rstrip(":")] = v.reshape(3, 4) if len(v) == 12 else v
    for key in ("P0", "P1"):
        if calib.get(key, np.zeros(0)).shape != (3, 4):
            raise DatasetError(f"{path}: no {key} line with 12 numbers")
    return calib


def stereo_calibration(calib: dict[str, np.ndarray], width: int, height: int, path: Path) -> Calibration:
    """The left camera from P0 and the baseline -P1[0,3] / P1[0,0] in metres."""
    P0, P1 = calib["P0"], calib["P1"]
    baseline = -P1[0, 3] / P1[0, 0]
    if not np.isfinite(baseline) or baseline <= 0:
        raise DatasetError(f"{path}: P1 gives a baseline of {baseline} m (expected > 0)")
    return Calibration(pinhole(P0[0, 0], P0[1, 1], P0[0, 2], P0[1, 2], width, height),
                       float(baseline), depth_scale=1.0)


class KittiDataset(Dataset):
    """A KITTI odometry sequence folder."""

    format = "kitti"

    def __init__(self, path: Path, *, max_frames: int | None = None):
        path = Path(path)
        self.path, self.name = path, path.resolve().name
        left = sorted((path / "image_0").glob("*.png"))
        times = path / "times.txt"
        stamps = numbers(times, [r[0] for r in read_rows(times)]) if times.is_file() else np.arange(len(left)) * 0.1
        if len(stamps) != len(left):
            raise DatasetError(f"{times}: {len(stamps)} stamps for {len(left)} images in {path / 'image_0'}")
        n = frame_count(len(left), max_frames, path / "image_0")
        self.stamps = stamps[:n]
        self._files = [(p, path / "image_1" / p.name) for p in left[:n]]
        w, h = image_size(left[0])
        self._shape = (h, w)
        self.calibration = stereo_calibration(read_calib(path / "calib.txt"), w, h, path / "calib.txt")
        seq = path.resolve()
        gt = [seq.parent.parent / "poses" / f"{seq.name}.txt"] if seq.parent.name == "sequences" else []
        gt = [p for p in gt + [path / "poses.txt"] if p.is_file()]
        self.ground_truth = read_kitti_poses(gt[0], self.stamps) if gt else None

    def __len__(self) -> int:
        return len(self.stamps)

    def frame(self, i: int) -> Frame:
        i = check_index(i, len(self))
        left, right = self._files[i]
        return Frame(i, float(self.stamps[i]), read_grey(left, self._shape),
                     right=read_grey(right, self._shape), source=f"{left}, {right}")
