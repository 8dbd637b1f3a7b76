"""Kinect v1 depth noise, modelled where the sensor measures: in disparity (noise="kinect").

A structured-light Kinect measures the disparity d = f·b / z of its projected pattern (IR
focal f ≈ 580 px, baseline b = 7.5 cm) to 1/8 pixel and converts it to depth, so (Khoshelham
& Elberink 2012, "Accuracy and resolution of Kinect depth data"):

* noise: Gaussian in disparity, giving a depth σ that grows with z²; with the quantisation
  below the total is σ_z = `SIGMA_Z2` · z² (1.5 mm at 1 m, 6 mm at 2 m, 13.5 mm at 3 m);
* quantisation: depth comes in disparity steps, Δz = z² / (8·f·b) (2.9 mm at 1 m, 26 mm at 3 m);
* range: no reading nearer than `MIN_RANGE` or farther than `MAX_RANGE`;
* missing pixels: at depth edges (the pattern is lost where the disparity jumps by more than
  `EDGE_DISPARITY_PX` within a pixel's 3×3 neighbourhood, and one pixel around), on surfaces
  seen at more than `MAX_INCIDENCE_DEG` from their normal, in random round blotches about
  `BLOTCH_CELL` pixels across (covering ~`BLOTCH_FRACTION`) and as scattered single pixels
  (`SPECKLE_FRACTION`).

The other noise model (`dataset.add_depth_noise`, noise=True) is the axial model of Nguyen et
al. (σ = 1.2 mm + 1.9 mm·(z − 0.4)², 1 mm steps, random holes).
"""
from __future__ import annotations

import math

import cv2
import numpy as np

IR_FOCAL = 580.0  # px, the Kinect's IR camera (the disparity is measured there, whatever the colour camera)
BASELINE = 0.075  # m, projector to IR camera
FB = IR_FOCAL * BASELINE  # disparity (px) × depth (m)
DISPARITY_STEP = 1.0 / 8.0  # px, the sensor's sub-pixel resolution
SIGMA_Z2 = 1.5e-3  # total depth σ / z² (1/m), quantisation included
MIN_RANGE, MAX_RANGE = 0.45, 5.0  # m
EDGE_DISPARITY_PX = 1.0  # disparity jump within 3×3 that loses the pattern
MAX_INCIDENCE_DEG = 78.0  # more grazing surfaces return nothing
BLOTCH_FRACTION = 0.01  # of the image in random blotches ...
BLOTCH_CELL = 12  # ... about this many pixels across
SPECKLE_FRACTION = 0.005  # scattered single missing pixels


def sigma_z(z) -> np.ndarray:
    """Standard deviation (m) of the Kinect model's depth at depth z (m), quantisation included."""
    return SIGMA_Z2 * np.asarray(z, np.float64) ** 2


def disparity_sigma() -> float:
    """σ (px) of the Gaussian disparity noise: the total SIGMA_Z2·FB less the quantisation's
    share (a uniform step of DISPARITY_STEP has variance step²/12)."""
    return math.sqrt(max((SIGMA_Z2 * FB) ** 2 - DISPARITY_STEP ** 2 / 12.0, 0.0))


def depth_edges(depth: np.ndarray) -> np.ndarray:
    """Pixels within one pixel of a disparity jump of more than EDGE_DISPARITY_PX (bool)."""
    d = np.where(depth > 0, FB / np.maximum(depth, 1e-6), 0.0).astype(np.float32)
    k = np.ones((3, 3), np.uint8)
    jump = (cv2.dilate(d, k) - cv2.erode(d, k)) > EDGE_DISPARITY_PX
    return cv2.dilate(jump.astype(np.uint8), k).astype(bool)


def add_kinect_noise(depth: np.ndarray, cos_incidence: np.ndarray | None, rng: np.random.Generator) -> np.ndarray:
    """The Kinect model's degradation of a clean depth image (metres, 0 = invalid)."""
    z = depth.astype(np.float32)
    h, w = z.shape
    valid = z > 0
    disp = FB / np.where(valid, z, np.float32(1.0))
    disp = disp + rng.standard_normal(z.shape, dtype=np.float32) * np.float32(disparity_sigma())
    disp = np.round(disp / DISPARITY_STEP) * np.float32(DISPARITY_STEP)
    out = (FB / np.maximum(disp, np.float32(DISPARITY_STEP))).astype(np.float32)
    drop = ~valid | (out < MIN_RANGE) | (out > MAX_RANGE) | depth_edges(depth)
    if cos_incidence is not None:
        drop |= cos_incidence < math.cos(math.radians(MAX_INCIDENCE_DEG))
    # blotches: random coarse cells, scaled up smoothly to full size and cut at one half (round blobs)
    cells = (rng.random((max(2, h // BLOTCH_CELL), max(2, w // BLOTCH_CELL)), dtype=np.float32)
             < BLOTCH_FRACTION).astype(np.float32)
    drop |= cv2.resize(cells, (w, h), interpolation=cv2.INTER_LINEAR) > 0.5
    drop |= rng.random(z.shape, dtype=np.float32) < SPECKLE_FRACTION
    out[drop] = 0.0
    return out
