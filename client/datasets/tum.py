"""TUM RGB-D player: `rgb.txt` / `depth.txt` lists, colour JPEG/PNG + 16-bit depth PNG
(5000 units per metre), optional `groundtruth.txt` (TUM format, camera-to-world) and optional
`accelerometer.txt` (the Kinect's accelerometer, `timestamp ax ay az` in m/s²).

Frames are the rgb images that have a depth image within 20 ms (one-to-one), stamped with the
rgb stamp; with an `accelerometer.txt` each frame carries the reading at its stamp (linear
between the two nearest readings, none when the nearer is more than `client.imu.MAX_GAP` away) in
the camera's axes as `frame.extras["accel"]` (x right, y down, z forward; the specific force:
+g along up when still). Intrinsics and lens distortion come from the sequence name (freiburg1/2/3, as
published by TUM); the images are delivered raw (depth is registered to the raw colour image)
and the service undistorts feature coordinates. The depth image's own stamp is
`frame.extras["depth_stamp"]` (the tracker moves the depth by the motion in between:
`odometry.depth_time_compensation`).
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..imu import accel_at
from ..kernel.frames import Calibration, DatasetError, Frame
from ..kernel.trajectory import read_tum
from ._io import (
    MAX_DT,
    check_index,
    frame_count,
    image_size,
    numbers,
    pinhole,
    read_color,
    read_depth,
    read_rows,
    sample_poses,
)
from .base import Dataset

log = logging.getLogger(__name__)

DEPTH_SCALE = 5000.0
INTRINSICS = {  # fx, fy, cx, cy of the TUM cameras
    "freiburg1": (517.3, 516.5, 318.6, 255.3),
    "freiburg2": (520.9, 521.0, 325.1, 249.7),
    "freiburg3": (535.4, 539.2, 320.1, 247.6),
}
DEFAULT_INTRINSICS = (525.0, 525.0, 319.5, 239.5)  # the ROS OpenNI default
DISTORTION = {  # k1, k2, p1, p2, k3 of the TUM colour cameras (freiburg3's images are undistorted already)
    "freiburg1": (0.2624, -0.9531, -0.0054, 0.0026, 1.1633),
    "freiburg2": (0.2312, -0.7849, -0.0033, -0.0001, 0.9172),
}
#: The Kinect's accelerometer axes (TUM's `accelerometer.txt`: ax ay az) in the colour camera's
#: (x right, y down, z forward): (-ax, -ay, az). Found from fr1/desk (docs/data.md,
#: tests/test_grid_real.py): of the 48 signed axis permutations the one that makes gravity
#: steadiest in the ground truth's world, and the floor seen in depth agrees with it.
ACCEL_TO_CAMERA = np.diag([-1.0, -1.0, 1.0])


def read_accelerometer(path: Path) -> np.ndarray:
    """TUM's `accelerometer.txt` as an (N, 4) array: stamp, then the reading in the camera's
    axes (`ACCEL_TO_CAMERA`), m/s², sorted by stamp."""
    rows = read_rows(path, 4)
    v = numbers(path, [r[:4] for r in rows]).reshape(-1, 4)
    v = v[np.argsort(v[:, 0], kind="stable")]
    v[:, 1:] = v[:, 1:] @ ACCEL_TO_CAMERA.T
    return v


def associate(a_stamps, b_stamps, max_dt: float = MAX_DT) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one matching of two stamp arrays (any order) with |dt| <= max_dt.

    Equivalent to greedily accepting candidate pairs by increasing |dt| (ties: earlier a, then
    earlier b), each stamp used at most once; done in vectorized rounds that accept every pair
    that is the best remaining candidate of both its stamps. Returns index arrays
    (idx_a, idx_b) ordered by a stamp.
    """
    a = np.asarray(a_stamps, dtype=np.float64).reshape(-1)
    b = np.asarray(b_stamps, dtype=np.float64).reshape(-1)
    ob = np.argsort(b, kind="stable")
    bs = b[ob]
    lo = np.searchsorted(bs, a - max_dt, "left")
    count = np.searchsorted(bs, a + max_dt, "right") - lo
    ia = np.repeat(np.arange(len(a)), count)  # all candidate pairs (a few per stamp)
    jb = np.arange(len(ia)) - np.repeat(np.cumsum(count) - count, count) + np.repeat(lo, count)
    dt = np.abs(a[ia] - bs[jb])
    order = np.lexsort((jb, ia, dt))
    order = order[dt[order] <= max_dt]
    ia, jb = ia[order], jb[order]  # global greedy order
    out_a, out_b = [], []
    while len(ia):
        pos = np.arange(len(ia))
        first_a = np.zeros(len(ia), bool)
        first_a[np.unique(ia, return_index=True)[1]] = True
        first_b = np.zeros(len(ia), bool)
        first_b[np.unique(jb, return_index=True)[1]] = True
        take = pos[first_a & first_b]  # never empty: the first pair is always taken
        out_a.append(ia[take])
        out_b.append(jb[take])
        rest = ~np.isin(ia, ia[take]) & ~np.isin(jb, jb[take])
        ia, jb = ia[rest], jb[rest]
    idx_a = np.concatenate(out_a) if out_a else np.zeros(0, np.intp)
    idx_b = ob[np.concatenate(out_b)] if out_b else np.zeros(0, np.intp)
    keep = np.argsort(a[idx_a], kind="stable")
    return idx_a[keep].astype(np.intp), idx_b[keep].astype(np.intp)


