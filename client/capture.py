"""`CaptureSource`: a webcam / video device or a video file as a mono camera source.

    src = CaptureSource(0)                       # /dev/video0 (an int or a string of digits)
    src = CaptureSource("walk.mp4")              # a video file (must exist)
    for frame in src: ...                        # BGR frames, no depth, until the video ends

Frames carry only the image (`depth` and `right` are None): the source is a monocular camera
(`kind = "mono"`). Unless a `Calibration` is given, the intrinsics are a pinhole guess:
fx = fy = 0.9 × width (a ~58° horizontal field of view, typical of webcams) and the principal
point at the image centre — fine for streaming tests, to be replaced by a real calibration for
metric work. Images are assumed undistorted.

Stamps: for files, the position of the decoded frame (CAP_PROP_POS_MSEC) when the backend
reports a usable one, else k / fps (fps from CAP_PROP_FPS, 30 if unknown). For devices, the
monotonic clock in seconds since the first frame (device timestamps are backend-specific).

Length: for files, CAP_PROP_FRAME_COUNT (capped by `max_frames`); it is only an estimate for
some containers, so iteration reads until the decoder stops and may yield fewer or more
frames. A device has no length unless `max_frames` is given (`len()` raises TypeError);
iterate it, and it yields frames until the device stops delivering (or `max_frames`).
"""
from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Iterator

import numpy as np

from .datasets.base import Dataset
from .kernel.frames import Calibration, DatasetError, Frame, PinholeCamera

DEFAULT_FOCAL_FACTOR = 0.9


def default_calibration(width: int, height: int, depth_scale: float = 1000.0) -> Calibration:
    """The pinhole guess used when no calibration is given: fx = fy = 0.9 × width, centred."""
    f = DEFAULT_FOCAL_FACTOR * width
    return Calibration(PinholeCamera(f, f, (width - 1) / 2.0, (height - 1) / 2.0, int(width), int(height)),
                       None, depth_scale)


def _device_index(source) -> int | None:
    if isinstance(source, bool):
        return None
    if isinstance(source, (int, np.integer)):
        return int(source)
    if isinstance(source, str) and source.strip().isdigit():
        return int(source.strip())
    return None


