"""Timestamped pose sequences and their file formats (TUM, KITTI)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .frames import DatasetError
from .geometry import quat_to_rot, rot_to_quat


@dataclass
class Trajectory:
    """N camera-to-world poses (N, 4, 4) with their stamps (N,) in seconds, sorted by stamp."""

    stamps: np.ndarray
    poses: np.ndarray

    def __post_init__(self):
        self.stamps = np.asarray(self.stamps, dtype=np.float64).reshape(-1)
        self.poses = np.asarray(self.poses, dtype=np.float64).reshape(-1, 4, 4)
        if len(self.stamps) != len(self.poses):
            raise ValueError(f"{len(self.stamps)} stamps for {len(self.poses)} poses")

    def __len__(self) -> int:
        return len(self.stamps)

    @property
    def positions(self) -> np.ndarray:
        return self.poses[:, :3, 3]

    def path_length(self) -> float:
        return float(np.linalg.norm(np.diff(self.positions, axis=0), axis=1).sum()) if len(self) > 1 else 0.0

    def transformed(self, T_left: np.ndarray | None = None, T_right: np.ndarray | None = None) -> "Trajectory":
        """T_left @ pose @ T_right for every pose (change of world frame / of body frame)."""
        P = self.poses
        if T_left is not None:
            P = np.asarray(T_left) @ P
        if T_right is not None:
            P = P @ np.asarray(T_right)
        return Trajectory(self.stamps.copy(), P)


def read_tum(path: str | Path) -> Trajectory:
    """Read `t tx ty tz qx qy qz qw` lines; '#' comments and blank lines are skipped."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as e:
        raise DatasetError(f"cannot read trajectory file {path}: {e.strerror}") from None
    rows = []
    for n, line in enumerate(text.splitlines(), 1):
        line = line.strip().replace(",", " ")
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        if len(parts) < 8:
            raise DatasetError(f"{path}:{n}: expected 8 numbers (t tx ty tz qx qy qz qw), got {len(parts)}")
        try:
            rows.append([float(p) for p in parts[:8]])
        except ValueError:
            raise DatasetError(f"{path}:{n}: not a number in {line!r}") from None
    a = np.array(rows, dtype=np.float64).reshape(-1, 8)
    order = np.argsort(a[:, 0], kind="stable")
    a = a[order]
    poses = np.tile(np.eye(4), (len(a), 1, 1))
    poses[:, :3, :3] = quat_to_rot(a[:, 4:8]) if len(a) else poses[:, :3, :3]
    poses[:, :3, 3] = a[:, 1:4]
    return Trajectory(a[:, 0], poses)


def format_tum(traj: Trajectory) -> str:
    q = rot_to_quat(traj.poses[:, :3, :3]) if len(traj) else np.zeros((0, 4))
    t = traj.positions
    lines = [
        f"{s:.6f} {p[0]:.6f} {p[1]:.6f} {p[2]:.6f} {r[0]:.7f} {r[1]:.7f} {r[2]:.7f} {r[3]:.7f}"
        for s, p, r in zip(traj.stamps, t, q)
    ]
    return "\n".join(lines) + ("\n" if lines else "")


def write_tum(path: str | Path, traj: Trajectory) -> None:
    Path(path).write_text(format_tum(traj))


def read_kitti_poses(path: str | Path, stamps: np.ndarray | None = None) -> Trajectory:
    """KITTI odometry poses: one row of 12 numbers (3×4, row-major) per frame."""
    path = Path(path)
    try:
        a = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except (OSError, ValueError) as e:
        raise DatasetError(f"cannot read KITTI poses {path}: {e}") from None
    if a.shape[1] != 12:
        raise DatasetError(f"{path}: expected 12 numbers per line, got {a.shape[1]}")
    poses = np.tile(np.eye(4), (len(a), 1, 1))
    poses[:, :3, :4] = a.reshape(-1, 3, 4)
    if stamps is None:
        stamps = np.arange(len(a)) * 0.1
    stamps = np.asarray(stamps, dtype=np.float64)[: len(a)]
    return Trajectory(stamps, poses[: len(stamps)])
