"""Local bundle adjustment over the newest keyframes of the odometry chain (ORB-SLAM's local
BA, in the map update behind tracking).

The tracker gives every keyframe feature the stable id of the local-map point it observed
(its PnP inlier) or created, so the keyframes of a window share point tracks without any
matching here. The window holds the last `window` keyframes of the chain (a new segment
starts a new window); each update solves jointly for their poses and the points seen by at
least two of them, the oldest `fixed` keyframes held at their poses (gauge), with GTSAM:

* a reprojection factor per observation (`GenericProjectionFactorCal3_S2`), σ = the
  keypoint's pyramid level (`scale_factor ** octave` px);
* where the keyframe measured the point's depth, the observation is a virtual stereo
  measurement instead (`GenericStereoFactor3D`, ORB-SLAM's RGB-D trick: u_R = u − f·b/z for
  a virtual baseline b) whose disparity σ_d = f·b·σ_z / z² carries the sensor's depth
  uncertainty (RGB-D: σ_z = depth_noise·z², i.e. a constant σ_d), the pixel and disparity
  errors correlated as they are (u_R = u − d);
* every factor robust (Huber at the χ² 95 % quantile of its dimension).

Depth that is biased (7-Scenes: colour and depth not registered, so the depth read at a
keypoint is that of a neighbouring surface point) must not outweigh reprojection. The depth
term's weight is `depth_weight` times the sensor's, and with `adaptive_depth` the solve is
repeated once with σ_d scaled by the robust spread (MAD) of the normalised disparity
residuals when that exceeds 1: a variance-component estimate of how well the depth agrees
with the multi-view geometry, per window, so registered depth keeps its weight and
misregistered depth loses what it does not deserve.

The result is the window's poses in the odometry frame; the map update uses the relative
pose of the newest keyframe to the one before as its odometry link.
"""
from __future__ import annotations

import collections
import time
from dataclasses import dataclass, field

import gtsam
import numpy as np

from mnemoslam.client.kernel.frames import PinholeCamera

from ..memory.vocabulary import as_u64, hamming_matrix
from .graph import to_pose3

VIRTUAL_BASELINE = 0.1  # m, of the virtual stereo measurement (any value: σ_d scales with it)
HUBER_2 = float(np.sqrt(5.991))  # χ² 95 %, 2 dof (pixels)
HUBER_3 = float(np.sqrt(7.815))  # χ² 95 %, 3 dof (pixels + disparity)
FIXED = gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)  # prior that holds the oldest keyframes (gauge)


def _X(k: int) -> int:
    return gtsam.symbol("x", k)


def _L(j: int) -> int:
    return gtsam.symbol("l", j)


@dataclass
class WindowKeyframe:
    node_id: int
    pose: np.ndarray  # camera-to-world, odometry frame
    uv: np.ndarray  # (n, 2) pixels of the features with a point id
    point_ids: np.ndarray  # (n,) int64
    points: np.ndarray  # (n, 3) camera-frame points (NaN: no depth)
    sigma_px: np.ndarray  # (n,) keypoint σ (px)
    sigma_z: np.ndarray  # (n,) depth σ (m, NaN: none)
    descriptors: np.ndarray  # (n, 32) ORB


@dataclass
class LocalBAResult:
    poses: dict[int, np.ndarray]  # node id -> refined camera-to-world (odometry frame)
    keyframes: int = 0
    points: int = 0
    observations: int = 0
    depth_observations: int = 0
    depth_scale: float = 1.0  # σ_d multiplier the adaptive step chose (1: the sensor's)
    error_before: float = 0.0
    error_after: float = 0.0
    timings_ms: dict = field(default_factory=dict)


