"""Depth registration: a depth image taken by one camera, re-projected into another camera's
pixels (what OpenNI's "depth registration" does inside a Kinect driver).

Sensors such as the Kinect v1 have separate depth (IR) and colour cameras. Datasets recorded
without registration (Microsoft 7-Scenes) deliver depth at the IR camera's pixels, so a colour
keypoint read at the same (u, v) gets the depth of a surface point some pixels away: at 1 m the
7-Scenes depth is ~13 px off its colour, and the colour camera's focal length is 525 px, not
the depth camera's 585. `DepthRegistration.register` forward-projects every valid depth pixel
into the colour image, keeping the nearest surface where several land on one pixel.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..kernel.frames import PinholeCamera


@dataclass(frozen=True)
class DepthRegistration:
    """Maps depth images of `depth_camera` into the pixels of `colour_camera`.

    `T_colour_depth` (4×4) takes points from the depth camera's frame to the colour camera's.
    """

    depth_camera: PinholeCamera
    colour_camera: PinholeCamera
    T_colour_depth: np.ndarray

    def __post_init__(self):
        d = self.depth_camera
        u, v = np.meshgrid(np.arange(d.width, dtype=np.float64), np.arange(d.height, dtype=np.float64))
        rays = np.stack(((u - d.cx) / d.fx, (v - d.cy) / d.fy, np.ones_like(u)))
        # each depth pixel's ray turned into the colour frame: a point at depth z is z·ray + t
        turned = np.einsum("ij,jhw->ihw", self.T_colour_depth[:3, :3], rays).reshape(3, -1)
        object.__setattr__(self, "_rays", turned.astype(np.float32))

    def register(self, depth: np.ndarray) -> np.ndarray:
        """The colour camera's depth image (float32 metres, 0 = no reading) from the depth
        camera's (metres, 0 or non-finite = invalid). Vectorised over the whole image."""
        c = self.colour_camera
        if depth.shape != (self.depth_camera.height, self.depth_camera.width):
            raise ValueError(f"depth image {depth.shape[::-1]} is not the depth camera's "
                             f"{self.depth_camera.width}x{self.depth_camera.height}")
        z = depth.reshape(-1).astype(np.float32, copy=False)
        t = self.T_colour_depth[:3, 3].astype(np.float32)
        X, Y, zc = (self._rays * z + t[:, None])  # whole image: cheaper than gathering valid pixels first
        with np.errstate(divide="ignore", invalid="ignore"):
            uc = np.rint(c.fx * X / zc + c.cx)
            vc = np.rint(c.fy * Y / zc + c.cy)
        inside = np.isfinite(z) & (z > 0) & (zc > 0) & (uc >= 0) & (uc < c.width) & (vc >= 0) & (vc < c.height)
        index = vc[inside].astype(np.intp) * c.width + uc[inside].astype(np.intp)
        out = np.full(c.width * c.height, np.inf, np.float32)
        np.minimum.at(out, index, zc[inside])  # the nearest surface wins
        out[np.isinf(out)] = 0.0
        return out.reshape(c.height, c.width)

    def colour_from_depth_poses(self, poses: np.ndarray) -> np.ndarray:
        """Camera-to-world poses (N×4×4) of the depth camera as those of the colour camera."""
        return poses @ np.linalg.inv(self.T_colour_depth)
