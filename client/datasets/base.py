"""The common interface of every camera source and the layout detection."""
from __future__ import annotations

from pathlib import Path
from typing import Iterator

import numpy as np

from ..kernel.frames import Calibration, DatasetError, Frame
from ..kernel.trajectory import Trajectory


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


FORMATS = ("tum", "euroc", "kitti", "7scenes", "rosbag", "synthetic")


def detect_format(path: Path) -> str:
    """Name the layout of a dataset folder, or raise DatasetError saying what was expected."""
    if (path / "metadata.yaml").is_file():
        return "rosbag"
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
        "KITTI image_0/+calib.txt, 7-Scenes seq-XX/frame-*.color.*, or a ROS bag: rosbag2 metadata.yaml); "
        "use --format"
    )


def _is_bag(path: Path) -> bool:
    from .rosbag import bag_path

    return bag_path(path) is not None


def open_dataset(spec: str | Path, format: str | None = None, **options) -> Dataset:
    """Open a dataset folder, a ROS bag (a rosbag2 folder with metadata.yaml, a `.db3` /
    `.mcap` file, a ROS 1 `.bag` file), or the synthetic scene with `synthetic[:TRAJECTORY][?person]`
    (`?person`: with the walking person, as `person=True`; `?rate=HZ`: its frame rate, default 30;
    both: `?person&rate=5`).

    `options` go to the player (e.g. `max_frames`; for bags `topics`, see
    `client.datasets.rosbag`; for 7-Scenes `register`: None (the default) registers depth into
    the Kinect v1 colour camera for Microsoft's data only, True / False always / never, see
    `client.datasets.sevenscenes`; for the synthetic scene `noise`, `seed`, `frames`, `person`, ...).
    """
    text = str(spec)
    topics = options.pop("topics", None)
    register = options.pop("register", None)

    def only_7scenes(fmt: str) -> None:
        if register is not None:
            raise DatasetError(f"{text}: depth registration (--depth-registration) applies to 7-Scenes only, "
                               f"not to {fmt}")

    if format == "synthetic" or text.startswith("synthetic"):
        if topics:
            raise DatasetError(f"{text}: --topics applies to ROS bags only")
        only_7scenes("synthetic")
        from ..synthetic import SyntheticDataset

        base, _, extra = text.partition("?")  # synthetic:loop?person: with the walking person
        for flag in filter(None, extra.split("&")):
            name, eq, value = flag.partition("=")
            if flag == "person":
                options.setdefault("person", True)
            elif name == "rate" and eq:  # synthetic:walk_a?rate=5: frames per second (default 30)
                try:
                    options["rate"] = float(value)
                except ValueError:
                    raise DatasetError(f"{text}: rate must be a number of frames per second, got {value!r}") from None
            else:
                raise DatasetError(f"{text}: unknown synthetic option {flag!r} (known: person, rate=HZ)")
        trajectory = base.split(":", 1)[1] if ":" in base else "loop"
        return SyntheticDataset(trajectory=trajectory, **options)
    path = Path(text).expanduser()
    if not path.exists():
        raise DatasetError(f"{path}: no such file or directory")
    if format == "rosbag" or (format is None and _is_bag(path)):
        from .rosbag import RosbagDataset

        only_7scenes("rosbag")
        return RosbagDataset(path, topics=topics, **options)
    if topics:
        raise DatasetError(f"{path}: --topics applies to ROS bags only")
    if not path.is_dir():
        raise DatasetError(f"{path}: not a dataset folder (nor a ROS bag: .bag, .db3, .mcap or a rosbag2 folder "
                           "with metadata.yaml)")
    fmt = format or detect_format(path)
    if fmt == "7scenes":
        options["register"] = register
    else:
        only_7scenes(fmt)
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
