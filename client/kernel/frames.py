"""The data model every camera source produces and the service consumes.

Conventions (used everywhere in the project):
- Images are numpy arrays: colour is H×W×3 uint8 **BGR** (OpenCV order), grey is H×W uint8.
- Depth is H×W float32 in **metres**; 0 or a non-finite value means "no measurement".
- Poses are 4×4 float64 **camera-to-world** transforms; the camera frame is OpenCV's
  (x right, y down, z forward).
- Images are delivered as the sensor took them; `PinholeCamera.distortion` says how the lens
  distorts them (empty: undistorted). RGB-D depth is registered to the raw colour image.
- Stereo frames are **rectified**: left and right share `Calibration.camera`, rows align,
  and `Calibration.baseline` is the distance between the two optical centres in metres.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import lru_cache

import numpy as np


@dataclass(frozen=True)
class PinholeCamera:
    """Intrinsics of the images a source delivers: the pinhole K and the lens distortion of
    those images (OpenCV's radial-tangential order k1, k2, p1, p2[, k3[, k4, k5, k6]]; empty:
    the images are undistorted).

    Distortion is handled one way everywhere: the images are used as delivered (depth
    registered to the raw colour image stays on its pixels), feature coordinates are
    undistorted (`undistort_points`) and dense code back-projects pixels along the undistorted
    rays (`pixel_rays`) or works on images remapped to the pinhole camera (`undistort_maps`)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    distortion: tuple[float, ...] = ()

    def __post_init__(self):
        d = tuple(float(v) for v in self.distortion)
        if len(d) not in (0, 4, 5, 8) or not all(np.isfinite(d)):
            raise ValueError(f"distortion must be 4, 5 or 8 finite coefficients (k1 k2 p1 p2 [k3 [k4 k5 k6]]), got {d}")
        object.__setattr__(self, "distortion", d if any(d) else ())

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def distorted(self) -> bool:
        """Whether the images have a lens distortion (non-zero coefficients)."""
        return bool(self.distortion)

    @property
    def pinhole(self) -> "PinholeCamera":
        """The same K without the distortion: the camera of undistorted coordinates."""
        return replace(self, distortion=()) if self.distortion else self

    def scaled(self, factor: float) -> "PinholeCamera":
        """The same camera for images resized by `factor` (the distortion, in normalized
        coordinates, is unchanged)."""
        return PinholeCamera(
            self.fx * factor, self.fy * factor, (self.cx + 0.5) * factor - 0.5,
            (self.cy + 0.5) * factor - 0.5, round(self.width * factor), round(self.height * factor), self.distortion,
        )

    def undistort_points(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) raw image pixels as undistorted pixels of K (float32; the input itself, as
        float32, when there is no distortion). One vectorised call for all points."""
        xy = np.asarray(xy, np.float32).reshape(-1, 2)
        if not self.distortion or not len(xy):
            return xy
        import cv2

        out = cv2.undistortPointsIter(xy.reshape(-1, 1, 2), self.K, np.asarray(self.distortion), np.eye(3), self.K,
                                      _UNDISTORT_CRITERIA)  # (R = identity: no rectification)
        return out.reshape(-1, 2).astype(np.float32)

    def pixel_rays(self) -> np.ndarray:
        """(H, W, 2) float32: for every raw pixel (u, v) its ray's normalized coordinates
        (x/z, y/z), the distortion removed; a point at depth z there is z·(x/z, y/z, 1).
        Computed once per camera."""
        return _pixel_rays(self)

    def undistort_maps(self) -> tuple[np.ndarray, np.ndarray]:
        """cv2.remap maps (float32 x, y) that turn a raw image into the image of `pinhole`
        (same K, no distortion). Computed once per camera."""
        return _undistort_maps(self)


_UNDISTORT_CRITERIA = (3, 20, 1e-6)  # cv2.TERM_CRITERIA_COUNT | EPS: 20 iterations (fr1's corners need > 5)


@lru_cache(maxsize=8)
def _pixel_rays(cam: PinholeCamera) -> np.ndarray:
    v, u = np.mgrid[0:cam.height, 0:cam.width].astype(np.float32)
    if not cam.distortion:
        rays = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy], axis=-1)
    else:
        xy = cam.undistort_points(np.stack([u.ravel(), v.ravel()], axis=1))
        rays = ((xy - [cam.cx, cam.cy]) / [cam.fx, cam.fy]).reshape(cam.height, cam.width, 2)
    rays = rays.astype(np.float32)
    rays.flags.writeable = False
    return rays


@lru_cache(maxsize=8)
def _undistort_maps(cam: PinholeCamera) -> tuple[np.ndarray, np.ndarray]:
    import cv2

    m1, m2 = cv2.initUndistortRectifyMap(cam.K, np.asarray(cam.distortion), None, cam.K, (cam.width, cam.height),
                                         cv2.CV_32FC1)
    m1.flags.writeable = m2.flags.writeable = False
    return m1, m2


@dataclass(frozen=True)
class Calibration:
    """What a consumer needs to turn a source's frames into geometry.

    `depth_scale` is the number of raw depth units per metre of the source's native depth
    encoding (5000 for TUM, 1000 for 7-Scenes); frames themselves always carry metres.
    """

    camera: PinholeCamera
    baseline: float | None = None  # rectified stereo baseline in metres, None if not stereo
    depth_scale: float = 1000.0

    def __post_init__(self):
        if self.baseline and self.camera.distorted:
            raise ValueError("a stereo calibration is for rectified images: its camera has no distortion")

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
    extras: dict = field(default_factory=dict)  # e.g. synthetic labels / instance ids, TUM "accel" (camera axes, m/s²)

    @property
    def grey(self) -> np.ndarray:
        if self.image.ndim == 2:
            return self.image
        import cv2

        return cv2.cvtColor(self.image, cv2.COLOR_BGR2GRAY)


class DatasetError(Exception):
    """A camera source cannot deliver: missing or corrupt file, unknown layout, bad calibration.
    The message names the offending file or folder."""
