"""The common interface of every camera source and the layout detection."""
from __future__ import annotations

from pathlib import Path
from typing import Iterator

import numpy as np

from ..frames import Calibration, DatasetError, Frame
from ..trajectory import Trajectory


class Dataset:
    """A finite, replayable sequence of frames.

    Subclasses set `name`, `calibration`, `ground_truth` (camera-to-world poses of the frame
    camera, or None) and implement `__len__` and `frame(i)`. Iteration yields frames in
    order; `frame(i)` raises `DatasetError` naming the file when an image is missing or
    corrupt.
    """

    name: str = "dataset"
    format: str = "?"
    calibration: Calibration
    ground_truth: Trajectory | None = None
    stamps: np.ndarray  # (len,) seconds, of every frame, known without reading the frames

    def __len__(self) -> int:  # pragma: no cover - abstract
        raise NotImplementedError

    def frame(self, i: int) -> Frame:  # pragma: no cover - abstract
        raise NotImplementedError

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self.frame(i)


FORMATS = ("tum", "euroc", "kitti", "7scenes", "synthetic")


def detect_format(path: Path) -> str:
    """Name the layout of a dataset folder, or raise DatasetError saying what was expected."""
    if (path / "rgb.txt").is_file() and (path / "depth.txt").is_file():
        return "tum"
    if (path / "mav0").is_dir() or (path.name == "mav0" and (path / "cam0").is_dir()):
        return "euroc"
    if (path / "image_0").is_dir() and (path / "calib.txt").is_file():
        return "kitti"
    if any(path.glob("frame-*.color.*")) or any(path.glob("seq-*/frame-*.color.*")):
        return "7scenes"
    raise DatasetError(
        f"{path}: unknown dataset layout (expected TUM rgb.txt+depth.txt, EuRoC mav0/, "
        "KITTI image_0/+calib.txt, or 7-Scenes seq-XX/frame-*.color.*); use --format"
    )


def open_dataset(spec: str | Path, format: str | None = None, **options) -> Dataset:
    """Open a dataset folder, or the synthetic scene with `synthetic[:TRAJECTORY]`.

    `options` go to the player (e.g. `max_frames`, and for the synthetic scene `noise`,
    `seed`, `frames`, ...).
    """
    text = str(spec)
    if format == "synthetic" or text.startswith("synthetic"):
        from ..synthetic import SyntheticDataset

        trajectory = text.split(":", 1)[1] if ":" in text else "loop"
        return SyntheticDataset(trajectory=trajectory, **options)
    path = Path(text).expanduser()
    if not path.exists():
        raise DatasetError(f"{path}: no such file or directory")
    if not path.is_dir():
        raise DatasetError(f"{path}: not a dataset folder")
    fmt = format or detect_format(path)
    if fmt == "tum":
        from .tum import TumDataset as cls
    elif fmt == "euroc":
        from .euroc import EurocDataset as cls
    elif fmt == "kitti":
        from .kitti import KittiDataset as cls
    elif fmt == "7scenes":
        from .sevenscenes import SevenScenesDataset as cls
    else:
        raise DatasetError(f"unknown dataset format {fmt!r}; known: {', '.join(FORMATS)}")
    return cls(path, **options)
