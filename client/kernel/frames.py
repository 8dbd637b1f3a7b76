"""The data model every camera source produces and the service consumes.

Conventions (used everywhere in the project):
- Images are numpy arrays: colour is H×W×3 uint8 **BGR** (OpenCV order), grey is H×W uint8.
- Depth is H×W float32 in **metres**; 0 or a non-finite value means "no measurement".
- Poses are 4×4 float64 **camera-to-world** transforms; the camera frame is OpenCV's
  (x right, y down, z forward).
- Stereo frames are **rectified**: left and right share `Calibration.camera`, rows align,
  and `Calibration.baseline` is the distance between the two optical centres in metres.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class PinholeCamera:
    """Undistorted pinhole intrinsics of the images a source delivers."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def scaled(self, factor: float) -> "PinholeCamera":
        """The same camera for images resized by `factor`."""
        return PinholeCamera(
            self.fx * factor, self.fy * factor, (self.cx + 0.5) * factor - 0.5,
            (self.cy + 0.5) * factor - 0.5, round(self.width * factor), round(self.height * factor),
        )


@dataclass(frozen=True)
class Calibration:
    """What a consumer needs to turn a source's frames into geometry.

    `depth_scale` is the number of raw depth units per metre of the source's native depth
    encoding (5000 for TUM, 1000 for 7-Scenes); frames themselves always carry metres.
    """

    camera: PinholeCamera
    baseline: float | None = None  # rectified stereo baseline in metres, None if not stereo
    depth_scale: float = 1000.0

    @property
    def kind(self) -> str:
        return "stereo" if self.baseline else "rgbd"


@dataclass
class Frame:
    """One timestamped observation from a camera source."""

    index: int  # position in the source's stream, from 0
    stamp: float  # seconds
    image: np.ndarray  # colour BGR H×W×3 or grey H×W, uint8 (left image for stereo)
    depth: np.ndarray | None = None  # H×W float32 metres, 0 / non-finite = invalid
    right: np.ndarray | None = None  # rectified right image (stereo)
    source: str = ""  # where it came from (file names), for error messages
    extras: dict = field(default_factory=dict)  # e.g. synthetic labels / instance ids

    @property
    def grey(self) -> np.ndarray:
        if self.image.ndim == 2:
            return self.image
        import cv2

        return cv2.cvtColor(self.image, cv2.COLOR_BGR2GRAY)


class DatasetError(Exception):
    """A camera source cannot deliver: missing or corrupt file, unknown layout, bad calibration.
    The message names the offending file or folder."""
