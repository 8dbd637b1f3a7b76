"""Depth registration (client/datasets/registration.py): depth of one camera re-projected into
another's pixels, checked against geometry computed in closed form, and on 7-Scenes, whose
depth is not registered to its colour."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from mnemoslam.client.datasets import open_dataset
from mnemoslam.client.datasets.registration import DepthRegistration
from mnemoslam.client.kernel.frames import PinholeCamera

from conftest import require

DEPTH = PinholeCamera(585.0, 585.0, 320.0, 240.0, 640, 480)
COLOUR = PinholeCamera(525.0, 525.0, 319.5, 239.5, 640, 480)


def rays(cam: PinholeCamera) -> np.ndarray:
    u, v = np.meshgrid(np.arange(cam.width, dtype=float), np.arange(cam.height, dtype=float))
    return np.stack(((u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u)), axis=-1)


def plane_depth(cam: PinholeCamera, n: np.ndarray, d: float) -> np.ndarray:
    """Depth image of the plane n·X = d seen by `cam` (X in its frame)."""
    r = rays(cam)
    return (d / (r @ n)).astype(np.float32)


def extrinsic(rx_deg: float, ry_deg: float, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.radians([rx_deg, ry_deg, 0.0]))[0]
    T[:3, 3] = t
    return T


def test_a_slanted_plane_gets_the_colour_cameras_depth():
    T_cd = extrinsic(1.0, -2.0, [-0.025, 0.004, 0.002])
    n_d = np.array([0.2, -0.1, 1.0]) / np.linalg.norm([0.2, -0.1, 1.0])
    d_d = 1.8
    depth = plane_depth(DEPTH, n_d, d_d)
    registered = DepthRegistration(DEPTH, COLOUR, T_cd).register(depth)
    # the same plane in the colour frame: n_c = R n_d, d_c = d_d + n_c·t
    n_c = T_cd[:3, :3] @ n_d
    truth = plane_depth(COLOUR, n_c, d_d + n_c @ T_cd[:3, 3])
    got = registered > 0
    assert got.mean() > 0.75  # the colour camera sees wider: (525 / 585)² = 0.80 of it has depth
    kernel = np.ones((5, 5), np.uint8)
    closed = cv2.morphologyEx(got.astype(np.uint8), cv2.MORPH_CLOSE, kernel)
    interior = cv2.erode(closed, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0) > 0
    assert interior.mean() > 0.7 and got[interior].all()  # no holes: depth pixels are denser than colour ones
    # a pixel gets a point within half a pixel of its centre: relative depth within the slope's share
    np.testing.assert_allclose(registered[got], truth[got], rtol=2e-3)


def test_the_nearest_surface_wins_and_occluded_pixels_stay_empty():
    T_cd = extrinsic(0, 0, [-0.025, 0, 0])
    depth = np.full((480, 640), 3.0, np.float32)
    depth[200:280, 280:360] = 1.0  # a box 1 m away in front of a wall at 3 m
    depth[:, :10] = 0.0  # invalid readings stay invalid
    depth[0, 20] = np.nan
    reg = DepthRegistration(DEPTH, COLOUR, T_cd)
    out = reg.register(depth)
    # the box's centre column in the colour image: u = cx + f (X - 0.025) / z
    X = (320 - DEPTH.cx) / DEPTH.fx * 1.0
    u = int(round(COLOUR.cx + COLOUR.fx * (X - 0.025) / 1.0))
    v = int(round(COLOUR.cy + COLOUR.fy * ((240 - DEPTH.cy) / DEPTH.fy)))
    assert out[v, u] == pytest.approx(1.0)
    assert np.isclose(out, 1.0).sum() == pytest.approx(80 * 80 * (525 / 585) ** 2, rel=0.05)
    # beside the box, on the side the colour camera sees behind it, the wall is hidden from
    # the depth camera: no reading there, rather than the box's or the wall's guessed depth
    right_edge = int(round(COLOUR.cx + COLOUR.fx * ((359 - DEPTH.cx) / DEPTH.fx - 0.025 / 1.0)))
    assert out[v, right_edge + 1: right_edge + 4].max() == 0.0
    assert np.isfinite(out).all() and out.dtype == np.float32
    with pytest.raises(ValueError, match="depth camera"):
        reg.register(depth[:100])


def edge_distance(frames) -> float:
    """Mean distance (px, capped at 10) from the near side of depth discontinuities to the
    colour image's Canny edges: small when depth is registered to colour."""
    total, count = 0.0, 0
    for f in frames:
        edges = cv2.Canny(cv2.GaussianBlur(f.grey, (5, 5), 1.2), 40, 100)
        dist = cv2.distanceTransform((edges == 0).astype(np.uint8), cv2.DIST_L2, 3)
        d = f.depth
        jump = (np.abs(np.diff(d, axis=1)) > 0.1 * np.minimum(d[:, 1:], d[:, :-1])) & (d[:, 1:] > 0) & (d[:, :-1] > 0)
        y, x = np.nonzero(jump)
        x = np.where(d[y, x] < d[y, x + 1], x, x + 1)  # the nearer side is the object's edge
        total += np.minimum(dist[y, x], 10).sum()
        count += len(x)
    return total / count


@pytest.mark.data
def test_7scenes_registered_depth_edges_meet_the_colour_edges(data_dir):
    """Measured 2026-11-26 on every 100th frame: 5.42 px raw, 2.88 px registered with the nominal
    Kinect v1 colour camera (over 20 frames: 5.6 raw, 3.4 registered, 3.3 with the best fit)."""
    path = require(data_dir / "7scenes_redkitchen")
    raw, reg = open_dataset(path, register=False), open_dataset(path)
    picks = range(0, 1000, 100)
    before = edge_distance(raw.frame(i) for i in picks)
    after = edge_distance(reg.frame(i) for i in picks)
    print(f"depth edges to colour edges: raw {before:.2f} px, registered {after:.2f} px")
    assert after < 0.75 * before
