"""Visual odometry: frame-to-local-map tracking with PnP + RANSAC.

The local map holds the 3-D points (world frame) of recent keyframes with their latest ORB
descriptor. Each frame is matched against the map points that project into the image,
predicted by a constant-velocity motion model; PnP + RANSAC estimates the pose, a
Levenberg–Marquardt refinement on the inliers polishes it. When the gated match fails, the
frame is matched again without the prediction (wide baselines, sudden motion); when that
fails too, the frame is lost. After `lost_frames_reset` lost frames in a row a new segment
starts from the last known pose.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import cv2
import numpy as np

from mnemoslam.client.kernel.frames import PinholeCamera
from mnemoslam.client.kernel.geometry import invert, make_pose, rotation_angle

from ..config import OdometryConfig, StereoConfig
from . import icp
from .features import FrameFeatures
from .matching import match_descriptors, match_map_points, match_map_points_tiled, one_per_query
from .refinement import mahalanobis2, offset_information, refine_pose, sigma_from_hessian
from .stereo_calibration import DisparityOffsetEstimator
from .window_ba import KeyframeRecord, WindowBA

RANSAC_MIN_SAMPLE = 40  # `odometry.pnp_ransac_max_sigma`: fewer fine matches than this: RANSAC sees all


def _within(predicted: np.ndarray, keypoints: np.ndarray, radius: float) -> np.ndarray:
    """Which matches keep their keypoint within `radius` px of where the motion model
    projects their map point (the gated search's check)."""
    return np.linalg.norm(predicted - keypoints, axis=1) <= radius


class _DepthReference:
    """A frame's depth (and grey) image, its pyramid built once on first use: for the frame
    being registered and, when that frame updates the map, as the next reference."""

    def __init__(self, depth: np.ndarray, grey: np.ndarray | None):
        self.pose: np.ndarray | None = None
        self.depth, self.grey = depth, grey
        self._levels: list[icp.DepthLevel] | None = None

    def levels(self, camera: PinholeCamera) -> list[icp.DepthLevel]:
        if self._levels is None:
            self._levels = icp.depth_pyramid(self.depth, camera, icp.STEPS, grey=self.grey)
        return self._levels


@dataclass
class TrackResult:
    """The outcome of tracking one frame."""

    status: str  # "init" (first frame of a segment), "ok", or "lost"
    pose: np.ndarray | None  # camera-to-world, None when lost
    inliers: int = 0
    matches: int = 0
    segment: int = 0
    map_index: np.ndarray | None = None  # per frame feature: matched local-map point or -1
    inlier_mask: np.ndarray | None = None  # per frame feature: PnP inlier
    # per frame feature: stable id of the local-map point it is (inlier or new point), or -1
    point_ids: np.ndarray | None = None

    @property
    def tracked(self) -> bool:
        return self.status != "lost"


# every per-point array of LocalMap (and of its archive), in one place
_POINT_FIELDS = ("points", "descriptors", "observations", "last_seen", "rays", "sigma", "origins", "disparity",
                 "cos0", "ids", "info", "info_x", "fused", "returned")


class PointArchive:
    """Points trimmed from the local map, with everything the map keeps per point, at most
    `capacity` of them (the least recently seen go first): `odometry.map_reuse`. The points
    live in rows of preallocated arrays, in the order they came (a point brought back leaves a
    dead row, compacted away when the dead outnumber the living), so that archiving and
    bringing back cost what moves, not the whole archive."""

    def __init__(self, capacity: int):
        self.capacity = capacity
        self._rows: dict[str, np.ndarray] | None = None  # every field's rows, the first `_used` of them written
        self._alive = np.zeros(0, bool)
        self._used = 0
        self._count = 0  # living rows

    def __len__(self) -> int:
        return self._count

    @property
    def arrays(self) -> dict[str, np.ndarray] | None:
        """The written rows of every field (living or not: the indices `in_view` gives)."""
        if self._rows is None:
            return None
        return {f: v[: self._used] for f, v in self._rows.items()}

    def add(self, arrays: dict[str, np.ndarray]) -> None:
        k = len(arrays["ids"])
        if self._rows is None:
            self._rows = {f: np.empty((max(2 * k, 1024),) + v.shape[1:], v.dtype) for f, v in arrays.items()}
            self._alive = np.zeros(len(self._rows["ids"]), bool)
        if self._used + k > len(self._alive):
            self._compact()
            if self._used + k > len(self._alive):
                size = max(2 * len(self._alive), self._used + k)
                for f, v in self._rows.items():
                    grown = np.empty((size,) + v.shape[1:], v.dtype)
                    grown[: self._used] = v[: self._used]
                    self._rows[f] = grown
                alive = np.zeros(size, bool)
                alive[: self._used] = self._alive[: self._used]
                self._alive = alive
        for f, v in arrays.items():
            self._rows[f][self._used: self._used + k] = v
        self._alive[self._used: self._used + k] = True
        self._used += k
        self._count += k
        if self._count > self.capacity:  # the least recently seen go (ties: the oldest row)
            self._compact()
            keep = np.sort(np.argsort(-self._rows["last_seen"][: self._used], kind="stable")[: self.capacity])
            self._keep_rows(keep)

    def pop(self, idx: np.ndarray) -> dict[str, np.ndarray]:
        """Remove the living rows `idx` and return their arrays."""
        assert self._rows is not None
        out = {f: v[idx] for f, v in self._rows.items()}
        self._alive[idx] = False
        self._count -= len(idx)
        if self._used - self._count > max(self._count, 1024):
            self._compact()
        return out

    def _compact(self) -> None:
        if self._count < self._used:
            self._keep_rows(np.nonzero(self._alive[: self._used])[0])

    def _keep_rows(self, keep: np.ndarray) -> None:
        assert self._rows is not None
        for v in self._rows.values():
            v[: len(keep)] = v[keep]
        self._alive[:] = False
        self._alive[: len(keep)] = True
        self._used = self._count = len(keep)

    def in_view(self, pose: np.ndarray, camera: PinholeCamera, distance_ratio: float,
                max_angle_deg: float) -> np.ndarray:
        """Indices of the archived points a camera at `pose` (camera-to-world) sees, as ORB-SLAM's
        `isInFrustum`: in front of it, projecting inside the image, at a distance within
        [1/distance_ratio, distance_ratio] × that of their first sighting, and seen within
        `max_angle_deg` of their first sighting's viewing direction."""
        a = self.arrays
        if a is None:
            return np.zeros(0, int)
        X = a["points"]
        T_cw = invert(pose)
        pc = X @ T_cw[:3, :3].T + T_cw[:3, 3]
        z = pc[:, 2]
        front = z > 0.05
        zs = np.where(front, z, 1.0)
        u = pc[:, 0] / zs * camera.fx + camera.cx
        v = pc[:, 1] / zs * camera.fy + camera.cy
        view = X - pose[:3, 3]
        dist = np.linalg.norm(view, axis=1)
        first = np.linalg.norm(X - a["origins"], axis=1)
        cos = np.einsum("ij,ij->i", view, X - a["origins"]) / np.maximum(dist * first, 1e-12)
        ok = (front & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
              & (dist >= first / distance_ratio) & (dist <= first * distance_ratio)
              & (cos >= np.cos(np.radians(max_angle_deg))) & self._alive[: self._used])
        return np.nonzero(ok)[0]


class LocalMap:
    """A bounded set of world points with descriptors, refreshed by keyframes."""

    def __init__(self, capacity: int, focal: float = 525.0, archive: int = 0, archive_min_observations: int = 1):
        self.capacity = capacity
        self.archive_capacity = archive
        self.archive_min_observations = archive_min_observations
        self.focal = focal  # px: a pixel σ across a reading's ray is z·σ/focal metres
        self.points = np.zeros((0, 3), np.float64)
        self.descriptors = np.zeros((0, 32), np.uint8)
        self.observations = np.zeros(0, np.int32)
        self.last_seen = np.zeros(0, np.int64)
        self.rays = np.zeros((0, 3), np.float64)  # unit world direction of the first sighting ...
        self.sigma = np.zeros(0, np.float64)  # ... along which the point is uncertain by this (m)
        self.origins = np.zeros((0, 3), np.float64)  # camera centre of the first sighting
        self.disparity = np.zeros(0, np.float64)  # stereo: disparity measured at the first sighting (NaN: none)
        self.cos0 = np.zeros(0, np.float64)  # cosine between the first ray and that camera's optical axis
        # stable point ids (indices shift when points are trimmed): the map update's point tracks
        self.ids = np.zeros(0, np.int64)
        # `fuse`: each point's information (3×3, world) and information × position summed over its
        # depth readings; NaN rows for points never fused (stereo points, fusion off)
        self.info = np.zeros((0, 3, 3), np.float64)
        self.info_x = np.zeros((0, 3), np.float64)
        self.fused = np.zeros(0, np.int32)  # depth readings fused into the point after its first
        self.returned = np.zeros(0, bool)  # `map_reuse`: the point came back from the archive
        self._next_id = 0
        # `odometry.map_reuse`: the points trimmed from the map, brought back when in view again
        self.archive: PointArchive | None = PointArchive(archive) if archive > 0 else None

    def __len__(self) -> int:
        return len(self.points)

    @property
    def next_id(self) -> int:
        """The id the next new point gets (ids are never reused)."""
        return self._next_id

    def clear(self) -> None:
        next_id = self._next_id  # ids stay unique over segments
        LocalMap.__init__(self, self.capacity, self.focal, self.archive_capacity, self.archive_min_observations)
        self._next_id = next_id

    def update(self, stamp_id: int, features: FrameFeatures, pose: np.ndarray, map_index: np.ndarray) -> np.ndarray:
        """Insert a tracked frame: features matched to a map point refresh its descriptor
        (the point keeps its first position: later observations come from poses that have
        drifted more, and averaging them in moves the map with the drift; `fuse` does so
        under `odometry.map_point_fusion`, off by default); unmatched
        features with depth become new points; the least recently seen points beyond
        capacity are dropped. Returns each feature's stable point id (the matched point's, the
        new point's, or -1)."""
        ids = np.where(map_index >= 0, self.ids[np.maximum(map_index, 0)] if len(self.ids) else -1, -1)
        has_depth = features.has_depth
        world = features.points.astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]
        matched = (map_index >= 0) & has_depth
        idx = map_index[matched]
        if len(idx):
            self.descriptors[idx] = features.descriptors[matched]
            self.observations[idx] += 1
            self.last_seen[idx] = stamp_id
        seen_only = (map_index >= 0) & ~has_depth
        self.last_seen[map_index[seen_only]] = stamp_id
        new = (map_index < 0) & has_depth
        n_new = int(new.sum())
        ids[new] = np.arange(self._next_id, self._next_id + n_new)
        self.ids = np.concatenate([self.ids, ids[new]])
        self._next_id += n_new
        rays = world[new] - pose[:3, 3]
        rays /= np.maximum(np.linalg.norm(rays, axis=1, keepdims=True), 1e-12)
        self.points = np.concatenate([self.points, world[new]])
        self.descriptors = np.concatenate([self.descriptors, features.descriptors[new]])
        self.observations = np.concatenate([self.observations, np.ones(n_new, np.int32)])
        self.last_seen = np.concatenate([self.last_seen, np.full(n_new, stamp_id, np.int64)])
        self.rays = np.concatenate([self.rays, rays])
        self.sigma = np.concatenate([self.sigma, features.depth_sigmas()[new]])
        self.origins = np.concatenate([self.origins, np.broadcast_to(pose[:3, 3], (n_new, 3))])
        info = _reading_information(features.points[new].astype(np.float64), features.pixel_sigmas()[new],
                                    features.depth_sigmas()[new], pose, self.focal)
        self.info = np.concatenate([self.info, info])
        self.info_x = np.concatenate([self.info_x, np.einsum("nij,nj->ni", info, world[new])])
        self.fused = np.concatenate([self.fused, np.zeros(n_new, np.int32)])
        self.returned = np.concatenate([self.returned, np.zeros(n_new, bool)])
        if features.disparity is None:
            self.disparity = np.concatenate([self.disparity, np.full(n_new, np.nan)])
            self.cos0 = np.concatenate([self.cos0, np.full(n_new, np.nan)])
        else:
            p = features.points[new].astype(np.float64)
            self.disparity = np.concatenate([self.disparity, features.disparity[new].astype(np.float64)])
            self.cos0 = np.concatenate([self.cos0, p[:, 2] / np.maximum(np.linalg.norm(p, axis=1), 1e-12)])
        self._trim()
        return ids

    def place_stereo_points(self, offset: float, fb: float, disparity_sigma: float) -> None:
        """Move every point triangulated by stereo along its first ray to the depth its
        measured disparity gives with the disparity offset `offset` (px), so the map agrees
        with the frames the extractor triangulates with that offset."""
        stereo = np.isfinite(self.disparity)
        d = self.disparity[stereo] + offset
        ok = d > 0
        idx = np.nonzero(stereo)[0][ok]
        z = fb / d[ok]
        self.points[idx] = self.origins[idx] + (z / self.cos0[idx])[:, None] * self.rays[idx]
        self.sigma[idx] = z ** 2 * (disparity_sigma / fb)

    def _trim(self) -> None:
        if len(self.points) > self.capacity:
            keep = np.sort(np.argsort(-self.last_seen, kind="stable")[: self.capacity])
            if self.archive is not None:  # the points observed often enough go to the archive
                kept = self.observations >= self.archive_min_observations
                kept[keep] = False
                self.archive.add(self._take(np.nonzero(kept)[0]))
            self._select(keep)

    def _take(self, idx: np.ndarray) -> dict[str, np.ndarray]:
        """The per-point arrays of points `idx` (copies)."""
        return {f: getattr(self, f)[idx] for f in _POINT_FIELDS}

    def _select(self, keep: np.ndarray) -> None:
        for f in _POINT_FIELDS:
            setattr(self, f, getattr(self, f)[keep])

    def remove(self, idx: np.ndarray, map_index: np.ndarray) -> np.ndarray:
        """Remove points `idx` (not archived); returns `map_index` (points' indices, -1 for
        none, none of them removed) under the new indexing."""
        keep = np.ones(len(self.points), bool)
        keep[idx] = False
        self._select(np.nonzero(keep)[0])
        new = np.cumsum(keep) - 1
        return np.where(map_index >= 0, new[np.maximum(map_index, 0)], -1)

    def readmit(self, pose: np.ndarray, camera: PinholeCamera, stamp_id: int, distance_ratio: float,
                max_angle_deg: float, max_points: int = 0) -> int:
        """Bring the archived points that the camera at `pose` would see back into the local map
        (`odometry.map_reuse`), as seen at map update `stamp_id`, up to `max_points` in the map
        (0: no bound; those observed most, then the oldest, first); the map keeps its points in
        the order of their ids. Returns how many came back."""
        if self.archive is None or not len(self.archive):
            return 0
        idx = self.archive.in_view(pose, camera, distance_ratio, max_angle_deg)
        if max_points > 0 and len(self) + len(idx) > max_points:
            assert self.archive.arrays is not None
            a = self.archive.arrays
            room = max(max_points - len(self), 0)
            idx = np.sort(idx[np.lexsort((a["ids"][idx], -a["observations"][idx]))[:room]])
        if not len(idx):
            return 0
        back = self.archive.pop(idx)
        back["last_seen"][:] = stamp_id
        back["returned"][:] = True
        merged = {f: np.concatenate([getattr(self, f), back[f]]) for f in _POINT_FIELDS}
        order = np.argsort(merged["ids"], kind="stable")
        for f in _POINT_FIELDS:
            setattr(self, f, merged[f][order])
        return int(len(idx))

    def fuse(self, features: FrameFeatures, pose: np.ndarray, map_index: np.ndarray, gate: float,
             max_readings: int) -> int:
        """Refine the points from this tracked frame's depth readings (`map_index`: each
        feature's inlier map point or -1): each reading is a 3-D point at the frame's pose,
        uncertain by the depth σ along its ray and by the pixel σ across it, and a point's
        position becomes the information-weighted mean of its readings (a structure-only
        bundle adjustment with the frames' poses fixed: ORB-SLAM refines its local map's points
        over many views, where each of ours had its first reading alone). A reading farther
        than `gate` (Mahalanobis) from the point is left out (a depth edge, a misregistered
        depth), and so is any beyond `max_readings` per point. Stereo points (re-placed by the
        disparity offset) are left alone. Returns the readings fused."""
        q = np.nonzero((map_index >= 0) & features.has_depth)[0]
        if not len(q) or features.disparity is not None:
            return 0
        m = map_index[q]
        keep = self.fused[m] < max_readings
        q, m = q[keep], m[keep]
        p = features.points[q].astype(np.float64)
        world = p @ pose[:3, :3].T + pose[:3, 3]
        info = _reading_information(p, features.pixel_sigmas()[q], features.depth_sigmas()[q], pose, self.focal)
        A, X = self.info[m], self.points[m]
        # gate on the difference's covariance (the point's plus the reading's)
        cov = np.linalg.inv(A) + np.linalg.inv(info)
        d = world - X
        chi2 = np.einsum("ni,ni->n", d, np.linalg.solve(cov, d[:, :, None])[:, :, 0])
        ok = np.isfinite(chi2) & (chi2 <= gate ** 2)
        m, info, world = m[ok], info[ok], world[ok]
        if not len(m):
            return 0
        np.add.at(self.info, m, info)
        np.add.at(self.info_x, m, np.einsum("nij,nj->ni", info, world))
        np.add.at(self.fused, m, 1)
        u = np.unique(m)
        cov = np.linalg.inv(self.info[u])
        self.points[u] = np.einsum("nij,nj->ni", cov, self.info_x[u])
        # the pose refinement's model of a point's uncertainty: its largest axis
        w, v = np.linalg.eigh(cov)
        self.rays[u] = v[:, :, 2]
        self.sigma[u] = np.sqrt(np.maximum(w[:, 2], 0.0))
        return int(len(m))