def read_list(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """A TUM `stamp filename` list as (stamps, file paths), sorted by stamp."""
    rows = read_rows(path, 2)
    stamps = numbers(path, [r[0] for r in rows])
    files = np.array([str(path.parent / r[1]) for r in rows], dtype=object)
    order = np.argsort(stamps, kind="stable")
    return stamps[order], files[order]


def distortion_for(name: str) -> tuple[float, ...]:
    """The published lens distortion of the TUM camera named in a sequence folder name
    (empty for freiburg3 and unknown names)."""
    for key, D in DISTORTION.items():
        if key in name:
            return D
    return ()


def intrinsics_for(name: str) -> tuple[float, float, float, float]:
    """fx, fy, cx, cy of the TUM camera named in a sequence folder name."""
    for key, K in INTRINSICS.items():
        if key in name:
            return K
    log.warning("%s: no freiburg1/2/3 in the name; using default intrinsics %s", name, DEFAULT_INTRINSICS)
    return DEFAULT_INTRINSICS


class TumDataset(Dataset):
    """A TUM RGB-D sequence folder."""

    format = "tum"

    def __init__(self, path: Path, *, max_frames: int | None = None):
        """`max_frames`: only the first frames. The camera's distortion is TUM's published one
        for freiburg1/2 (the frames are the raw images, depth registered to them); the service's
        `features.distortion` overrides it."""
        path = Path(path)
        self.path = path
        self.name = path.resolve().name
        rgb_t, rgb_f = read_list(path / "rgb.txt")
        depth_t, depth_f = read_list(path / "depth.txt")
        ia, ib = associate(rgb_t, depth_t, MAX_DT)
        if len(rgb_t) and not len(ia):
            raise DatasetError(f"{path}: no rgb image has a depth image within {MAX_DT * 1e3:.0f} ms")
        n = frame_count(len(ia), max_frames, path)
        self.stamps = rgb_t[ia[:n]]
        self._rgb, self._depth = rgb_f[ia[:n]], depth_f[ib[:n]]
        self._depth_stamps = depth_t[ib[:n]]
        w, h = image_size(self._rgb[0])
        self._shape = (h, w)
        self.calibration = Calibration(pinhole(*intrinsics_for(self.name), w, h, distortion_for(self.name)), None,
                                       DEPTH_SCALE)
        gt = path / "groundtruth.txt"
        self.ground_truth = sample_poses(read_tum(gt), self.stamps) if gt.is_file() else None
        acc = path / "accelerometer.txt"
        #: (N, 4): stamp, reading in camera axes (m/s²); empty without accelerometer.txt
        self.accel = read_accelerometer(acc) if acc.is_file() else np.zeros((0, 4))

    def __len__(self) -> int:
        return len(self.stamps)

    def frame(self, i: int) -> Frame:
        i = check_index(i, len(self))
        rgb, depth = self._rgb[i], self._depth[i]
        stamp = float(self.stamps[i])
        extras = {"depth_stamp": float(self._depth_stamps[i])}
        a = accel_at(self.accel, stamp)
        if a is not None:
            extras["accel"] = a
        return Frame(i, stamp, read_color(rgb, self._shape), depth=read_depth(depth, DEPTH_SCALE, shape=self._shape),
                     source=f"{rgb}, {depth}", extras=extras)
