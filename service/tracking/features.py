"""Feature extraction: ORB keypoints spread over the image, each with its 3-D point in the
camera frame when the sensor measured one (depth image for RGB-D, rectified stereo match
for stereo)."""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import cv2
import numpy as np

from mnemoslam.client.kernel.frames import Calibration, Frame

from ..config import FeatureConfig, StereoConfig


@dataclass
class FrameFeatures:
    """Keypoints of one frame. `points` holds camera-frame 3-D coordinates, NaN rows where
    the keypoint has no depth."""

    keypoints: np.ndarray  # (N, 2) float32 pixel coordinates (level 0) of the pinhole K, the lens distortion removed
    descriptors: np.ndarray  # (N, 32) uint8 ORB
    points: np.ndarray  # (N, 3) float32 camera frame, NaN when unknown
    octaves: np.ndarray  # (N,) int8 pyramid level of each keypoint
    depth: np.ndarray | None = None  # the frame's depth image (RGB-D), for dense registration
    grey: np.ndarray | None = None  # the frame's grey image (RGB-D), for dense registration
    depth_sigma: np.ndarray | None = None  # (N,) float32 std. dev. of each point's depth (m), NaN when unknown
    level_scale: float = 1.2  # pyramid scale factor: a keypoint at octave k is known to level_scale**k px
    # (N,) float32 stereo: measured disparity (px, before the offset correction), NaN when none
    disparity: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.keypoints)

    @property
    def has_depth(self) -> np.ndarray:
        return np.isfinite(self.points[:, 2])

    def subset(self, idx) -> FrameFeatures:
        return FrameFeatures(self.keypoints[idx], self.descriptors[idx], self.points[idx], self.octaves[idx],
                             self.depth, self.grey, None if self.depth_sigma is None else self.depth_sigma[idx],
                             self.level_scale, None if self.disparity is None else self.disparity[idx])

    def pixel_sigmas(self) -> np.ndarray:
        """(N,) keypoint position std. dev. in pixels (1 at level 0, growing per octave)."""
        return self.level_scale ** self.octaves.astype(np.float64)

    def depth_sigmas(self, nan: bool = False) -> np.ndarray:
        """(N,) depth standard deviations; where the extractor gave none, 0 (or NaN with `nan`)."""
        if self.depth_sigma is None:
            return np.full(len(self), np.nan if nan else 0.0)
        s = self.depth_sigma.astype(np.float64)
        return s if nan else np.nan_to_num(s, nan=0.0)


