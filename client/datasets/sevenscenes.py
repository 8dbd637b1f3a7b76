"""Microsoft 7-Scenes player: a `seq-XX` folder of `frame-XXXXXX.color.{png,jpg}`,
`frame-XXXXXX.depth.png` (uint16 millimetres, 65535 = invalid) and `frame-XXXXXX.pose.txt`
(4x4 camera-to-world), or a scene folder (its first `seq-XX` in sorted order is played).

There are no timestamps: frame number k is stamped k/30 s. `camera-intrinsics.txt` in the
sequence folder or its parent (default 585, 585, 320, 240) holds the *depth* camera's
intrinsics, and the ground truth (KinectFusion) is the depth camera's pose.

7-Scenes colour is not registered to depth (the dataset says so): by default the player
registers each depth image into the colour camera (`registration.DepthRegistration`) with the
Kinect v1's nominal colour intrinsics (525, 525, 319.5, 239.5) and its colour camera 2.5 cm
along the depth camera's +x. It delivers the colour camera's calibration, and the ground truth
moved to the colour camera by the same extrinsic. Fitted without ground truth on this data
(depth discontinuities against colour edges, 20 frames of redkitchen): fx 526, fy 531,
baseline 2.52 cm, principal point within 1.4 px. `register=False` plays the raw images with the
depth camera's intrinsics, as the dataset's own note suggests.
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..kernel.frames import Calibration, DatasetError, Frame
from ..kernel.trajectory import Trajectory
from ._io import check_index, frame_count, image_size, numbers, pinhole, read_color, read_depth, read_rows
from .base import Dataset
from .registration import DepthRegistration

log = logging.getLogger(__name__)

DEPTH_SCALE = 1000.0
INVALID_DEPTH = 65535
FPS = 30.0
DEFAULT_INTRINSICS = (585.0, 585.0, 320.0, 240.0)
KINECT_COLOUR_INTRINSICS = (525.0, 525.0, 319.5, 239.5)  # Kinect v1 colour camera, nominal
KINECT_COLOUR_OFFSET = (0.025, 0.0, 0.0)  # m, the colour camera's centre in the depth camera's frame


def read_intrinsics(seq: Path) -> tuple[float, float, float, float]:
    """fx, fy, cx, cy from camera-intrinsics.txt (a 3x3 matrix) in `seq` or its parent."""
    for path in (seq / "camera-intrinsics.txt", seq.parent / "camera-intrinsics.txt"):
        if path.is_file():
            K = numbers(path, read_rows(path, 3))
            if K.shape != (3, 3):
                raise DatasetError(f"{path}: expected a 3x3 matrix, got shape {K.shape}")
            return K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    log.info("%s: no camera-intrinsics.txt; using the 7-Scenes default %s", seq, DEFAULT_INTRINSICS)
    return DEFAULT_INTRINSICS


def read_poses(paths: list[Path]) -> tuple[np.ndarray, np.ndarray]:
    """4x4 pose files as (poses (N, 4, 4), valid (N,)); a missing file or one with non-finite
    values is invalid (7-Scenes has some -inf poses), a malformed one raises."""
    rows = []
    for path in paths:
        try:
            fields = path.read_text().split()
        except FileNotFoundError:
            fields = ["nan"] * 16
        except (OSError, UnicodeDecodeError) as e:
            raise DatasetError(f"{path}: cannot read pose ({e})") from None
        if len(fields) != 16:
            raise DatasetError(f"{path}: expected 16 numbers (a 4x4 pose), got {len(fields)}")
        rows.append(numbers(path, fields))
    poses = np.array(rows).reshape(-1, 4, 4)
    return poses, np.isfinite(poses).all(axis=(1, 2))


class SevenScenesDataset(Dataset):
    """One 7-Scenes sequence."""

    format = "7scenes"

    def __init__(self, path: Path, *, max_frames: int | None = None, register: bool = True):
        path = Path(path)
        seq = path
        if not any(path.glob("frame-*.color.*")):
            seqs = sorted(p for p in path.glob("seq-*") if p.is_dir())
            if not seqs:
                raise DatasetError(f"{path}: no frame-*.color.* images and no seq-XX folders")
            seq = seqs[0]
            log.info("%s: playing %s (first of %d sequences)", path, seq.name, len(seqs))
        self.path, self.name = seq, f"{seq.resolve().parent.name}/{seq.name}"
        colour = sorted(p for p in seq.glob("frame-*.color.*") if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
        n = frame_count(len(colour), max_frames, seq)
        self._colour = colour[:n]
        stems = [p.name.split(".")[0] for p in self._colour]  # frame-XXXXXX
        self._depth = [seq / f"{s}.depth.png" for s in stems]
        self.stamps = numbers(seq, [s[len("frame-"):] for s in stems]) / FPS
        w, h = image_size(self._colour[0])
        self._shape = (h, w)
        depth_camera = pinhole(*read_intrinsics(seq), w, h)
        self.registration = None
        if register:
            T_colour_depth = np.eye(4)
            T_colour_depth[:3, 3] = -np.asarray(KINECT_COLOUR_OFFSET)
            colour_camera = pinhole(*KINECT_COLOUR_INTRINSICS, 640, 480).scaled(w / 640)  # nominal at 640×480
            self.registration = DepthRegistration(depth_camera, colour_camera, T_colour_depth)
        camera = self.registration.colour_camera if register else depth_camera
        self.calibration = Calibration(camera, None, DEPTH_SCALE)
        poses, valid = read_poses([seq / f"{s}.pose.txt" for s in stems])
        if not valid.all():
            log.info("%s: %d of %d poses missing or non-finite, left out of the ground truth", seq, (~valid).sum(), n)
        if register:
            poses[valid] = self.registration.colour_from_depth_poses(poses[valid])
        self.ground_truth = Trajectory(self.stamps[valid], poses[valid])

    def __len__(self) -> int:
        return len(self.stamps)

    def frame(self, i: int) -> Frame:
        i = check_index(i, len(self))
        colour, depth = self._colour[i], self._depth[i]
        d = read_depth(depth, DEPTH_SCALE, INVALID_DEPTH, self._shape)
        if self.registration is not None:
            d = self.registration.register(d)
        return Frame(i, float(self.stamps[i]), read_color(colour, self._shape), depth=d, source=f"{colour}, {depth}")
