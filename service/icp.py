"""Dense depth registration: coarse-to-fine point-to-plane ICP with projective data
association (KinectFusion-style), vectorized over whole depth maps.

It tracks where features cannot: textureless scenes (a plain cabinet on a white floor)
still have planes and edges. The Hessian's smallest eigenvalue tells when the geometry
does not constrain all six degrees of freedom (a single wall), so a degenerate solution is
reported rather than trusted.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from client.frames import PinholeCamera
from client.geometry import invert, make_pose


@dataclass
class DepthLevel:
    """Vertex and normal maps of one pyramid level (camera frame)."""

    step: int
    fx: float
    fy: float
    cx: float
    cy: float
    vertices: np.ndarray  # (h, w, 3), NaN where invalid
    normals: np.ndarray  # (h, w, 3), NaN where invalid

    @property
    def valid(self) -> np.ndarray:
        return np.isfinite(self.normals[..., 0])

    def points(self) -> tuple[np.ndarray, np.ndarray]:
        ok = self.valid.ravel()
        return self.vertices.reshape(-1, 3)[ok], self.normals.reshape(-1, 3)[ok]


@dataclass
class IcpResult:
    pose: np.ndarray  # T_ref_cur
    inlier_ratio: float  # associated inliers / source points
    rmse: float  # point-to-plane residual of the inliers, metres
    conditioning: float  # smallest / largest eigenvalue of the normalized Hessian
    ok: bool


STEPS = (16, 8, 4)  # pyramid subsampling, coarse first: 40×30 … 160×120 at 640×480


def depth_pyramid(depth: np.ndarray, cam: PinholeCamera, steps=STEPS, min_depth=0.2, max_depth=6.0) -> list[DepthLevel]:
    """Vertex + normal maps subsampled by each step (coarse first)."""
    depth = np.where(np.isfinite(depth) & (depth >= min_depth) & (depth <= max_depth), depth, 0).astype(np.float32)
    levels = []
    for s in steps:
        h, w = depth.shape[0] // s, depth.shape[1] // s
        # Median-free subsampling: the block's minimum valid depth keeps edges sharp enough.
        d = cv2.resize(depth, (w, h), interpolation=cv2.INTER_NEAREST)
        fx, fy = cam.fx / s, cam.fy / s
        cx, cy = (cam.cx + 0.5) / s - 0.5, (cam.cy + 0.5) / s - 0.5
        u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
        z = np.where(d > 0, d, np.nan)
        V = np.stack([(u - cx) / fx * z, (v - cy) / fy * z, z], axis=-1)
        levels.append(DepthLevel(s, fx, fy, cx, cy, V, _normals(V)))
    return levels


def _normals(V: np.ndarray) -> np.ndarray:
    """Normals from central differences, oriented towards the camera; NaN on depth edges."""
    dx = np.full_like(V, np.nan)
    dy = np.full_like(V, np.nan)
    dx[:, 1:-1] = V[:, 2:] - V[:, :-2]
    dy[1:-1] = V[2:] - V[:-2]
    n = np.cross(dx, dy)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        n = n / norm
        # Reject edges: neighbours much farther apart than the pixel footprint.
        z = V[..., 2:3]
        edge = (np.linalg.norm(dx, axis=-1, keepdims=True) > 0.1 * z) | (np.linalg.norm(dy, axis=-1, keepdims=True) > 0.1 * z)
        flip = np.sum(n * V, axis=-1, keepdims=True) > 0
    n = np.where(flip, -n, n)
    return np.where(edge | ~np.isfinite(norm) | (norm == 0), np.nan, n).astype(np.float32)


def register(src: list[DepthLevel], ref: list[DepthLevel], T_init: np.ndarray, iterations=(10, 10, 10),
             max_distance=(0.3, 0.15, 0.08), max_normal_angle_deg=40.0, min_inlier_ratio=0.3,
             min_conditioning=1e-3) -> IcpResult:
    """Align the source depth pyramid onto the reference one, starting at T_init (T_ref_src)."""
    T = T_init.copy()
    cos_max = np.cos(np.radians(max_normal_angle_deg))
    result = None
    for level, (s_lvl, r_lvl) in enumerate(zip(src, ref)):
        p_src, n_src = s_lvl.points()
        if len(p_src) < 50:
            continue
        for _ in range(iterations[level]):
            step = _icp_step(p_src, n_src, r_lvl, T, max_distance[level], cos_max)
            if step is None:
                break
            delta, result = step
            T = delta @ T
            if np.linalg.norm(delta[:3, 3]) < 1e-5 and np.linalg.norm(cv2.Rodrigues(delta[:3, :3])[0]) < 1e-5:
                break
    if result is None:
        return IcpResult(T, 0.0, np.inf, 0.0, False)
    ratio, rmse, cond = result
    ok = ratio >= min_inlier_ratio and cond >= min_conditioning
    return IcpResult(T, ratio, rmse, cond, bool(ok))


def _icp_step(p_src, n_src, ref: DepthLevel, T, max_dist, cos_max):
    R, t = T[:3, :3], T[:3, 3]
    p = p_src @ R.T + t
    n_s = n_src @ R.T
    h, w = ref.vertices.shape[:2]
    with np.errstate(invalid="ignore", divide="ignore"):
        u = np.rint(p[:, 0] / p[:, 2] * ref.fx + ref.cx)
        v = np.rint(p[:, 1] / p[:, 2] * ref.fy + ref.cy)
    inside = (p[:, 2] > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    idx = np.nonzero(inside)[0]
    ui, vi = u[idx].astype(int), v[idx].astype(int)
    q = ref.vertices[vi, ui]
    n = ref.normals[vi, ui]
    ps = p[idx]
    diff = ps - q
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(n[:, 0]) & (np.linalg.norm(diff, axis=1) < max_dist) & (np.sum(n * n_s[idx], axis=1) > cos_max)
    if ok.sum() < 30:
        return None
    ps, n, diff = ps[ok], n[ok], diff[ok]
    r = np.sum(diff * n, axis=1)
    J = np.concatenate([np.cross(ps, n), n], axis=1)  # d r / d (omega, tau), left perturbation
    # Huber weights on the point-to-plane residual.
    k = 0.02
    a = np.abs(r)
    wgt = np.where(a <= k, 1.0, k / np.maximum(a, 1e-12))
    H = (J * wgt[:, None]).T @ J
    b = (J * wgt[:, None]).T @ r
    try:
        x = -np.linalg.solve(H, b)
    except np.linalg.LinAlgError:
        return None
    # Conditioning of the problem with rotation scaled to the scene's size.
    scale = np.sqrt(np.mean(np.sum(ps * ps, axis=1)))
    D = np.diag([scale] * 3 + [1.0] * 3)
    Hn = np.linalg.inv(D) @ H @ np.linalg.inv(D)
    eig = np.linalg.eigvalsh(Hn)
    cond = float(eig[0] / eig[-1]) if eig[-1] > 0 else 0.0
    Rd, _ = cv2.Rodrigues(x[:3])
    delta = make_pose(Rd, x[3:])
    rmse = float(np.sqrt(np.mean(r[a <= 3 * k] ** 2))) if np.any(a <= 3 * k) else float("inf")
    return delta, (ok.sum() / len(p_src), rmse, cond)


def relative(T_w_ref: np.ndarray, T_w_cur: np.ndarray) -> np.ndarray:
    """T_ref_cur from two camera-to-world poses."""
    return invert(T_w_ref) @ T_w_cur