class LocalBundleAdjustment:
    """A sliding window of keyframes and the local BA over it.

    Parameters: ``window`` keyframes at most; ``fixed`` oldest ones held fixed; ``iterations``
    of Levenberg–Marquardt; ``depth_weight`` multiplies the depth term's information (0: no
    depth term, reprojection only); ``adaptive_depth`` rescales σ_d per window from the
    residuals; ``min_points`` shared points (and observations per free keyframe) below which
    the window is not solved; ``search_radius`` / ``max_hamming`` / ``match_ratio`` of the
    search by projection; ``fuse``: fuse the tracker's duplicate points (see ``add``)."""

    def __init__(self, camera: PinholeCamera, window: int = 8, fixed: int = 1, iterations: int = 10,
                 depth_weight: float = 1.0, adaptive_depth: bool = True, min_points: int = 30,
                 max_initial_error: float = 10.0, search_radius: float = 15.0, max_hamming: int = 64,
                 match_ratio: float = 0.8, fuse: bool = False):
        if window < 2 or not 1 <= fixed < window:
            raise ValueError(f"local BA needs window >= 2 and 1 <= fixed < window, got {window}, {fixed}")
        self.camera = camera
        self.window = int(window)
        self.fixed = int(fixed)
        self.iterations = int(iterations)
        self.depth_weight = float(depth_weight)
        self.adaptive_depth = bool(adaptive_depth)
        self.min_points = int(min_points)
        self.max_initial_error = float(max_initial_error)
        self.search_radius, self.max_hamming = float(search_radius), int(max_hamming)
        self.match_ratio = float(match_ratio)
        self._next_id = 1 << 40  # ids of points this module creates (the tracker's count up from 0)
        self.fuse = bool(fuse)
        # tracker ids found to be the same point as an older window point -> that point's id (sorted keys)
        self._alias_from = np.zeros(0, np.int64)
        self._alias_to = np.zeros(0, np.int64)
        self.keyframes: collections.deque[WindowKeyframe] = collections.deque(maxlen=self.window)
        self._K = gtsam.Cal3_S2(camera.fx, camera.fy, 0.0, camera.cx, camera.cy)
        self._Ks = gtsam.Cal3_S2Stereo(camera.fx, camera.fy, 0.0, camera.cx, camera.cy, VIRTUAL_BASELINE)
        self._fb = camera.fx * VIRTUAL_BASELINE

    def __contains__(self, node_id: int) -> bool:
        return any(k.node_id == node_id for k in self.keyframes)

    def add(self, node_id: int, pose: np.ndarray, keypoints: np.ndarray, descriptors: np.ndarray,
            points: np.ndarray, sigma_px: np.ndarray, sigma_z: np.ndarray | None, point_ids: np.ndarray | None,
            continues: bool) -> int:
        """A new keyframe: its odometry pose, features and the tracker's point ids (-1: none).
        `continues`: it follows the window's newest keyframe on the odometry chain (else the
        window starts again). Features without a tracker id (e.g. a frame the tracker
        registered densely) are matched to the window's points by projection (ORB-SLAM's
        search by projection: descriptor within `max_hamming` and ratio, at most
        `search_radius` px from where the odometry pose projects the point); the other ones
        with depth become new points. With `fuse`, features with a tracker id are searched
        too: one that matches an older window point is that point (the tracker's local map
        creates a new point for every feature it did not match, so one surface point gets
        several ids), and its id is mapped to the older one from then on. Returns how many
        features were matched by projection."""
        if not continues:
            self.keyframes.clear()
            self._alias_from, self._alias_to = np.zeros(0, np.int64), np.zeros(0, np.int64)
        n = len(keypoints)
        ids = np.full(n, -1, np.int64) if point_ids is None else np.asarray(point_ids, np.int64).copy()
        pts = np.asarray(points, np.float64)
        desc = np.asarray(descriptors, np.uint8)
        uv = np.asarray(keypoints, np.float64)
        ids = self._resolve(ids)
        matched = self._search_by_projection(np.asarray(pose, np.float64), uv, desc, ids) if self.keyframes else 0
        fresh = (ids < 0) & np.isfinite(pts[:, 2])
        ids[fresh] = self._next_id + np.arange(int(fresh.sum()))
        self._next_id += int(fresh.sum())
        has = ids >= 0
        sz = np.full(n, np.nan) if sigma_z is None else np.asarray(sigma_z, np.float64)
        self.keyframes.append(WindowKeyframe(
            int(node_id), np.asarray(pose, np.float64), uv[has], ids[has], pts[has],
            np.asarray(sigma_px, np.float64)[has], sz[has], desc[has]))
        return matched

    def _resolve(self, ids: np.ndarray) -> np.ndarray:
        """`ids` with every fused id replaced by the point it was fused into."""
        if not len(self._alias_from) or not len(ids):
            return ids
        k = np.minimum(np.searchsorted(self._alias_from, ids), len(self._alias_from) - 1)
        return np.where(self._alias_from[k] == ids, self._alias_to[k], ids)

    def _add_aliases(self, old: np.ndarray, new: np.ndarray) -> None:
        """Fuse points `old` into `new` (earlier aliases that pointed at an `old` follow)."""
        keep = ~np.isin(self._alias_from, old)
        src = np.concatenate([self._alias_from[keep], old])
        dst = np.concatenate([self._alias_to[keep], new])
        order = np.argsort(src, kind="stable")
        self._alias_from, self._alias_to = src[order], dst[order]
        self._alias_to = self._resolve(self._alias_to)  # chains a -> b -> c become a -> c

    def _search_by_projection(self, pose: np.ndarray, uv: np.ndarray, desc: np.ndarray, ids: np.ndarray) -> int:
        """Give features without an id (in place) the id of the window point they see."""
        free = np.nonzero(ids < 0)[0] if not self.fuse else np.arange(len(ids))
        if not len(free):
            return 0
        kfs = list(self.keyframes)
        all_ids = np.concatenate([k.point_ids for k in kfs])
        pc = np.concatenate([k.points for k in kfs])
        kf = np.concatenate([np.full(len(k.point_ids), i) for i, k in enumerate(kfs)])
        d_all = np.concatenate([k.descriptors for k in kfs])
        depth = np.nonzero(np.isfinite(pc[:, 2]))[0][::-1]  # the newest view with depth places the point ...
        uniq, where = np.unique(all_ids[depth], return_index=True)
        src = depth[where]
        last = len(all_ids) - 1 - np.unique(all_ids[::-1], return_index=True)[1]  # ... its newest view describes it
        lm_desc = d_all[last[np.searchsorted(np.unique(all_ids), uniq)]]
        poses = np.stack([k.pose for k in kfs])
        X = np.einsum("nij,nj->ni", poses[kf[src], :3, :3], pc[src]) + poses[kf[src], :3, 3]
        keep = ~np.isin(uniq, ids[ids >= 0])  # points this keyframe already sees
        T_cw = np.linalg.inv(pose)
        p = X @ T_cw[:3, :3].T + T_cw[:3, 3]
        cam = self.camera
        with np.errstate(divide="ignore", invalid="ignore"):
            proj = p[:, :2] / p[:, 2:3] * [cam.fx, cam.fy] + [cam.cx, cam.cy]
        keep &= (p[:, 2] > 0.05) & (proj[:, 0] >= 0) & (proj[:, 0] < cam.width) & (proj[:, 1] >= 0) \
            & (proj[:, 1] < cam.height)
        cand = np.nonzero(keep)[0]
        if len(cand) < 2:
            return 0
        dist = hamming_matrix(as_u64(desc[free]), as_u64(lm_desc[cand]))
        px = np.linalg.norm(uv[free][:, None, :] - proj[cand][None], axis=2)
        dist = np.where(px <= self.search_radius, dist, 256.0)
        best = np.argmin(dist, axis=1)
        d1 = dist[np.arange(len(free)), best]
        dist[np.arange(len(free)), best] = 256.0
        d2 = dist.min(axis=1)
        ok = (d1 <= self.max_hamming) & (d1 < self.match_ratio * d2)
        q, t, d1 = free[ok], best[ok], d1[ok]
        order = np.lexsort((d1, t))  # one feature per point: the closest descriptor
        first = np.ones(len(order), bool)
        first[1:] = t[order][1:] != t[order][:-1]
        keep_m = order[first]
        q, lm = q[keep_m], uniq[cand[t[keep_m]]]
        dup = ids[q] >= 0  # a tracker point that is an older window point: fuse them (ORB-SLAM's fusion)
        if dup.any():
            self._add_aliases(ids[q[dup]], lm[dup])
            for k in self.keyframes:
                k.point_ids[:] = self._resolve(k.point_ids)
        ids[q] = lm
        return len(keep_m)

    def solve(self) -> LocalBAResult | None:
        """Bundle-adjust the window; None when it is too small or shares too few points."""
        t0 = time.perf_counter()
        kfs = list(self.keyframes)
        if len(kfs) <= self.fixed:
            return None
        n_kf = len(kfs)
        kf = np.concatenate([np.full(len(k.point_ids), i) for i, k in enumerate(kfs)])
        ids = np.concatenate([k.point_ids for k in kfs])
        uv = np.concatenate([k.uv for k in kfs])
        pc = np.concatenate([k.points for k in kfs])
        spx = np.concatenate([k.sigma_px for k in kfs])
        sz = np.concatenate([k.sigma_z for k in kfs])
        poses = np.stack([k.pose for k in kfs])
        # points seen by ≥ 2 keyframes of the window, one of them with depth (its first such view places it)
        uniq, inv, counts = np.unique(ids, return_inverse=True, return_counts=True)
        depth_ok = np.isfinite(pc[:, 2]) & (pc[:, 2] > 0)
        first = np.full(len(uniq), -1)
        d_idx = np.nonzero(depth_ok)[0]  # observations are ordered by keyframe: the first is the oldest
        order = d_idx[::-1]
        first[inv[order]] = order  # written last = the oldest view with depth
        landmark = (counts >= 2) & (first >= 0)
        if landmark.sum() < self.min_points:
            return None
        src = first[landmark]
        X0 = np.full((len(uniq), 3), np.nan)
        X0[landmark] = np.einsum("nij,nj->ni", poses[kf[src], :3, :3], pc[src]) + poses[kf[src], :3, 3]
        obs = landmark[inv]
        # reprojection at the odometry poses: an observation already far off is an outlier (wrong track)
        T_cw = np.linalg.inv(poses)
        Xo = X0[inv]
        p = np.einsum("nij,nj->ni", T_cw[kf, :3, :3], np.nan_to_num(Xo)) + T_cw[kf, :3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            proj = p[:, :2] / p[:, 2:3] * [self.camera.fx, self.camera.fy] + [self.camera.cx, self.camera.cy]
            err = np.linalg.norm(proj - uv, axis=1) / spx
        obs &= (p[:, 2] > 0.05) & (err <= self.max_initial_error)
        # landmarks still seen twice
        seen = np.bincount(inv[obs], minlength=len(uniq))
        obs &= seen[inv] >= 2
        sel = np.nonzero(obs)[0]
        lm_ids = np.unique(inv[sel])
        per_kf = np.bincount(kf[sel], minlength=n_kf)
        if len(lm_ids) < self.min_points or per_kf[self.fixed:].min() < self.min_points:
            return None  # a free keyframe held by a few points only would go where they put it
        use_depth = depth_ok[sel] & np.isfinite(sz[sel]) & (self.depth_weight > 0)
        # σ_d = f·b·σ_z / z², from the depth weight (information × weight = σ / √weight)
        sigma_d = np.where(use_depth, self._fb * np.nan_to_num(sz[sel]) / np.maximum(pc[sel, 2], 1e-6) ** 2
                           / np.sqrt(max(self.depth_weight, 1e-12)), np.nan)
        t1 = time.perf_counter()
        values = gtsam.Values()
        for i in range(n_kf):
            values.insert(_X(i), to_pose3(poses[i]))
        for j in lm_ids.tolist():
            values.insert(_L(j), X0[j])
        result_values, scale, e0, e1, t_build = self._optimise(values, n_kf, sel, kf, inv, uv, pc, spx, sigma_d,
                                                               use_depth, 1.0)
        if self.adaptive_depth and use_depth.any():
            s = self._disparity_spread(result_values, sel, kf, inv, uv, pc, sigma_d, use_depth)
            if s > 1.0:
                result_values, scale, _, e1, t_b2 = self._optimise(values, n_kf, sel, kf, inv, uv, pc, spx, sigma_d,
                                                                   use_depth, s)
                t_build += t_b2
        out = {kfs[i].node_id: result_values.atPose3(_X(i)).matrix() for i in range(n_kf)}
        t2 = time.perf_counter()
        return LocalBAResult(out, n_kf, len(lm_ids), len(sel), int(use_depth.sum()), scale, e0, e1,
                             {"prepare": (t1 - t0) * 1e3, "factors": t_build, "solve": (t2 - t1) * 1e3 - t_build})

    # -- internals ------------------------------------------------------------------------
    def _optimise(self, values, n_kf, sel, kf, inv, uv, pc, spx, sigma_d, use_depth, scale):
        t0 = time.perf_counter()
        graph = gtsam.NonlinearFactorGraph()
        for i in range(self.fixed):
            graph.add(gtsam.PriorFactorPose3(_X(i), values.atPose3(_X(i)), FIXED))
        models: dict = {}
        huber2 = gtsam.noiseModel.mEstimator.Huber.Create(HUBER_2)
        huber3 = gtsam.noiseModel.mEstimator.Huber.Create(HUBER_3)
        K, Ks, fb = self._K, self._Ks, self._fb
        u, v = uv[sel, 0], uv[sel, 1]
        disp = np.where(use_depth, fb / np.maximum(pc[sel, 2], 1e-6), 0.0)
        s_px = spx[sel]
        s_d = np.where(use_depth, sigma_d * scale, 0.0)
        xk = kf[sel].tolist()
        lk = inv[sel].tolist()
        # noise models shared per (pixel σ, disparity σ to 3 significant digits)
        key_d = np.where(use_depth, np.round(np.log(np.maximum(s_d, 1e-12)) * 100).astype(np.int64), 0)
        for n, (x, lmk, depth) in enumerate(zip(xk, lk, use_depth.tolist())):
            if depth:
                key = (float(s_px[n]), int(key_d[n]))
                m = models.get(key)
                if m is None:
                    a, d2 = s_px[n] ** 2, s_d[n] ** 2
                    cov = np.array([[a, a, 0.0], [a, a + d2, 0.0], [0.0, 0.0, a]])
                    m = models[key] = gtsam.noiseModel.Robust.Create(huber3, gtsam.noiseModel.Gaussian.Covariance(cov))
                graph.add(gtsam.GenericStereoFactor3D(gtsam.StereoPoint2(u[n], u[n] - disp[n], v[n]), m, _X(x), _L(lmk),
                                                      Ks))
            else:
                key = (float(s_px[n]), None)
                m = models.get(key)
                if m is None:
                    m = models[key] = gtsam.noiseModel.Robust.Create(huber2,
                                                                     gtsam.noiseModel.Isotropic.Sigma(2, s_px[n]))
                graph.add(gtsam.GenericProjectionFactorCal3_S2(np.array([u[n], v[n]]), m, _X(x), _L(lmk), K))
        t_build = (time.perf_counter() - t0) * 1e3
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(self.iterations)
        e0 = graph.error(values)
        res = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
        return res, scale, float(e0), float(graph.error(res)), t_build

    def _disparity_spread(self, values, sel, kf, inv, uv, pc, sigma_d, use_depth) -> float:
        """Robust spread (1.4826 · MAD) of the depth observations' disparity residuals over
        their σ_d at the solution: > 1 when the depth disagrees with the geometry more than
        its σ says."""
        idx = np.nonzero(use_depth)[0]
        if len(idx) < 10:
            return 1.0
        o = sel[idx]
        poses = np.stack([values.atPose3(_X(int(i))).matrix() for i in range(kf.max() + 1)])
        lm = np.unique(inv[o])
        X = np.full((inv.max() + 1, 3), np.nan)
        X[lm] = np.stack([values.atPoint3(_L(int(j))) for j in lm])
        T_cw = np.linalg.inv(poses[kf[o]])
        z = np.einsum("nj,nj->n", T_cw[:, 2, :3], X[inv[o]]) + T_cw[:, 2, 3]
        r = (self._fb / np.maximum(z, 1e-6) - self._fb / pc[o, 2]) / sigma_d[idx]
        r = r[np.isfinite(r)]
        if not len(r):
            return 1.0
        return float(1.4826 * np.median(np.abs(r - np.median(r))))