class Odometry:
    """Tracks frames against a local map; owns the motion model and the segment counter."""

    def __init__(self, camera: PinholeCamera, config: OdometryConfig, seed: int = 0,
                 stereo: StereoConfig | None = None, baseline: float | None = None):
        self.camera = camera
        self.config = config
        self.K = camera.K
        self.map = LocalMap(config.local_map_size, camera.fx, config.map_reuse_archive if config.map_reuse else 0,
                            config.map_reuse_min_observations)
        self.pose: np.ndarray | None = None  # last tracked pose
        self.velocity = np.eye(4)  # last inter-frame motion, camera frame
        self.last_stamp: float | None = None
        self.segment = 0
        self.lost_in_row = 0
        self._last_dt: float | None = None
        self._reference: _DepthReference | None = None
        self._pending_reference: _DepthReference | None = None
        self._updates = 0
        self._map_pose = np.eye(4)
        self._map_inliers = 0
        self._seed = seed
        # stereo: online estimate of the disparity offset (the pipeline hands it to the extractor)
        self.calibration = DisparityOffsetEstimator(stereo, camera.fx * baseline) \
            if stereo is not None and stereo.self_calibrate and baseline else None
        # RGB-D: windowed BA of the map updates' poses and points (ORB-SLAM's local mapping)
        self.window_ba = WindowBA(self.K, config.window_ba_size, config.window_ba_fixed, config.window_ba_every,
                                  config.window_ba_iterations, config.window_ba_history,
                                  config.window_ba_points, config.window_ba_hold) \
            if config.window_ba and not baseline else None

    @property
    def disparity_offset(self) -> float | None:
        """The current estimate of the stereo disparity offset (px), None when not estimated."""
        return None if self.calibration is None else self.calibration.offset

    # -- tracking -----------------------------------------------------------------------
    def track(self, features: FrameFeatures, stamp: float, depth_stamp: float | None = None) -> TrackResult:
        if (depth_stamp is not None and self.config.depth_time_compensation and features.depth is not None
                and self.pose is not None and self._last_dt and abs(depth_stamp - stamp) > 1e-4):
            # the depth camera where the motion model puts it at the depth image's stamp
            motion = _scale_motion(self.velocity, (depth_stamp - stamp) / self._last_dt)
            features = compensate_depth_time(features, self.camera, motion)
            features = grow_depth_sigma(features, motion, self.config.depth_time_sigma)
        if self.pose is None or len(self.map) == 0:
            return self._start_segment(features, stamp)
        predicted = self._predict(stamp)
        c = self.config
        if c.map_reuse and c.map_reuse_each_frame:  # archived points in the predicted view come back
            self.map.readmit(predicted, self.camera, self._updates, c.map_reuse_distance_ratio, c.map_reuse_angle,
                             c.map_reuse_points)
        result = self._register(features, predicted, gated=True) if c.motion_model else None
        if _support(result) < c.confident_inliers:  # wide baseline or bad prediction: search everywhere
            result = max(result, self._register(features, predicted, gated=False), key=_support)
        if c.icp_fallback and not self._confident(result):  # few features or a weak pose: use the depth
            result = self._register_depth(features, predicted if result is None else result[0]) or result
        if result is None:
            self.lost_in_row += 1
            if (self.lost_in_row >= self.config.lost_frames_reset
                    and features.has_depth.sum() >= self.config.min_inliers):
                return self._start_segment(features, stamp, new_segment=True)
            return TrackResult("lost", None, segment=self.segment, map_index=np.full(len(features), -1))
        pose, map_index, inliers = result[:3]
        if len(result) > 4 and len(result[4]):  # `map_reuse_replace`: duplicates of older points leave the map
            map_index = self.map.remove(result[4], map_index)
        offset = self.disparity_offset
        if self.calibration is not None and features.disparity is not None:
            self._calibrate(features, pose, np.where(inliers, map_index, -1))
        inlier_index = np.where(inliers, map_index, -1)
        point_ids = np.where(inlier_index >= 0, self.map.ids[np.maximum(inlier_index, 0)], -1)
        updated = self._needs_map_update(pose, int(inliers.sum()))
        if updated:
            if self.config.map_point_fusion:
                self.map.fuse(features, pose, inlier_index, self.config.fusion_gate, self.config.fusion_readings)
            point_ids = self._update_map(features, pose, inlier_index, int(inliers.sum()))
            if self.config.map_reuse and not self.config.map_reuse_each_frame:
                self.map.readmit(pose, self.camera, self._updates, self.config.map_reuse_distance_ratio,
                                 self.config.map_reuse_angle, self.config.map_reuse_points)

        cal = self.calibration
        if cal is not None and cal.offset != offset:  # the map follows the new estimate (the frames will)
            self.map.place_stereo_points(cal.offset, cal.fb, cal.config.disparity_sigma)
        self.velocity = invert(self.pose) @ pose  # motion over the last interval ...
        self._last_dt = self._dt(stamp)  # ... of this length, rescaled in _predict
        if updated and self.window_ba is not None and self.window_ba.due():
            pose = self._adjust_window(pose)
        self.pose, self.last_stamp, self.lost_in_row = pose, stamp, 0
        return TrackResult("ok", pose, int(inliers.sum()), int((map_index >= 0).sum()), self.segment, map_index,
                           inliers, point_ids)

    def _confident(self, result) -> bool:
        """A PnP pose the depth cannot improve: enough inliers and, where its σ was estimated
        (RGB-D), a σ within confident_sigma_* (few inliers bunched in one part of the image
        can pass the count and still leave the pose 2° off)."""
        c = self.config
        if _support(result) < c.confident_inliers:
            return False
        sigma = result[3]
        return sigma is None or (np.degrees(sigma[0]) <= c.confident_sigma_rotation
                                 and sigma[1] <= c.confident_sigma_translation)

    def _needs_map_update(self, pose: np.ndarray, inliers: int) -> bool:
        c = self.config
        delta = invert(self._map_pose) @ pose
        return bool(np.linalg.norm(delta[:3, 3]) >= c.map_update_linear
                    or rotation_angle(delta[:3, :3]) >= c.map_update_angular
                    or inliers < c.map_update_ratio * self._map_inliers)

    def _update_map(self, features: FrameFeatures, pose: np.ndarray, map_index: np.ndarray, inliers: int) -> np.ndarray:
        """The frame's features into the local map; returns their stable point ids."""
        self._updates += 1
        first_new = self.map.next_id
        ids = self.map.update(self._updates, features, pose, map_index)
        self._map_pose, self._map_inliers = pose, inliers
        if self.window_ba is not None:
            seen = ids >= 0
            self.window_ba.add(KeyframeRecord(
                invert(pose), ids[seen], features.keypoints[seen].astype(np.float64), features.pixel_sigmas()[seen],
                features.points[seen, 2].astype(np.float64), features.depth_sigmas(nan=True)[seen],
                first_new, self.map.next_id))
        if features.depth is not None:
            pending = self._pending_reference  # this frame's pyramid, if ICP already built it
            ref = pending if pending is not None and pending.depth is features.depth else \
                _DepthReference(features.depth, features.grey)
            ref.pose = pose
            self._reference = ref
        return ids

    def _adjust_window(self, pose: np.ndarray) -> np.ndarray:
        """Run the windowed BA (`odometry.window_ba`) and feed it back into tracking: the adjusted
        points take their refined positions, a point created by a map update whose pose moved
        moves with it, and the tracker continues from the newest map update's refined pose
        (this frame's), which it returns."""
        wba = self.window_ba
        assert wba is not None
        out = wba.run(self.map.ids, self.map.points, self.map.returned)
        if out is None:
            return pose
        old, new, pts, X = out
        mp = self.map
        for lo, hi, M in wba.corrections(old, new):
            a, b = np.searchsorted(mp.ids, [lo, hi])
            if b > a:
                mp.points[a:b] = mp.points[a:b] @ M[:3, :3].T + M[:3, 3]
                mp.origins[a:b] = mp.origins[a:b] @ M[:3, :3].T + M[:3, 3]
                mp.rays[a:b] = mp.rays[a:b] @ M[:3, :3].T
        mp.points[pts] = X
        pose = invert(new[-1])
        self._map_pose = pose
        if self._reference is not None:
            self._reference.pose = pose
        return pose

    def _calibrate(self, features: FrameFeatures, pose: np.ndarray, map_index: np.ndarray) -> None:
        """Feed the disparity-offset estimate with this frame: its inliers' information on the
        offset at the refined pose (stereo map points slide along their first ray by
        ∂ρ/∂δ = −ρ²·cos/(f·b), this frame's depths by ∂z/∂δ = −z²/(f·b))."""
        cal = self.calibration
        assert cal is not None  # track() calibrates only with an estimator
        q = np.nonzero(map_index >= 0)[0]
        m = map_index[q]
        mp = self.map
        fb = cal.fb
        stereo = np.isfinite(mp.disparity[m])
        rho = np.linalg.norm(mp.points[m] - mp.origins[m], axis=1)
        dworld = np.where(stereo, -rho ** 2 * np.nan_to_num(mp.cos0[m]) / fb, 0.0)
        z = features.points[q, 2].astype(np.float64)
        ddepth = np.where(np.isfinite(z), -z ** 2 / fb, 0.0)
        grad, info = offset_information(invert(pose), self.K, mp.points[m], features.keypoints[q],
                                        features.pixel_sigmas()[q], mp.rays[m], mp.sigma[m], dworld, z,
                                        features.depth_sigmas(nan=True)[q], ddepth)
        if info > 0:
            cal.add(cal.offset - grad / info, info)

    def _register_depth(self, features: FrameFeatures, predicted: np.ndarray):
        """Point-to-plane ICP of this frame's depth against the last map update's depth."""
        ref = self._reference
        if ref is None or features.depth is None:
            return None
        assert ref.pose is not None  # _update_map sets the reference's pose with it
        c = self.config
        current = self._pending_reference = _DepthReference(features.depth, features.grey)
        res = icp.register(current.levels(self.camera), ref.levels(self.camera), invert(ref.pose) @ predicted,
                           min_inlier_ratio=c.icp_min_inlier_ratio, min_conditioning=c.icp_min_conditioning)
        if not res.ok:
            return None
        return ref.pose @ res.pose, np.full(len(features), -1), np.zeros(len(features), bool), None

    # -- internals ----------------------------------------------------------------------
    def _start_segment(self, features: FrameFeatures, stamp: float, new_segment: bool = False) -> TrackResult:
        if new_segment:
            self.segment += 1
        self.map.clear()
        if self.window_ba is not None:
            self.window_ba.clear()
        self.pose = np.eye(4) if self.pose is None else self.pose
        self.velocity = np.eye(4)
        self.last_stamp, self.lost_in_row = stamp, 0
        self._last_dt = None
        ids = self._update_map(features, self.pose, np.full(len(features), -1), int(features.has_depth.sum()))
        return TrackResult("init", self.pose.copy(), int(features.has_depth.sum()), 0, self.segment,
                           np.full(len(features), -1), np.zeros(len(features), bool), ids)

    def _dt(self, stamp: float) -> float | None:
        return None if self.last_stamp is None else stamp - self.last_stamp

    def _predict(self, stamp: float) -> np.ndarray:
        """Constant-velocity prediction, the last motion scaled to the elapsed time."""
        assert self.pose is not None  # track() starts a segment first
        if not self.config.motion_model:
            return self.pose
        dt, last_dt = self._dt(stamp), self._last_dt
        motion = self.velocity
        if dt and last_dt and last_dt > 0 and abs(dt / last_dt - 1) > 0.2:
            motion = _scale_motion(motion, dt / last_dt)
        return self.pose @ motion

    def _register(self, features: FrameFeatures, predicted: np.ndarray, gated: bool):
        """Match against the local map and solve PnP. Returns (pose, map_index, inlier mask, σ)
        or None when fewer than min_inliers support a pose."""
        c = self.config
        cam = self.camera
        # Map points in front of the predicted camera and inside the image (with a margin
        # that is the whole image when ungated).
        T_cw = invert(predicted)
        pc = self.map.points @ T_cw[:3, :3].T + T_cw[:3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = pc[:, :2] / pc[:, 2:3] * [cam.fx, cam.fy] + [cam.cx, cam.cy]
        margin = c.guided_radius if gated else max(cam.width, cam.height)
        visible = (pc[:, 2] > 0.05) & (uv[:, 0] > -margin) & (uv[:, 0] < cam.width + margin) \
            & (uv[:, 1] > -margin) & (uv[:, 1] < cam.height + margin)
        if not gated:
            visible = np.ones(len(pc), bool)
        cand = np.nonzero(visible)[0]
        if len(cand) < c.min_inliers or len(features) < c.min_inliers:
            return None
        if c.match_from_map:  # ORB-SLAM's direction: each map point takes a keypoint, the oldest point wins
            if gated and c.match_tile > 0:  # by projection: keypoints near each map point's tile only
                q_idx, m_idx, dist = match_map_points_tiled(
                    features.descriptors, features.keypoints.astype(np.float64), self.map.descriptors[cand], uv[cand],
                    c.guided_radius, c.match_ratio, c.max_hamming, c.match_tile)
            else:
                q_idx, m_idx, dist = match_map_points(features.descriptors, self.map.descriptors[cand],
                                                      c.match_ratio, c.max_hamming)
            m_idx = cand[m_idx]
            if gated:
                near = _within(uv[m_idx], features.keypoints[q_idx], c.guided_radius)
                q_idx, m_idx, dist = q_idx[near], m_idx[near], dist[near]
            q_all, m_all = q_idx, m_idx
            q_idx, m_idx = one_per_query(q_idx, m_idx, dist, self.map.ids[m_idx])
        else:
            q_idx, m_idx = match_descriptors(features.descriptors, self.map.descriptors[cand], c.match_ratio,
                                             c.max_hamming)
            m_idx = cand[m_idx]
            if gated:
                near = _within(uv[m_idx], features.keypoints[q_idx], c.guided_radius)
                q_idx, m_idx = q_idx[near], m_idx[near]
        if len(q_idx) < c.min_inliers:
            return None
        sigma_px = features.pixel_sigmas()[q_idx]
        pose, inl, sigma = self._solve_pnp(self.map.points[m_idx], features.keypoints[q_idx], T_cw,
                                           sigma_px, self.map.rays[m_idx], self.map.sigma[m_idx],
                                           features.points[q_idx, 2], features.depth_sigmas(nan=True)[q_idx])
        if pose is None or inl.sum() < c.min_inliers:
            return None
        if not self._depth_consistent(pose, self.map.points[m_idx[inl]], features.points[q_idx[inl]]):
            return None
        if not self._plausible(pose, predicted):
            return None
        map_index = np.full(len(features), -1)
        map_index[q_idx] = m_idx
        inliers = np.zeros(len(features), bool)
        inliers[q_idx[inl]] = True
        if c.match_from_map and c.map_reuse_replace:
            # the newer map points that took a keypoint an older point took as a PnP inlier:
            # duplicates of that point (ORB-SLAM replaces them by the one observed most)
            lost = ~np.isin(m_all, m_idx)
            return pose, map_index, inliers, sigma, np.unique(m_all[lost & inliers[q_all]])
        return pose, map_index, inliers, sigma

    def _plausible(self, pose: np.ndarray, predicted: np.ndarray) -> bool:
        """A registration may correct the constant-velocity prediction, not contradict it: it
        must stay within max_jump_factor × the last motion (at least max_jump_min_m /
        max_jump_min_rad) of it. Rejects the rotation/translation ambiguity of a flat wall
        with a repeated pattern, where RANSAC can prefer a slid-and-turned pose."""
        c = self.config
        if self._last_dt is None:  # no motion known yet in this segment: nothing to compare with
            return True
        delta = invert(predicted) @ pose
        speed = float(np.linalg.norm(self.velocity[:3, 3]))
        turn = float(rotation_angle(self.velocity[:3, :3]))
        return bool(np.linalg.norm(delta[:3, 3]) <= max(c.max_jump_min_m, c.max_jump_factor * speed)
                    and rotation_angle(delta[:3, :3]) <= max(c.max_jump_min_rad, c.max_jump_factor * turn))

    def _depth_consistent(self, pose: np.ndarray, world: np.ndarray, measured: np.ndarray) -> bool:
        """Reprojection alone cannot see a pose slid along the line of sight when the inliers
        are clustered (one poster of a repeated pattern); the frame's own depth can: the
        inliers' depth under the pose must agree with the depth the sensor measured."""
        z_meas = measured[:, 2]
        ok = np.isfinite(z_meas)
        if ok.sum() < 10:
            return True  # nothing to check against (e.g. far stereo points only)
        T_cw = invert(pose)
        z_pred = world[ok] @ T_cw[2, :3] + T_cw[2, 3]
        return float(np.median(np.abs(z_pred - z_meas[ok]) / z_meas[ok])) <= self.config.max_depth_residual

    def _solve_pnp(self, world: np.ndarray, pixels: np.ndarray, T_cw_guess: np.ndarray, sigma_px: np.ndarray,
                   rays: np.ndarray, sigma_ray: np.ndarray, depth: np.ndarray, depth_sigma: np.ndarray):
        """AP3P + RANSAC, then Gauss–Newton on the inliers weighted by their keypoint level
        and the map points' depth uncertainty, with this frame's measured depth as a third
        residual (`refinement.refine_pose`); the inliers are selected again under the refined
        pose (within pnp_reprojection_error pixels at level 0, scaled by the level and
        widened along an uncertain point's ray). With `odometry.pnp_ransac_max_sigma` RANSAC sees
        only the matches of fine keypoints (σ at most that): its one pixel threshold fits them,
        their larger inlier share ends it in fewer iterations, and the re-selection under the
        refined pose takes the inliers among all the matches, each at its own σ."""
        c = self.config
        rvec0, _ = cv2.Rodrigues(T_cw_guess[:3, :3])
        tvec0 = T_cw_guess[:3, 3].reshape(3, 1).copy()
        cv2.setRNGSeed(self._seed)
        sample = np.arange(len(world))
        if c.pnp_ransac_max_sigma > 0:  # the fine keypoints, whose pixels the one threshold fits
            fine = np.nonzero(sigma_px <= c.pnp_ransac_max_sigma)[0]
            if len(fine) >= RANSAC_MIN_SAMPLE:
                sample = fine
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            world[sample].astype(np.float64), pixels[sample].astype(np.float64), self.K, None,
            rvec=rvec0.copy(), tvec=tvec0.copy(), useExtrinsicGuess=False,
            iterationsCount=c.pnp_iterations, reprojectionError=c.pnp_reprojection_error,
            confidence=c.pnp_confidence, flags=cv2.SOLVEPNP_AP3P,
        )
        if not ok or inl is None or len(inl) < 4:
            return None, np.zeros(len(world), bool), None
        mask = np.zeros(len(world), bool)
        mask[sample[inl.ravel()]] = True
        R, _ = cv2.Rodrigues(rvec)
        T_cw, H = refine_pose(make_pose(R, tvec.ravel()), self.K, world[mask], pixels[mask], sigma_px[mask],
                              rays[mask], sigma_ray[mask], depth[mask], depth_sigma[mask], hessian=True)
        # Re-select inliers under the refined pose (RANSAC's set came from a minimal sample).
        mask = mahalanobis2(T_cw, self.K, world, pixels, sigma_px, rays, sigma_ray) <= c.pnp_reprojection_error ** 2
        if mask.sum() >= 4:
            T_cw, H = refine_pose(T_cw, self.K, world[mask], pixels[mask], sigma_px[mask], rays[mask], sigma_ray[mask],
                                  depth[mask], depth_sigma[mask], hessian=True)
        pose = invert(T_cw)
        if c.max_translation > 0 and self.pose is not None and \
                np.linalg.norm(pose[:3, 3] - self.pose[:3, 3]) > c.max_translation:
            return None, np.zeros(len(world), bool), None
        return pose, mask, None if H is None else sigma_from_hessian(H)


