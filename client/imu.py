"""Accelerometer readings from ROS `sensor_msgs/Imu` for the occupancy grid's up direction:
the rosbag player (client/datasets/rosbag.py) and the live ROS bridge (service/ros.py) give a
frame the reading at its stamp as `frame.extras["accel"]`, as the TUM player does from
`accelerometer.txt`: the specific force (`linear_acceleration`, m/s²; +g along up when still)
in the camera's optical axes (x right, y down, z forward). Only its direction matters (the
grid's up is the mean of many readings, docs/grid.md); the IMU's lever arm is ignored.

The IMU's axes in the camera's (`imu_axes`), in order:

1. configured: ``optical`` (the IMU reports in the camera's optical axes), ``body`` (REP 103
   body axes, x forward, y left, z up, of a frame aligned with the camera), or three signed
   axes ``A:B:C`` naming the IMU axis along the camera's x, y and z (``body`` is ``-y:-z:x``);
2. a bag's `/tf_static` chain between the Imu's `header.frame_id` and the colour image's
   (the rotation only);
3. by the Imu's frame name: one ending in ``optical_frame`` (a RealSense's
   ``camera_imu_optical_frame``) is ``optical``, any other ``body`` (REP 103's convention for
   a sensor's non-optical frame). An assumption: a bag whose IMU is mounted otherwise and
   carries no tf needs the axes configured.
"""
from __future__ import annotations

import threading
from collections import deque

import numpy as np

from .kernel.frames import DatasetError
from .kernel.protocol import MAX_ACCEL

IMU = "sensor_msgs/msg/Imu"
#: The camera's optical axes from REP 103 body axes (x forward, y left, z up): optical x = -body y,
#: optical y = -body z, optical z = body x.
BODY_TO_OPTICAL = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
#: s; a frame farther than this from every reading gets none (the TUM player's, a bag's, a live robot's)
MAX_GAP = 0.05
_AXES = {"x": 0, "y": 1, "z": 2}


def parse_axes(spec) -> np.ndarray:
    """`imu_axes` as the rotation camera ← IMU (3×3): ``optical``, ``body``, ``A:B:C`` (signed
    IMU axes along the camera's x, y, z, e.g. ``-y:-z:x``) or a 3×3 rotation (DatasetError
    otherwise)."""
    if not isinstance(spec, str):
        R = np.asarray(spec, np.float64)
        if R.shape != (3, 3) or not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise DatasetError(f"imu_axes: expected a 3x3 rotation, got {spec!r}")
        return R
    s = spec.strip().lower()
    if s == "optical":
        return np.eye(3)
    if s == "body":
        return BODY_TO_OPTICAL.copy()
    parts = s.split(":")
    R = np.zeros((3, 3))
    ok = len(parts) == 3
    for row, p in enumerate(parts if ok else []):
        sign, axis = (-1.0, p[1:]) if p.startswith("-") else (1.0, p.lstrip("+"))
        if axis not in _AXES:
            ok = False
            break
        R[row, _AXES[axis]] = sign
    if not ok or abs(np.linalg.det(R) - 1.0) > 1e-9:
        raise DatasetError(f"imu_axes: expected optical, body or three signed axes A:B:C making a rotation "
                           f"(the IMU axis along the camera's x, y, z; body = -y:-z:x), got {spec!r}")
    return R


def axes_by_name(frame_id: str) -> tuple[np.ndarray, str]:
    """The IMU's axes in the camera's from its frame name alone (rule 3 above), and which."""
    if str(frame_id).rstrip("/").endswith("optical_frame"):
        return np.eye(3), "optical"
    return BODY_TO_OPTICAL.copy(), "body"


def reading(msg) -> tuple[np.ndarray, str] | None:
    """An Imu message's linear_acceleration (3,) and its frame, or None when it has none
    (covariance[0] = -1 by the message's convention, or not finite, zero or beyond the wire
    protocol's MAX_ACCEL)."""
    cov = np.asarray(msg.linear_acceleration_covariance, np.float64).reshape(-1)
    a = msg.linear_acceleration
    v = np.array([a.x, a.y, a.z], np.float64)
    if (len(cov) and cov[0] == -1.0) or not np.all(np.isfinite(v)) or not np.any(v) \
            or float(np.linalg.norm(v)) > MAX_ACCEL:
        return None
    return v, str(msg.header.frame_id)


def accel_at(readings: np.ndarray, stamp: float, max_gap: float = MAX_GAP) -> np.ndarray | None:
    """The reading at `stamp` from (N, 4) rows (stamp, x, y, z; sorted by stamp; the TUM
    player's `accelerometer.txt`, a bag's or a live robot's Imu): linear between the readings
    either side, the nearest one at the ends; None when the nearest is more than `max_gap` away."""
    if not len(readings):
        return None
    t = readings[:, 0]
    j = int(np.searchsorted(t, stamp))
    if j == 0 or j == len(t):
        k = min(j, len(t) - 1)
        return readings[k, 1:].copy() if abs(t[k] - stamp) <= max_gap else None
    t0, t1 = t[j - 1], t[j]
    if min(stamp - t0, t1 - stamp) > max_gap:
        return None
    w = (stamp - t0) / (t1 - t0) if t1 > t0 else 0.0
    return (1.0 - w) * readings[j - 1, 1:] + w * readings[j, 1:]


class ImuBuffer:
    """The last seconds of one robot's Imu readings (the live bridge): `add` on the Zenoh
    thread, `at` on the worker that decodes the frames (readings in camera axes)."""

    def __init__(self, axes: np.ndarray | None, keep: float = 2.0, cap: int = 4096):
        self.axes = axes  # camera ← IMU; None: from the first message's frame name
        self.how = "configured" if axes is not None else None
        self.keep, self._rows = keep, deque(maxlen=cap)
        self._lock = threading.Lock()

    def add(self, stamp: float, v: np.ndarray, frame_id: str) -> None:
        with self._lock:
            if self.axes is None:
                self.axes, self.how = axes_by_name(frame_id)
            if self._rows and stamp <= self._rows[-1][0]:  # out of order or repeated: kept sorted
                if stamp < self._rows[0][0] or any(r[0] == stamp for r in self._rows):
                    return
                rows = sorted([*self._rows, (stamp, *(self.axes @ v))])
                self._rows.clear()
                self._rows.extend(rows)
            else:
                self._rows.append((stamp, *(self.axes @ v)))
            while self._rows and self._rows[0][0] < stamp - self.keep:
                self._rows.popleft()

    def at(self, stamp: float) -> np.ndarray | None:
        with self._lock:
            rows = np.array(self._rows, np.float64).reshape(-1, 4)
        return accel_at(rows, stamp)
