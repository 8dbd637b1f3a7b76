"""Helpers shared by the dataset players: checked image and depth loading, text tables,
nearest-stamp pose sampling and argument checks. Every failure is a `DatasetError` that names
the offending file or folder."""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from ..kernel.frames import DatasetError, PinholeCamera
from ..kernel.trajectory import Trajectory

MAX_DT = 0.02  # seconds: the largest stamp difference accepted when pairing streams


def _imread(path: str | Path, flags: int, shape: tuple[int, int] | None = None) -> np.ndarray:
    """cv2.imread that raises on a missing or corrupt file, or on a size other than `shape`
    (height, width)."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: image file is missing")
    img = cv2.imread(str(path), flags)
    if img is None or img.size == 0:
        raise DatasetError(f"{path}: unreadable or corrupt image")
    if shape is not None and img.shape[:2] != tuple(shape):
        raise DatasetError(f"{path}: image is {img.shape[1]}x{img.shape[0]}, expected {shape[1]}x{shape[0]}")
    return img


def read_color(path: str | Path, shape: tuple[int, int] | None = None) -> np.ndarray:
    """An 8-bit BGR image."""
    return _imread(path, cv2.IMREAD_COLOR, shape)


def read_grey(path: str | Path, shape: tuple[int, int] | None = None) -> np.ndarray:
    """An 8-bit grey image."""
    return _imread(path, cv2.IMREAD_GRAYSCALE, shape)


def read_depth(path: str | Path, units_per_metre: float, invalid: int | None = None,
               shape: tuple[int, int] | None = None) -> np.ndarray:
    """A 16-bit depth PNG as float32 metres; raw 0 (and raw `invalid`) become 0."""
    raw = _imread(path, cv2.IMREAD_UNCHANGED, shape)
    if raw.ndim != 2 or raw.dtype != np.uint16:
        raise DatasetError(f"{path}: expected a single-channel 16-bit depth PNG, got {raw.dtype} {raw.shape}")
    depth = raw.astype(np.float32) / np.float32(units_per_metre)
    if invalid is not None:
        depth[raw == invalid] = 0.0
    return depth


def image_size(path: str | Path) -> tuple[int, int]:
    """(width, height) of an image file."""
    h, w = _imread(path, cv2.IMREAD_UNCHANGED).shape[:2]
    return w, h


def pinhole(fx, fy, cx, cy, width, height, distortion=()) -> PinholeCamera:
    """A PinholeCamera with plain Python numbers (not numpy scalars)."""
    return PinholeCamera(float(fx), float(fy), float(cx), float(cy), int(width), int(height),
                         tuple(float(v) for v in distortion))


def read_rows(path: str | Path, min_fields: int = 1) -> list[list[str]]:
    """The lines of a text table split on commas and whitespace; blank lines and '#' comments
    are skipped, and every row must have at least `min_fields` fields."""
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise DatasetError(f"{path}: cannot read ({getattr(e, 'strerror', None) or e})") from None
    rows = []
    for n, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        fields = line.replace(",", " ").split()
        if len(fields) < min_fields:
            raise DatasetError(f"{path}:{n}: expected at least {min_fields} fields, got {len(fields)}")
        rows.append(fields)
    return rows


def numbers(path: str | Path, fields: Sequence, dtype=np.float64) -> np.ndarray:
    """Text fields (a list, or a list of equal-length rows) as a numeric array; `path` is only
    for the error message."""
    try:
        return np.array(fields, dtype=str).astype(dtype)
    except ValueError as e:
        raise DatasetError(f"{path}: not a table of numbers ({e})") from None


def sample_poses(traj: Trajectory, stamps: np.ndarray, max_dt: float = MAX_DT) -> Trajectory:
    """For each of `stamps` the pose of `traj` with the nearest stamp, if within `max_dt`
    (stamps without one are left out). The result is stamped with `stamps`."""
    stamps = np.asarray(stamps, dtype=np.float64).reshape(-1)
    if len(traj) == 0 or len(stamps) == 0:
        return Trajectory(np.zeros(0), np.zeros((0, 4, 4)))
    order = np.argsort(traj.stamps, kind="stable")
    ref = traj.stamps[order]
    k = np.searchsorted(ref, stamps)
    cand = np.clip(np.stack([k - 1, k]), 0, len(ref) - 1)  # neighbours on either side
    dt = np.abs(ref[cand] - stamps)
    best = np.argmin(dt, axis=0)
    j = cand[best, np.arange(len(stamps))]
    ok = dt[best, np.arange(len(stamps))] <= max_dt
    return Trajectory(stamps[ok], traj.poses[order[j[ok]]])


def frame_count(available: int, max_frames: int | None, where: Path) -> int:
    """How many frames a player keeps: all of them, or at most `max_frames` (a positive int)."""
    if available == 0:
        raise DatasetError(f"{where}: no frames found")
    if max_frames is None:
        return available
    if isinstance(max_frames, bool) or not isinstance(max_frames, (int, np.integer)) or max_frames < 1:
        raise DatasetError(f"{where}: max_frames must be a positive integer, got {max_frames!r}")
    return min(available, int(max_frames))


def check_index(i: int, n: int) -> int:
    """A frame index in 0..n-1 (negative indices count from the end)."""
    if not -n <= i < n:
        raise IndexError(f"frame {i} out of range for {n} frames")
    return int(i) % n