def _reading_information(points: np.ndarray, sigma_px: np.ndarray, sigma_z: np.ndarray, pose: np.ndarray,
                         focal: float) -> np.ndarray:
    """(n, 3, 3) world-frame information of depth readings `points` (camera frame) taken at
    `pose`: σ_z along the camera's z axis, z·σ_px/focal across it (rotated into the world).
    Readings without a depth σ get σ_z = 1 cm·z² (so the matrix stays invertible)."""
    z = np.maximum(np.nan_to_num(points[:, 2], nan=1.0), 1e-3)
    lateral = z * np.asarray(sigma_px, np.float64) / focal
    sz = np.asarray(sigma_z, np.float64)
    sz = np.where(np.isfinite(sz) & (sz > 0), sz, 0.01 * z ** 2)
    diag = np.zeros((len(z), 3, 3))
    diag[:, 0, 0] = diag[:, 1, 1] = 1.0 / lateral ** 2
    diag[:, 2, 2] = 1.0 / sz ** 2
    R = pose[:3, :3]
    return R @ diag @ R.T


def _support(result) -> int:
    """Inlier count of a registration result (None counts as 0)."""
    return 0 if result is None else int(result[2].sum())


def _scale_motion(T: np.ndarray, s: float) -> np.ndarray:
    """The rigid motion T scaled by s along its geodesic (axis-angle × s, translation × s)."""
    rvec, _ = cv2.Rodrigues(T[:3, :3])
    R, _ = cv2.Rodrigues(rvec * s)
    return make_pose(R, T[:3, 3] * s)


