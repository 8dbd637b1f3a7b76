"""Motion blur of a rendered colour image: the average of the views during the exposure.

The frame's pose is the camera's pose at mid-exposure; over the exposure [−e/2, e/2] the
camera moves from `start` to `end`. A pixel p at time s ∈ [−1, 1] (start … end) sees the
scene point that, at mid-exposure, is seen at p + flow(s). The flow at the ends is exact for
rotation and uses the pixel's own (mid-exposure) depth for translation: the pixel is
back-projected at its depth in the start (end) camera and projected into the mid camera.
In between, flow(s) is the parabola through flow(−1), 0 and flow(1), which follows the
curved image-space path of a camera turning and accelerating. The blurred image is the mean
of the sharp render remapped at n evenly spaced s (`cv2.remap`, bilinear), n growing with the
longest flow (one sample per `SAMPLE_STEP_PX` pixels of motion, at most `MAX_SAMPLES`: at
2 px spacing the bilinear samples' tents add up to a flat box, so no ghost edges).
Occlusions are not re-rendered: each sub-view is a warp of the mid-exposure view (at image
borders the nearest pixels repeat).
"""
from __future__ import annotations

import math

import cv2
import numpy as np

FAR = 10.0  # m, depth given to pixels without one (rotation dominates their flow)
SAMPLE_STEP_PX = 2.0  # one sub-view per this many pixels of the longest flow ...
MAX_SAMPLES = 16  # ... up to this many
MIN_BLUR_PX = 0.25  # shorter motion: the image is returned unchanged

_GRIDS: dict = {}


def _grid(camera):
    """Pixel coordinates (u, v) and normalised rays (x, y) of the camera, cached."""
    key = (camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height)
    g = _GRIDS.get(key)
    if g is None:
        if len(_GRIDS) > 8:
            _GRIDS.clear()
        u, v = np.meshgrid(np.arange(camera.width, dtype=np.float32), np.arange(camera.height, dtype=np.float32))
        g = _GRIDS[key] = (u, v, (u - camera.cx) / np.float32(camera.fx), (v - camera.cy) / np.float32(camera.fy))
    return g


def flow_to_mid(depth: np.ndarray, camera, mid: np.ndarray, other: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel, where the point it sees in camera pose `other` (camera-to-world) appears in
    camera pose `mid`, minus the pixel: (du, dv) float32 images. Depth is `depth` (0 = FAR)."""
    u, v, x, y = _grid(camera)
    z = np.where(depth > 0, depth, np.float32(FAR)).astype(np.float32)
    T = np.linalg.inv(mid) @ other  # other camera -> mid camera
    R, t = T[:3, :3].astype(np.float32), T[:3, 3].astype(np.float32)
    # X_mid = R @ (z·[x, y, 1]) + t, written per component on whole images
    X = z * (R[0, 0] * x + R[0, 1] * y + R[0, 2]) + t[0]
    Y = z * (R[1, 0] * x + R[1, 1] * y + R[1, 2]) + t[1]
    Z = z * (R[2, 0] * x + R[2, 1] * y + R[2, 2]) + t[2]
    Z = np.maximum(Z, np.float32(1e-3))
    du = np.float32(camera.fx) * X / Z + np.float32(camera.cx) - u
    dv = np.float32(camera.fy) * Y / Z + np.float32(camera.cy) - v
    return du, dv


def motion_blur(image: np.ndarray, depth: np.ndarray, camera, mid: np.ndarray, start: np.ndarray,
                end: np.ndarray) -> np.ndarray:
    """`image` (rendered at pose `mid`, with `depth`) as seen by a camera that moved from
    pose `start` to pose `end` while its shutter was open (see the module's docstring)."""
    su, sv = flow_to_mid(depth, camera, mid, start)
    eu, ev = flow_to_mid(depth, camera, mid, end)
    extent = float(np.sqrt(np.max((eu - su) ** 2 + (ev - sv) ** 2)))
    if not extent >= MIN_BLUR_PX:
        return image
    n = int(min(MAX_SAMPLES, max(2, math.ceil(extent / SAMPLE_STEP_PX) + 1)))
    u, v, _, _ = _grid(camera)
    a_u, a_v = (eu - su) * np.float32(0.5), (ev - sv) * np.float32(0.5)  # flow(s) = s·a + s²·b
    b_u, b_v = (eu + su) * np.float32(0.5), (ev + sv) * np.float32(0.5)
    acc = np.zeros(image.shape, np.float32)
    for s in np.linspace(-1.0, 1.0, n, dtype=np.float32):  # sub-views, not pixels
        mu = u + s * a_u + (s * s) * b_u
        mv = v + s * a_v + (s * s) * b_v
        cv2.accumulate(cv2.remap(image, mu, mv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE), acc)
    return np.clip(acc * np.float32(1.0 / n) + np.float32(0.5), 0, 255).astype(np.uint8)


def blur_length(depth: np.ndarray, camera, mid: np.ndarray, start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """Length (px) of each pixel's blur streak between the exposure's start and end."""
    su, sv = flow_to_mid(depth, camera, mid, start)
    eu, ev = flow_to_mid(depth, camera, mid, end)
    return np.hypot(eu - su, ev - sv)
