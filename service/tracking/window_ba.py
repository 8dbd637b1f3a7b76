"""Windowed bundle adjustment of the tracker's local map (ORB-SLAM's local mapping → tracking
feedback, `odometry.window_ba`).

The tracker's map updates are its keyframes: each one records the local-map points it observed
(PnP inliers) and the points it created, with the keypoint's pixel, pyramid σ and the depth
it measured. Every `window_ba_every` map updates the poses of the last `window_ba_size` map
updates and the points they observe are refined jointly, with the `window_ba_fixed` map
updates before them held (the gauge, and what anchors the window to the older map): the
residuals are ORB-SLAM's RGB-D edges, the reprojection (σ of the keypoint's level) and the
measured depth (the extractor's σ), Huber-weighted, solved by Levenberg–Marquardt on whole
arrays with the points eliminated (Schur complement: a 6·W system). The refined points go
back into the local map; a point seen by one map update alone moves with that update's pose
(it is anchored to it), and the tracker continues from the refined pose of the newest one.
With `window_ba_hold` the points that older map updates, outside the window, anchor (those the
map brought back from its archive on a revisit, or all made before the window) keep their
place: their views constrain the poses, and the revisit's old map is not bent to the drift.
When the held map updates see too few of the adjusted points (frames tracked by ICP observe
none), the window's oldest are held too: the gauge never rests on the solver's damping.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from mnemoslam.client.kernel.geometry import invert, make_pose

CHI2_PX = 5.991  # χ² 95 %, 2 dof (no depth)
CHI2_DEPTH = 7.815  # 3 dof (pixel and depth)
HOLD = ("none", "old", "returned")  # `odometry.window_ba_hold`: the points an adjustment holds
MIN_GAUGE_OBSERVATIONS = 30  # views of the adjusted points by its held map updates, at least


@dataclass
class KeyframeRecord:
    """One map update's observations: `T_cw` (world to camera, refined by the BA), the point ids
    it observed or created, their pixels (n, 2), pixel σ (n,), measured depth (n,; NaN none)
    and depth σ (n,), and the ids [created_lo, created_hi) it created."""

    T_cw: np.ndarray
    ids: np.ndarray
    pixels: np.ndarray
    sigma_px: np.ndarray
    depth: np.ndarray
    sigma_z: np.ndarray
    created_lo: int
    created_hi: int


def _sums(index: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """Sum of `values` (m, ...) by `index` (m,) into (n, ...): one bincount per component."""
    flat = values.reshape(len(values), -1)
    out = np.empty((n, flat.shape[1]))
    for k in range(flat.shape[1]):
        out[:, k] = np.bincount(index, weights=flat[:, k], minlength=n)
    return out.reshape((n,) + values.shape[1:])


def _inv3(A: np.ndarray) -> np.ndarray:
    """Inverses of (n, 3, 3) matrices (adjugate over determinant; a singular one gives zeros:
    its point does not move)."""
    a, b, c = A[:, 0, 0], A[:, 0, 1], A[:, 0, 2]
    d, e, f = A[:, 1, 0], A[:, 1, 1], A[:, 1, 2]
    g, h, i = A[:, 2, 0], A[:, 2, 1], A[:, 2, 2]
    adj = np.empty_like(A)
    adj[:, 0, 0], adj[:, 0, 1], adj[:, 0, 2] = e * i - f * h, c * h - b * i, b * f - c * e
    adj[:, 1, 0], adj[:, 1, 1], adj[:, 1, 2] = f * g - d * i, a * i - c * g, c * d - a * f
    adj[:, 2, 0], adj[:, 2, 1], adj[:, 2, 2] = d * h - e * g, b * g - a * h, a * e - b * d
    det = a * adj[:, 0, 0] + b * adj[:, 1, 0] + c * adj[:, 2, 0]
    ok = np.abs(det) > 1e-300
    return np.where(ok[:, None, None], adj / np.where(ok, det, 1.0)[:, None, None], 0.0)


def _exp(xi: np.ndarray) -> np.ndarray:
    R, _ = cv2.Rodrigues(xi[:3].reshape(3, 1))
    return make_pose(R, xi[3:])


def _terms(T: np.ndarray, X: np.ndarray, cam: np.ndarray, pt: np.ndarray, px: np.ndarray, z_meas: np.ndarray,
           has_z: np.ndarray, K: np.ndarray, jacobians: bool = True):
    """Residuals (n, 3) (u, v, depth; depth 0 where none: `has_z` false), camera Jacobians
    (n, 3, 6) for a left perturbation (ω, τ) of T_cw, point Jacobians (n, 3, 3) in world, and
    whether each point lies in front of its camera, for the observations of point `pt[o]` by
    camera `cam[o]`."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    Xo = X[pt]
    Tg = T[cam]
    R = Tg[:, :3, :3]
    p = np.einsum("nij,nj->ni", R, Xo) + Tg[:, :3, 3]
    front = p[:, 2] > 1e-3
    z = np.where(front, p[:, 2], 1.0)
    x, y = p[:, 0], p[:, 1]
    iz = 1.0 / z
    r = np.empty((len(p), 3))
    r[:, 0] = fx * x * iz + cx - px[:, 0]
    r[:, 1] = fy * y * iz + cy - px[:, 1]
    r[:, 2] = np.where(has_z, p[:, 2] - z_meas, 0.0)
    if not jacobians:
        return r, None, None, front
    xz, yz = x * iz, y * iz
    Jc = np.zeros((len(p), 3, 6))  # ∂(u, v, z)/∂(ω, τ), p' = p + ω × p + τ
    Jc[:, 0, 0], Jc[:, 0, 1], Jc[:, 0, 2] = -fx * xz * yz, fx * (1 + xz * xz), -fx * yz
    Jc[:, 0, 3], Jc[:, 0, 5] = fx * iz, -fx * xz * iz
    Jc[:, 1, 0], Jc[:, 1, 1], Jc[:, 1, 2] = -fy * (1 + yz * yz), fy * xz * yz, fy * xz
    Jc[:, 1, 4], Jc[:, 1, 5] = fy * iz, -fy * yz * iz
    Jc[:, 2, 0], Jc[:, 2, 1], Jc[:, 2, 5] = y, -x, 1.0
    Jp = np.empty((len(p), 3, 3))  # ∂(u, v, z)/∂X = ∂(u, v, z)/∂p · R
    Jp[:, 0] = (fx * iz)[:, None] * R[:, 0] - (fx * xz * iz)[:, None] * R[:, 2]
    Jp[:, 1] = (fy * iz)[:, None] * R[:, 1] - (fy * yz * iz)[:, None] * R[:, 2]
    Jp[:, 2] = R[:, 2]
    return r, Jc, Jp, front