def _keypoint_arrays(kps) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions, responses and octaves of cv2.KeyPoints as arrays (the one place we cross
    from OpenCV's keypoint objects to numpy)."""
    n = len(kps)
    xy = np.asarray(cv2.KeyPoint.convert(kps)).reshape(-1, 2) if n else np.zeros((0, 2), np.float32)
    response = np.fromiter((k.response for k in kps), np.float32, n)
    octave = np.fromiter((k.octave for k in kps), np.int8, n)
    return xy, response, octave


class FeatureExtractor:
    """ORB over a grid: each cell keeps its strongest keypoints so features cover the image
    (RTAB-Map's GFTT/ORB with grid cells, ORB-SLAM's octree distribution)."""

    def __init__(self, calibration: Calibration, config: FeatureConfig, stereo: StereoConfig):
        self.calibration = calibration
        self.config = config
        self.stereo = stereo
        c = config
        cam = calibration.camera
        # max_features is for a 640×480 image; larger images (a 1241×376 KITTI frame) get more
        self.max_features = n = round(c.max_features * max(1.0, cam.width * cam.height / (640 * 480)))
        self._orb = cv2.ORB.create(
            nfeatures=n * 2, scaleFactor=c.scale_factor, nlevels=c.levels,
            edgeThreshold=19, patchSize=31, fastThreshold=c.fast_threshold,
        )
        self._orb_low = cv2.ORB.create(
            nfeatures=n * 2, scaleFactor=c.scale_factor, nlevels=c.levels,
            edgeThreshold=19, patchSize=31, fastThreshold=c.min_fast_threshold,
        )
        # px added to every measured disparity (a rectification error: the odometry estimates
        # it online, stereo.self_calibrate, and the pipeline sets it here)
        self.disparity_offset = stereo.disparity_offset

    # -- public -------------------------------------------------------------------------
    def extract(self, frame: Frame) -> FrameFeatures:
        grey = frame.grey
        desc, raw, octave = self._detect(grey)
        # Distortion: the keypoints' coordinates are undistorted (one vectorised call), the
        # depth is read at the raw pixel it is registered to (ORB-SLAM's mvKeysUn).
        xy = self.calibration.camera.undistort_points(raw)
        z_sigma = disparity = None
        if self.calibration.baseline and frame.right is not None:
            points, disparity = self._stereo_points(grey, frame.right, xy, desc, octave)
            # σ_z = z² σ_d / (f b): depth uncertainty of a disparity known to σ_d pixels
            cam = self.calibration.camera
            z_sigma = points[:, 2] ** 2 * np.float32(self.stereo.disparity_sigma / (cam.fx * self.calibration.baseline))
        elif frame.depth is not None:
            points = self._depth_points(frame.depth, raw, xy)
            z_sigma = points[:, 2] ** 2 * np.float32(self.config.depth_noise)
        else:
            points = np.full((len(xy), 3), np.nan, np.float32)
        rgbd = not self.calibration.baseline and frame.depth is not None
        return FrameFeatures(xy, desc, points, octave, frame.depth if rgbd else None, grey if rgbd else None, z_sigma,
                             self.config.scale_factor, disparity)

    # -- detection ----------------------------------------------------------------------
    def _detect(self, grey: np.ndarray):
        # One pass over the image pyramid: every detected keypoint gets its descriptor (the
        # same bits `compute` gives the kept ones alone; the pyramid is then built once, not
        # twice), and the spread keeps the rows of the ones it keeps. A low-texture image's
        # first pass is thrown away with its few descriptors (the TUM cabinet, mostly such
        # images, is no slower than detecting twice and computing once: bench/bench_features.py).
        kps, desc = self._orb.detectAndCompute(grey, None)
        if len(kps) < self.max_features // 2:
            kps, desc = self._orb_low.detectAndCompute(grey, None)  # low-texture image: lower FAST threshold
        if desc is None or not len(kps):
            return np.zeros((0, 32), np.uint8), np.zeros((0, 2), np.float32), np.zeros(0, np.int8)
        xy, response, octave = _keypoint_arrays(kps)  # (xy float32, as OpenCV gives it)
        keep = self._spread(xy, response, grey.shape)
        return desc[keep], xy[keep], octave[keep]

    def _spread(self, xy: np.ndarray, response: np.ndarray, shape) -> np.ndarray:
        """Indices (ascending) of the keypoints kept: the strongest max_features/(rows*cols)
        of every grid cell (cells with fewer donate their quota to the global ranking)."""
        c = self.config
        n = self.max_features
        if len(xy) <= n:
            return np.arange(len(xy))
        h, w = shape[:2]
        cell = (np.minimum((xy[:, 1] * c.grid_rows / h).astype(int), c.grid_rows - 1) * c.grid_cols
                + np.minimum((xy[:, 0] * c.grid_cols / w).astype(int), c.grid_cols - 1))
        order = np.lexsort((-response, cell))  # by cell, strongest first
        cell_sorted = cell[order]
        first = np.searchsorted(cell_sorted, cell_sorted, side="left")
        rank = np.arange(len(order)) - first  # rank inside its cell
        quota = max(1, n // (c.grid_rows * c.grid_cols))
        keep = order[rank < quota]
        if len(keep) < n:  # fill up with the best of the rest
            rest = order[rank >= quota]
            rest = rest[np.argsort(-response[rest], kind="stable")][: n - len(keep)]
            keep = np.concatenate([keep, rest])
        keep.sort()
        return keep

    # -- 3-D from depth -----------------------------------------------------------------
    def _depth_points(self, depth: np.ndarray, raw: np.ndarray, xy: np.ndarray) -> np.ndarray:
        """Back-project keypoints with the depth image: the depth read at the raw pixel `raw`
        (where the image has it), the ray of the undistorted pixel `xy`. A reading is rejected
        when it is missing, outside [min_depth, max_depth], or on a depth edge (3×3 range > 5%
        of z)."""
        cam = self.calibration.camera
        h, w = depth.shape[:2]
        u = np.clip(np.rint(raw[:, 0]).astype(int), 1, w - 2)
        v = np.clip(np.rint(raw[:, 1]).astype(int), 1, h - 2)
        offsets = np.array([-1, 0, 1])
        patch = depth[(v[:, None, None] + offsets[None, :, None]), (u[:, None, None] + offsets[None, None, :])]
        patch = patch.reshape(len(xy), 9).astype(np.float32)
        patch = np.where(np.isfinite(patch) & (patch > 0), patch, np.nan)
        z = patch[:, 4]
        with np.errstate(invalid="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN patches
            spread = np.nanmax(patch, axis=1) - np.nanmin(patch, axis=1) if len(xy) else z
            ok = (z >= self.config.min_depth) & (z <= self.config.max_depth) & (spread <= 0.05 * z)
        z = np.where(ok, z, np.nan)
        x = (xy[:, 0] - cam.cx) / cam.fx * z
        y = (xy[:, 1] - cam.cy) / cam.fy * z
        return np.stack([x, y, z], axis=1).astype(np.float32)

    # -- 3-D from rectified stereo ------------------------------------------------------
    def _stereo_points(self, left, right, xy_l, desc_l, octave_l) -> tuple[np.ndarray, np.ndarray]:
        """Match left keypoints to right keypoints on the same rectified row, refine the
        disparity to sub-pixel with a SAD patch search, correct it by the disparity offset and
        triangulate. Returns the points and the measured (uncorrected) disparities."""
        s = self.stereo
        cam = self.calibration.camera
        baseline = self.calibration.baseline
        assert baseline is not None  # a stereo calibration's (extract's test)
        out = np.full((len(xy_l), 3), np.nan, np.float32)
        measured = np.full(len(xy_l), np.nan, np.float32)
        right = right if right.ndim == 2 else cv2.cvtColor(right, cv2.COLOR_BGR2GRAY)
        kps_r, desc_r = self._orb_low.detectAndCompute(right, None)  # (one pass over the pyramid)
        if desc_r is None or not len(kps_r) or not len(xy_l):
            return out, measured
        xy_r, _, _ = _keypoint_arrays(kps_r)
        # Candidate pairs on the same rectified row (within the keypoint level's tolerance)
        # and in the disparity range, then the nearest right descriptor of each left keypoint.
        # coarser levels, coarser rows
        row_tol = s.max_row_diff * self.config.scale_factor ** octave_l.astype(np.float32)
        li, ri = _row_candidates(xy_l, xy_r, row_tol)
        disp = xy_l[li, 0] - xy_r[ri, 0]
        keep = (disp >= s.min_disparity) & (disp <= s.max_disparity * cam.width)
        li, ri = li[keep], ri[keep]
        i, j, dist = _nearest_per_left(li, ri, _hamming_pairs(desc_l, desc_r, li, ri), len(xy_r))
        ok = dist <= s.max_hamming
        i, j = i[ok], j[ok]
        d = xy_l[i, 0] - xy_r[j, 0]
        d = _refine_disparity(left, right, xy_l[i], d)
        d_true = d + self.disparity_offset
        with np.errstate(invalid="ignore"):
            good = d_true >= s.min_disparity  # (NaN: no SAD minimum inside the search range)
        i, d, d_true = i[good], d[good], d_true[good]
        z = cam.fx * baseline / d_true
        keep = z <= s.max_depth
        i, z, d = i[keep], z[keep], d[keep]
        out[i, 0] = (xy_l[i, 0] - cam.cx) / cam.fx * z
        out[i, 1] = (xy_l[i, 1] - cam.cy) / cam.fy * z
        out[i, 2] = z
        measured[i] = d
        return out, measured


def _row_candidates(xy_l: np.ndarray, xy_r: np.ndarray, row_tol: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """All (left, right) index pairs whose rows differ by at most the left keypoint's
    tolerance: a band of the right keypoints sorted by row per left keypoint."""
    order = np.argsort(xy_r[:, 1], kind="stable")
    y = xy_r[order, 1]
    lo = np.searchsorted(y, xy_l[:, 1] - row_tol - 1e-3, "left")  # widened, then the exact test
    hi = np.searchsorted(y, xy_l[:, 1] + row_tol + 1e-3, "right")
    count = hi - lo
    li = np.repeat(np.arange(len(xy_l)), count)
    ri = order[np.repeat(lo - (np.cumsum(count) - count), count) + np.arange(count.sum())]
    exact = np.abs(xy_l[li, 1] - xy_r[ri, 1]) <= row_tol[li]
    return li[exact], ri[exact]  # li ascending


def _hamming_pairs(a: np.ndarray, b: np.ndarray, ia: np.ndarray, ib: np.ndarray) -> np.ndarray:
    """Hamming distances (n,) int between the 256-bit descriptors a[ia] and b[ib]."""
    au = np.ascontiguousarray(a).view(np.uint64)
    bu = np.ascontiguousarray(b).view(np.uint64)
    return np.bitwise_count(au[ia] ^ bu[ib]).sum(axis=1, dtype=np.int64)


def _nearest_per_left(li: np.ndarray, ri: np.ndarray, dist: np.ndarray, n_right: int):
    """For each left index of the pairs (`li` ascending): the right index at the smallest
    distance (ties: the smallest right index) and that distance."""
    if not len(li):
        return li, ri, dist
    starts = np.flatnonzero(np.r_[True, li[1:] != li[:-1]])
    best = np.minimum.reduceat(dist * n_right + ri, starts)  # distance first, then right index
    return li[starts], best % n_right, best // n_right


def _refine_disparity(left, right, xy, disp, half=5, search=4) -> np.ndarray:
    """Sub-pixel disparity: SAD of (2·half+1)² patches at disparity d-search..d+search on
    the same row, then a parabola through the best cost and its neighbours."""
    h, w = left.shape[:2]
    n = len(xy)
    if n == 0:
        return disp
    x = np.rint(xy[:, 0]).astype(int)
    y = np.rint(xy[:, 1]).astype(int)
    d0 = np.rint(disp).astype(int)
    r = np.arange(-half, half + 1)
    shifts = np.arange(-search, search + 1)
    inside = (y - half >= 0) & (y + half < h) & (x - half >= 0) & (x + half < w) \
        & (x - d0 - search - half >= 0) & (x - d0 + search + half < w)
    rows = np.clip(y[:, None] + r[None, :], 0, h - 1)  # (n, P)
    cols_l = np.clip(x[:, None] + r[None, :], 0, w - 1)
    pl = left[rows[:, :, None], cols_l[:, None, :]].astype(np.int16)  # (n, P, P)
    pl = pl - pl.mean(axis=(1, 2), keepdims=True).astype(np.int16)
    cols_r = np.clip(x[:, None, None] - d0[:, None, None] - shifts[None, :, None] + r[None, None, :],
                     0, w - 1)  # (n, S, P)
    pr = right[rows[:, None, :, None], cols_r[:, :, None, :]].astype(np.int16)  # (n, S, P, P)
    pr = pr - pr.mean(axis=(2, 3), keepdims=True).astype(np.int16)
    cost = np.abs(pl[:, None] - pr).sum(axis=(2, 3)).astype(np.float64)  # (n, S)
    k = np.argmin(cost, axis=1)
    interior = (k > 0) & (k < len(shifts) - 1)
    kc = np.clip(k, 1, len(shifts) - 2)
    c0, c1, c2 = (cost[np.arange(n), kc + o] for o in (-1, 0, 1))
    denom = c0 - 2 * c1 + c2
    with np.errstate(divide="ignore", invalid="ignore"):
        frac = np.where(interior & (denom > 0), 0.5 * (c0 - c2) / denom, 0.0)
    refined = d0 + shifts[k] + np.clip(frac, -0.5, 0.5)
    # Outside the image: keep the keypoint disparity; a minimum on the search border: NaN (no match).
    return np.where(inside & interior, refined, np.where(inside, np.nan, disp)).astype(np.float64)