class CaptureSource(Dataset):
    """A cv2.VideoCapture as a `Dataset` of mono frames (see the module documentation)."""

    kind = "mono"

    def __init__(self, source: int | str | Path, calibration: Calibration | None = None, *,
                 max_frames: int | None = None, fps: float | None = None):
        import cv2

        if max_frames is not None and (isinstance(max_frames, bool) or not isinstance(max_frames, (int, np.integer))
                                       or max_frames < 1):
            raise DatasetError(f"{source}: max_frames must be a positive integer, got {max_frames!r}")
        self.max_frames = None if max_frames is None else int(max_frames)
        index = _device_index(source)
        self.device = index
        if index is None:
            path = Path(str(source)).expanduser()
            if not path.exists():
                raise DatasetError(f"{path}: no such file or directory")
            if not path.is_file():
                raise DatasetError(f"{path}: not a video file")
            self.source = str(path)
            self.name = path.stem
            self.format = "video"
            self._cap = cv2.VideoCapture(str(path))
            if not self._cap.isOpened():
                raise DatasetError(f"{path}: cannot open as a video (unknown or corrupt format)")
        else:
            self.source = f"camera:{index}"
            self.name = f"camera{index}"
            self.format = "camera"
            self._cap = cv2.VideoCapture(index)
            if not self._cap.isOpened():
                raise DatasetError(f"camera device {index}: cannot open (no such device or busy)")
        cap_fps = self._cap.get(cv2.CAP_PROP_FPS)
        self.fps = float(fps) if fps else (cap_fps if math.isfinite(cap_fps) and 0 < cap_fps < 1000 else 30.0)
        self._next = 0  # index of the frame the next read returns
        self._pending: tuple[float, np.ndarray] | None = None  # first frame read to learn the size
        self._t0: float | None = None
        w = int(self._cap.get(cv2.CAP_PROP_FRAME_WIDTH))
        h = int(self._cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        if w <= 0 or h <= 0:
            first = self._read()
            if first is None:
                self.release()
                raise DatasetError(f"{self.source}: delivers no frames")
            self._pending = first
            h, w = first[1].shape[:2]
        self.width, self.height = w, h
        if calibration is None:
            calibration = default_calibration(w, h)
        elif (calibration.camera.width, calibration.camera.height) != (w, h):
            raise DatasetError(f"{self.source}: calibration is for {calibration.camera.width}×"
                               f"{calibration.camera.height} images, the source delivers {w}×{h}")
        self.calibration = calibration
        count = int(self._cap.get(cv2.CAP_PROP_FRAME_COUNT)) if index is None else 0
        self._count = count if count > 0 else None

    def __repr__(self) -> str:
        return f"CaptureSource({self.source!r}, {self.width}x{self.height} @ {self.fps:g} fps)"

    def __len__(self) -> int:
        n = self._count
        if self.max_frames is not None:
            n = self.max_frames if n is None else min(n, self.max_frames)
        if n is None:
            raise TypeError(f"{self.source}: a live camera has no length (give max_frames)")
        return n

    def _read(self) -> tuple[float, np.ndarray] | None:
        """(stamp, image) of the next frame, or None at the end."""
        import cv2

        if self._cap is None:
            raise DatasetError(f"{self.source}: already released")
        ok, image = self._cap.read()
        if not ok or image is None:
            return None
        k = self._next
        self._next += 1
        if self.device is not None:
            now = time.monotonic()
            if self._t0 is None:
                self._t0 = now
            stamp = now - self._t0
        else:
            ms = self._cap.get(cv2.CAP_PROP_POS_MSEC)
            stamp = ms / 1000.0 if math.isfinite(ms) and ms >= 0 and (k == 0 or ms > 0) else k / self.fps
        if image.ndim == 3 and image.shape[2] == 4:
            image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
        return stamp, image

    def _make(self, i: int, item: tuple[float, np.ndarray]) -> Frame:
        stamp, image = item
        return Frame(index=i, stamp=float(stamp), image=image, source=f"{self.source}#{i}")

    def frame(self, i: int) -> Frame:
        """Frame i. Files seek when i is not the next frame; devices deliver only in order."""
        import cv2

        if i < 0 or (self.max_frames is not None and i >= self.max_frames):
            raise IndexError(f"{self.source}: frame {i} out of range")
        if self._pending is not None and i == 0:
            item, self._pending = self._pending, None
            return self._make(0, item)
        self._pending = None
        if i != self._next:
            if self.device is not None:
                raise DatasetError(f"{self.source}: a live camera delivers frames in order "
                                   f"(asked {i}, next {self._next})")
            self._cap.set(cv2.CAP_PROP_POS_FRAMES, i)
            self._next = i
        item = self._read()
        if item is None:
            raise DatasetError(f"{self.source}: cannot read frame {i} (end of video or corrupt)")
        return self._make(i, item)

    def __iter__(self) -> Iterator[Frame]:
        """Frames from the start (files) or from now (devices) until the source stops or
        `max_frames` frames were delivered."""
        i = 0
        if self.device is None and self._pending is None and self._next != 0:
            import cv2

            self._cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
            self._next = 0
        while self.max_frames is None or i < self.max_frames:
            if self._pending is not None:
                item, self._pending = self._pending, None
            else:
                item = self._read()
            if item is None:
                return
            yield self._make(i, item)
            i += 1

    def release(self) -> None:
        """Close the device / file."""
        cap, self._cap = getattr(self, "_cap", None), None
        if cap is not None:
            cap.release()

    close = release

    def __enter__(self) -> "CaptureSource":
        return self

    def __exit__(self, *exc) -> None:
        self.release()

    def __del__(self):
        try:
            self.release()
        except Exception:
            pass


__all__ = ["CaptureSource", "default_calibration", "DEFAULT_FOCAL_FACTOR"]