def bundle_adjust(T_cw: np.ndarray, n_fixed: int, X: np.ndarray, cam: np.ndarray, pt: np.ndarray,
                  pixels: np.ndarray, sigma_px: np.ndarray, depth: np.ndarray, sigma_z: np.ndarray, K: np.ndarray,
                  iterations: int = 5,
                  held_points: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Levenberg–Marquardt over camera poses `T_cw` (C, 4, 4; the first `n_fixed` held) and world
    points `X` (P, 3; those `held_points` marks held) from observations o of point `pt[o]` by
    camera `cam[o]`: pixel `pixels[o]` (σ `sigma_px[o]`) and measured depth `depth[o]` (NaN: none;
    σ `sigma_z[o]`). Huber weights on each observation's Mahalanobis distance. Returns (T_cw, X,
    inlier mask per observation: within the χ² 95 % bound at the solution)."""
    T = np.array(T_cw, np.float64)
    X = np.array(X, np.float64)
    C, P = len(T), len(X)
    n_obs = len(cam)
    # sorted by camera; a second observation of a point by one camera is left out
    _, order = np.unique(np.asarray(cam, np.int64) * max(P, 1) + pt, return_index=True)
    cam, pt, pixels, sigma_px, depth, sigma_z = (a[order] for a in (cam, pt, pixels, sigma_px, depth, sigma_z))
    V = C - n_fixed  # cameras optimised
    has_z = np.isfinite(depth) & np.isfinite(sigma_z) & (sigma_z > 0)
    w_obs = np.empty((len(cam), 3))
    w_obs[:, :2] = (1.0 / sigma_px ** 2)[:, None]
    w_obs[:, 2] = np.where(has_z, 1.0 / np.where(has_z, sigma_z, 1.0) ** 2, 0.0)
    z_meas = np.where(has_z, depth, 0.0)
    chi2_max = np.where(has_z, CHI2_DEPTH, CHI2_PX)
    # the free cameras' observations (sorted by camera): free camera v's from free_bounds[v] to [v + 1]
    free_bounds = np.searchsorted(cam, np.arange(n_fixed, C + 1))
    # the free cameras' observations of points that move (a held point's terms only add to its
    # camera's own block): the Schur complement's
    moving = np.arange(free_bounds[0], len(cam))  # (observation indices)
    if held_points is not None:
        moving = moving[~held_points[pt[moving]]]
    vc_m, pt_m = cam[moving] - n_fixed, pt[moving]
    moving_bounds = np.searchsorted(vc_m, np.arange(V + 1))
    # the pairs of free cameras that see a point (each point is seen by few of them):
    # (v, w, v's observations, w's observations of the points both see), indices into the moving ones
    slot = np.full((P, V), -1)
    slot[pt_m, vc_m] = np.arange(len(pt_m))
    pairs = []
    for v in range(V):
        for w in range(v, V):
            both = np.nonzero((slot[:, v] >= 0) & (slot[:, w] >= 0))[0]
            if len(both):
                pairs.append((v, w, slot[both, v], slot[both, w]))

    def cost(T_, X_):
        r, _, _, front = _terms(T_, X_, cam, pt, pixels, z_meas, has_z, K, jacobians=False)
        e2 = (w_obs * r * r).sum(axis=1)
        e = np.sqrt(e2)
        k = np.sqrt(chi2_max)
        rho = np.where(e <= k, e2, 2 * k * e - k * k)  # Huber
        return float(np.sum(np.where(front, rho, 0.0))), e2, front

    lam = 1e-4
    current, e2, front = cost(T, X)
    for _ in range(iterations):
        r, Jc, Jp, front = _terms(T, X, cam, pt, pixels, z_meas, has_z, K)
        e = np.sqrt(e2)
        k = np.sqrt(chi2_max)
        hub = np.where(front, np.where(e <= k, 1.0, k / np.maximum(e, 1e-12)), 0.0)
        W = w_obs * hub[:, None]  # (n, 3)
        WJp = W[:, :, None] * Jp
        Hpp = _sums(pt, WJp.transpose(0, 2, 1) @ Jp, P)
        bp = _sums(pt, np.einsum("nji,nj->ni", WJp, r), P)
        Hcc = np.zeros((V, 6, 6))
        bc = np.zeros((V, 6))
        if V:
            # a camera's blocks: one product over its observations (sorted by camera)
            WJc = W[:, :, None] * Jc
            for v in range(V):
                a, b = free_bounds[v], free_bounds[v + 1]
                if b > a:
                    A = WJc[a:b].reshape(-1, 6).T
                    Hcc[v] = A @ Jc[a:b].reshape(-1, 6)
                    bc[v] = A @ r[a:b].reshape(-1)
            BoT = WJp[moving].transpose(0, 2, 1) @ Jc[moving]  # (n_moving, 3, 6): ∂²/∂point∂camera
        improved = False
        for _attempt in range(4):
            Hpp_d = Hpp + lam * (np.trace(Hpp, axis1=1, axis2=2)[:, None, None] / 3 + 1e-9) * np.eye(3)
            Cinv = _inv3(Hpp_d)
            if held_points is not None:
                Cinv[held_points] = 0.0  # a held point does not move (its terms still constrain the cameras)
            dc: np.ndarray = np.zeros((V, 6))
            if V:
                # Schur complement S = Hcc − Σ_p B_p C_p⁻¹ B_pᵀ over the pairs of free cameras
                # that see a point (each point is seen by few of them)
                YoT = Cinv[pt_m] @ BoT  # (n_moving, 3, 6): (B·C⁻¹)ᵀ
                S = np.zeros((6 * V, 6 * V))
                for v in range(V):
                    S[6 * v:6 * v + 6, 6 * v:6 * v + 6] = Hcc[v]
                for v, w, ov, ow in pairs:
                    block = YoT[ov].reshape(-1, 6).T @ BoT[ow].reshape(-1, 6)
                    S[6 * v:6 * v + 6, 6 * w:6 * w + 6] -= block
                    if v != w:
                        S[6 * w:6 * w + 6, 6 * v:6 * v + 6] -= block.T
                S += lam * np.diag(np.diag(S).clip(min=1e-9))
                rhs = -bc
                bpm = bp[pt_m]
                for v in range(V):
                    a, b = moving_bounds[v], moving_bounds[v + 1]
                    if b > a:
                        rhs[v] += YoT[a:b].reshape(-1, 6).T @ bpm[a:b].reshape(-1)
                try:
                    dc = np.linalg.solve(S, rhs.reshape(-1)).reshape(V, 6)
                except np.linalg.LinAlgError:
                    return T, X, np.zeros(n_obs, bool)
                Bdc = _sums(pt_m, np.einsum("nij,nj->ni", BoT, dc[vc_m]), P)
                dX = -(Cinv @ (bp + Bdc)[:, :, None])[:, :, 0]
            else:
                dX = -(Cinv @ bp[:, :, None])[:, :, 0]
            T_new = T.copy()
            for v in range(V):
                T_new[n_fixed + v] = _exp(dc[v]) @ T[n_fixed + v]
            X_new = X + dX
            c_new, e2_new, front_new = cost(T_new, X_new)
            if c_new < current:
                T, X, current, e2, front = T_new, X_new, c_new, e2_new, front_new
                lam = max(lam / 10, 1e-7)
                improved = True
                break
            lam *= 10
        if not improved or (np.abs(dc).max(initial=0.0) < 1e-6 and np.abs(dX).max(initial=0.0) < 1e-6):
            break
    inliers = np.zeros(n_obs, bool)
    inliers[order] = front & (e2 <= chi2_max)
    return T, X, inliers


class WindowBA:
    """The tracker's keyframe records and the windowed BA over them (`odometry.window_ba`)."""

    def __init__(self, K: np.ndarray, size: int, fixed: int, every: int, iterations: int = 5, history: int = 0,
                 max_points: int = 0, hold: str = "none"):
        if hold not in HOLD:
            raise ValueError(f"odometry.window_ba_hold: {hold!r} is not one of {', '.join(HOLD)}")
        self.K = K
        self.hold = hold
        self.size, self.fixed, self.every, self.iterations = size, fixed, every, iterations
        self.history, self.max_points = history, max_points
        self.records: list[KeyframeRecord] = []
        self._last: list[KeyframeRecord] = []  # the records of the last adjustment, fixed first
        self._since = 0

    def clear(self) -> None:
        self.records.clear()
        self._since = 0

    def add(self, record: KeyframeRecord) -> None:
        self.records.append(record)
        del self.records[: max(0, len(self.records) - self.size - max(self.fixed, self.history))]
        self._since += 1

    def due(self) -> bool:
        return self._since >= self.every and len(self.records) >= 3

    def run(self, map_ids: np.ndarray, map_points: np.ndarray, map_returned: np.ndarray | None = None):
        """Adjust the window. `map_ids` (sorted), `map_points` and `map_returned` (points brought
        back from the archive; `hold` "returned" holds them): the local map's. Returns
        (old poses T_cw (C, 4, 4), new poses, map indices of the adjusted points, their new
        positions), or None when nothing was adjusted."""
        self._since = 0
        window = self.records[-self.size:]
        older = self.records[:-self.size]
        if self.history > 0 and len(older) > self.fixed:
            # ORB-SLAM's fixed keyframes: the older map updates that see the window's points most
            seen = np.unique(np.concatenate([r.ids for r in window]))
            shared = np.array([np.isin(r.ids, seen, assume_unique=True).sum() for r in older])
            pick = np.sort(np.argsort(-shared, kind="stable")[: self.fixed])
            older = [older[i] for i in pick if shared[i] > 0]
        else:
            older = older[-self.fixed:] if self.fixed else []
        if not older:  # the gauge: the window's oldest is held
            older, window = window[:1], window[1:]
        recs = older + window
        n_fixed = len(older)
        cams, ids, pix, spx, dep, sz = [], [], [], [], [], []
        for c, rec in enumerate(recs):
            cams.append(np.full(len(rec.ids), c))
            ids.append(rec.ids)
            pix.append(rec.pixels)
            spx.append(rec.sigma_px)
            dep.append(rec.depth)
            sz.append(rec.sigma_z)
        cam, oid = np.concatenate(cams), np.concatenate(ids)
        # observations of points still in the map, seen by at least two records, one of them free
        idx = np.searchsorted(map_ids, oid)
        idx = np.minimum(idx, max(len(map_ids) - 1, 0))
        in_map = (len(map_ids) > 0) & (map_ids[idx] == oid) if len(map_ids) else np.zeros(len(oid), bool)
        uniq, inv, counts = np.unique(oid, return_inverse=True, return_counts=True)
        while True:
            free_seen = np.zeros(len(uniq), bool)
            free_seen[inv[cam >= n_fixed]] = True
            ok = in_map & (counts[inv] >= 2) & free_seen[inv]
            # the gauge: the held map updates must see the adjusted points, else the window floats
            # (map updates tracked by ICP, TUM cabinet's keyframes, observe no map point): the
            # window's oldest are held too until they do (none left free: no adjustment)
            if (ok & (cam < n_fixed)).sum() >= MIN_GAUGE_OBSERVATIONS:
                break
            if n_fixed >= len(recs) - 1:
                return None
            n_fixed += 1
        if self.max_points > 0:
            # the points seen most often (the longest tracks constrain the poses most; ties: newest)
            eligible = np.zeros(len(uniq), bool)
            eligible[inv[ok]] = True
            cand = np.nonzero(eligible)[0]
            if len(cand) > self.max_points:
                keep = np.zeros(len(uniq), bool)
                keep[cand[np.lexsort((-uniq[cand], -counts[cand]))[: self.max_points]]] = True
                ok &= keep[inv]
        if ok.sum() < 30:
            return None
        held = None
        if self.hold != "none":
            # points made before the adjustment's oldest map update ("old"), or those of them the
            # map brought back from its archive ("returned"), are held: older map updates, outside
            # it, anchor them; a held camera's view of a held point is a constant term, left out
            hold = oid < min(r.created_lo for r in recs)
            if self.hold == "returned":
                assert map_returned is not None  # (the tracker passes its map's)
                hold &= map_returned[idx]
            ok &= ~(hold & (cam < n_fixed))
        cam, oid, midx = cam[ok], oid[ok], idx[ok]
        pts, pt = np.unique(midx, return_inverse=True)
        if self.hold != "none":
            held = np.zeros(len(pts), bool)
            held[pt] = hold[ok]  # (a property of the point: the same for each of its views)
        old = np.stack([r.T_cw for r in recs])
        T, X, _inl = bundle_adjust(old, n_fixed, map_points[pts], cam, pt, np.concatenate(pix)[ok],
                                   np.concatenate(spx)[ok], np.concatenate(dep)[ok], np.concatenate(sz)[ok],
                                   self.K, self.iterations, held)
        for rec, Tn in zip(recs, T):
            rec.T_cw = Tn
        self._last = recs
        return old, T, pts, X

    def corrections(self, old: np.ndarray, new: np.ndarray) -> list[tuple[int, int, np.ndarray]]:
        """Per record of the last adjustment whose pose moved: (created_lo, created_hi, world
        correction T_new⁻¹·T_old as a 4×4 that carries a point it created from its old place to
        its new one)."""
        out = []
        for rec, To, Tn in zip(self._last, old, new):
            if rec.created_hi > rec.created_lo and not np.allclose(To, Tn):
                out.append((rec.created_lo, rec.created_hi, invert(Tn) @ To))
        return out