def compensate_depth_time(features: FrameFeatures, camera: PinholeCamera, T_color_depth: np.ndarray) -> FrameFeatures:
    """The features with each depth point moved from the depth image's camera into the colour
    image's, `T_color_depth` being the depth camera's pose in the colour camera (the camera's
    motion between the two images' stamps; TUM's Kinect takes them up to 20 ms apart). A
    keypoint's depth was read at its colour pixel, where the depth camera saw another surface
    point: its point is carried into the depth camera, the depth read again where it projects
    (twice: the second read corrects the first's depth), and the point seen there carried
    back, then placed on the keypoint's colour ray at that depth. A keypoint whose depth is
    missing there, or more than 5 % from the expected one (a depth edge), loses its depth."""
    if np.allclose(T_color_depth, np.eye(4)) or features.depth is None:
        return features
    depth = features.depth
    h, w = depth.shape[:2]
    p = features.points.astype(np.float64)
    idx = np.nonzero(np.isfinite(p[:, 2]))[0]
    T_dc = invert(T_color_depth)
    q = p[idx] @ T_dc[:3, :3].T + T_dc[:3, 3]  # in the depth camera
    good = q[:, 2] > 1e-3
    u, v = np.zeros(len(q), int), np.zeros(len(q), int)
    # the depth image is registered to the raw colour image: a point is read at its raw (distorted)
    # pixel, and the point seen there lies on that pixel's undistorted ray
    rays = camera.pixel_rays() if camera.distorted else None
    for _ in range(2):
        g = np.nonzero(good)[0]
        if rays is None:
            u[g] = np.rint(q[g, 0] / q[g, 2] * camera.fx + camera.cx)
            v[g] = np.rint(q[g, 1] / q[g, 2] * camera.fy + camera.cy)
        elif len(g):
            raw, _ = cv2.projectPoints(q[g].reshape(-1, 1, 3), np.zeros(3), np.zeros(3), camera.K,
                                       np.asarray(camera.distortion))
            u[g], v[g] = np.rint(raw[:, 0, 0]), np.rint(raw[:, 0, 1])
        good &= (u >= 0) & (u < w) & (v >= 0) & (v < h)
        z = np.zeros(len(q))
        z[good] = depth[v[good], u[good]]
        good &= np.isfinite(z) & (np.abs(z - q[:, 2]) <= 0.05 * q[:, 2])
        if rays is None:
            x, y = (u[good] - camera.cx) / camera.fx, (v[good] - camera.cy) / camera.fy
        else:
            x, y = rays[v[good], u[good], 0], rays[v[good], u[good], 1]
        q[good] = np.stack([x * z[good], y * z[good], z[good]], axis=1)
    zc = q[:, 2] * T_color_depth[2, 2] + q[:, :2] @ T_color_depth[2, :2] + T_color_depth[2, 3]  # colour depth
    z_new = np.where(good, zc, np.nan)
    xy = features.keypoints[idx].astype(np.float64)
    points = features.points.copy()
    points[idx] = np.stack([(xy[:, 0] - camera.cx) / camera.fx * z_new, (xy[:, 1] - camera.cy) / camera.fy * z_new,
                            z_new], axis=1)
    return dataclasses.replace(features, points=points)


def grow_depth_sigma(features: FrameFeatures, motion: np.ndarray, k: float) -> FrameFeatures:
    """The features with each depth σ grown by `k` × how far `motion` (the depth-time motion,
    a guess of the motion model) moves a point at that depth, |t| + z·|θ|, added in quadrature:
    the depth moved by it is as uncertain as that guess (`odometry.depth_time_sigma`)."""
    if k <= 0 or features.depth_sigma is None:
        return features
    rvec, _ = cv2.Rodrigues(motion[:3, :3])
    z = np.nan_to_num(features.points[:, 2].astype(np.float64), nan=0.0)
    extra = k * (np.linalg.norm(motion[:3, 3]) + z * np.linalg.norm(rvec))
    sigma = np.sqrt(features.depth_sigma.astype(np.float64) ** 2 + extra ** 2)
    return dataclasses.replace(features, depth_sigma=sigma.astype(np.float32))
