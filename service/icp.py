"""Dense RGB-D registration: coarse-to-fine point-to-plane ICP with projective data
association (KinectFusion-style) joined with a direct photometric term (DVO-style), solved
by robust Gauss–Newton, vectorized over whole images.

It tracks where features cannot: textureless scenes (a plain cabinet on a white floor)
still have planes, and the colour edges between surfaces pin the sliding directions the
planes leave free. The Hessian's smallest eigenvalue tells when neither the geometry nor the
image constrains all six degrees of freedom (a single untextured wall), so a degenerate
solution is reported rather than trusted.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from client.frames import PinholeCamera
from client.geometry import invert, make_pose


@dataclass
class DepthLevel:
    """Vertex and normal maps of one pyramid level (camera frame), and optionally the grey
    image with its gradients sampled at the same pixels."""

    step: int
    fx: float
    fy: float
    cx: float
    cy: float
    vertices: np.ndarray  # (h, w, 3), NaN where invalid
    normals: np.ndarray  # (h, w, 3), NaN where invalid
    intensity: np.ndarray | None = None  # (h, w, 3) float32: grey in [0, 1], d/du, d/dv per level pixel
    _cache: dict = field(default_factory=dict, repr=False)

    @property
    def valid(self) -> np.ndarray:
        return np.isfinite(self.normals[..., 0])

    def points(self) -> tuple[np.ndarray, np.ndarray]:
        if "points" not in self._cache:
            ok = self.valid.ravel()
            self._cache["points"] = (np.ascontiguousarray(self.vertices.reshape(-1, 3)[ok]),
                                     np.ascontiguousarray(self.normals.reshape(-1, 3)[ok]))
        return self._cache["points"]

    def photometric_points(self, min_gradient: float, max_points: int) -> tuple[np.ndarray, np.ndarray]:
        """3-D points and grey values of the pixels with depth and a strong image gradient."""
        key = ("photo", min_gradient, max_points)
        if key not in self._cache:
            if self.intensity is None:
                self._cache[key] = (np.zeros((0, 3), np.float32), np.zeros(0, np.float32))
            else:
                g2 = self.intensity[..., 1] ** 2 + self.intensity[..., 2] ** 2
                sel = np.isfinite(self.vertices[..., 2]) & (g2 >= min_gradient ** 2)
                idx = np.flatnonzero(sel)
                if len(idx) > max_points:
                    idx = idx[np.argpartition(-g2.ravel()[idx], max_points)[:max_points]]
                self._cache[key] = (np.ascontiguousarray(self.vertices.reshape(-1, 3)[idx]),
                                    np.ascontiguousarray(self.intensity[..., 0].ravel()[idx]))
        return self._cache[key]


@dataclass
class IcpResult:
    pose: np.ndarray  # T_ref_cur
    inlier_ratio: float  # associated inliers / source points
    rmse: float  # point-to-plane residual of the inliers, metres
    conditioning: float  # smallest / largest eigenvalue of the normalized Hessian
    ok: bool


STEPS = (16, 8, 4)  # pyramid subsampling, coarse first: 40×30 … 160×120 at 640×480


def depth_pyramid(depth: np.ndarray, cam: PinholeCamera, steps=STEPS, min_depth=0.2, max_depth=6.0,
                  grey: np.ndarray | None = None) -> list[DepthLevel]:
    """Vertex + normal maps subsampled by each step (coarse first); with `grey` (H×W uint8,
    or float in [0, 1]) also the Gaussian-pyramid grey image and its gradients, which enable
    the photometric term of `register`. Steps must be powers of two when `grey` is given."""
    depth = np.where(np.isfinite(depth) & (depth >= min_depth) & (depth <= max_depth), depth, 0).astype(np.float32)
    images = {}
    if grey is not None:
        g = np.asarray(grey)
        g = g.astype(np.float32) / 255.0 if g.dtype == np.uint8 else g.astype(np.float32)
        if g.shape != depth.shape:
            raise ValueError(f"grey image {g.shape} does not match depth {depth.shape}")
        for s in steps:
            if s < 1 or s & (s - 1):
                raise ValueError(f"pyramid steps must be powers of two with a grey image, got {s}")
        s = 1
        images[1] = g
        while s < max(steps):
            g = cv2.pyrDown(g)
            s *= 2
            images[s] = g
    levels = []
    for s in steps:
        # Sample s·x of the full image: the pixel a Gaussian pyramid centres its level-x pixel on.
        d = depth[::s, ::s]
        h, w = d.shape
        fx, fy, cx, cy = cam.fx / s, cam.fy / s, cam.cx / s, cam.cy / s
        u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
        z = np.where(d > 0, d, np.nan)
        V = np.stack([(u - cx) / fx * z, (v - cy) / fy * z, z], axis=-1)
        inten = None
        if grey is not None:
            g = images[s]
            gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3, scale=1 / 8, borderType=cv2.BORDER_REPLICATE)
            gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3, scale=1 / 8, borderType=cv2.BORDER_REPLICATE)
            inten = np.ascontiguousarray(np.stack([g, gx, gy], axis=-1))
        levels.append(DepthLevel(s, fx, fy, cx, cy, V, _normals(V), inten))
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


@dataclass
class _Params:
    max_dist: float
    cos_max: float
    photometric_weight: float
    min_gradient: float
    max_photo_points: int
    sigma_g_min: float = 0.002
    sigma_i_min: float = 2.0 / 255


def _geometric(p_src, n_src, ref: DepthLevel, T, prm: _Params):
    """Point-to-plane residuals and Jacobians (left perturbation ω, τ) of the associated points."""
    R, t = T[:3, :3].astype(np.float32), T[:3, 3].astype(np.float32)
    p = p_src @ R.T + t
    h, w = ref.vertices.shape[:2]
    with np.errstate(invalid="ignore", divide="ignore"):
        iz = 1.0 / p[:, 2]
        u = np.rint(p[:, 0] * iz * ref.fx + ref.cx)
        v = np.rint(p[:, 1] * iz * ref.fy + ref.cy)
    inside = (p[:, 2] > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    idx = np.flatnonzero(inside)
    lin = v[idx].astype(np.intp) * w + u[idx].astype(np.intp)
    q = ref.vertices.reshape(-1, 3)[lin]
    n = ref.normals.reshape(-1, 3)[lin]
    ps = p[idx]
    diff = ps - q
    n_s = n_src[idx] @ R.T
    with np.errstate(invalid="ignore"):
        ok = (np.isfinite(n[:, 0]) & (np.einsum("ij,ij->i", diff, diff) < prm.max_dist ** 2)
              & (np.einsum("ij,ij->i", n, n_s) > prm.cos_max))
    ps, n, diff = ps[ok], n[ok], diff[ok]
    r = np.einsum("ij,ij->i", diff, n)
    J = np.concatenate([np.cross(ps, n), n], axis=1)
    return r, J, ps


def _photometric(p_src, i_src, ref: DepthLevel, T, prm: _Params):
    """Grey-value residuals I_ref(π(T p)) − I_src and their Jacobians (left perturbation)."""
    R, t = T[:3, :3].astype(np.float32), T[:3, 3].astype(np.float32)
    p = p_src @ R.T + t
    h, w = ref.vertices.shape[:2]
    with np.errstate(invalid="ignore", divide="ignore"):
        iz = 1.0 / p[:, 2]
        u = p[:, 0] * iz * ref.fx + ref.cx
        v = p[:, 1] * iz * ref.fy + ref.cy
    inside = (p[:, 2] > 0.05) & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    idx = np.flatnonzero(inside)
    u, v, ps, iz = u[idx], v[idx], p[idx], iz[idx]
    s = cv2.remap(ref.intensity, u.reshape(-1, 1), v.reshape(-1, 1), cv2.INTER_LINEAR,
                  borderMode=cv2.BORDER_REPLICATE).reshape(-1, 3)
    # Occlusion: the reference sees a nearer surface there.
    lin = np.rint(v).astype(np.intp) * w + np.rint(u).astype(np.intp)
    zr = ref.vertices[..., 2].ravel()[lin]
    with np.errstate(invalid="ignore"):
        vis = ~(ps[:, 2] > zr * 1.05 + 0.02)
    s, ps, iz, i0 = s[vis], ps[vis], iz[vis], i_src[idx][vis]
    r = s[:, 0] - i0
    gx, gy = s[:, 1] * ref.fx, s[:, 2] * ref.fy
    gp = np.stack([gx * iz, gy * iz, -(gx * ps[:, 0] + gy * ps[:, 1]) * iz * iz], axis=1)
    J = np.concatenate([np.cross(ps, gp), gp], axis=1)
    return r, J


def _mad(r: np.ndarray) -> float:
    return 1.4826 * float(np.median(np.abs(r - np.median(r)))) if len(r) else 0.0


def _huber(a: np.ndarray, k: float) -> np.ndarray:
    return np.where(a <= k, 1.0, k / np.maximum(a, 1e-12)).astype(np.float32)


def _linearize(src: DepthLevel, ref: DepthLevel, T: np.ndarray, prm: _Params):
    p_src, n_src = src.points()
    r_g, J_g, ps = _geometric(p_src, n_src, ref, T, prm)
    if len(r_g) < 30:
        return None
    sg = max(_mad(r_g), prm.sigma_g_min)
    w_g = _huber(np.abs(r_g) / sg, 1.345) / sg ** 2
    H = (J_g * w_g[:, None]).T.astype(np.float64) @ J_g
    b = (J_g * w_g[:, None]).T.astype(np.float64) @ r_g
    info = {"n_g": len(r_g), "N_g": len(p_src), "r_g": r_g, "ps": ps, "sg": sg, "H_g": H.copy()}
    use_photo = prm.photometric_weight > 0 and ref.intensity is not None and src.intensity is not None
    if use_photo:
        p_i, i_src = src.photometric_points(prm.min_gradient, prm.max_photo_points)
        if len(p_i) >= 30:
            r_i, J_i = _photometric(p_i, i_src, ref, T, prm)
            if len(r_i) >= 30:
                r_i = r_i - np.median(r_i)  # global brightness change
                si = max(_mad(r_i), prm.sigma_i_min)
                a = np.abs(r_i) / si
                nu = 5.0
                w_i = ((nu + 1) / (nu + a * a) * prm.photometric_weight / si ** 2).astype(np.float32)
                Hi = (J_i * w_i[:, None]).T.astype(np.float64) @ J_i
                H += Hi
                b += (J_i * w_i[:, None]).T.astype(np.float64) @ r_i
                info.update(n_i=len(r_i), N_i=len(p_i), r_i=r_i, si=si, H_i=Hi)
    return H, b, info


def _conditioning(H: np.ndarray, ps: np.ndarray) -> float:
    """Smallest / largest eigenvalue with rotation scaled to the scene's size."""
    scale = np.sqrt(np.mean(np.sum(ps.astype(np.float64) ** 2, axis=1)))
    d = 1.0 / np.array([scale] * 3 + [1.0] * 3)
    eig = np.linalg.eigvalsh(H * d[:, None] * d[None, :])
    return float(max(eig[0], 0.0) / eig[-1]) if eig[-1] > 0 else 0.0


def _exp(x: np.ndarray) -> np.ndarray:
    Rd, _ = cv2.Rodrigues(x[:3].reshape(3, 1))
    return make_pose(Rd, x[3:])


def _cost(src: DepthLevel, ref: DepthLevel, T: np.ndarray, prm: _Params, tau_g: float, tau_i: float) -> float:
    """Truncated quadratic cost over all source points (unassociated ones cost the maximum),
    comparable between different poses."""
    p_src, n_src = src.points()
    r_g, _, _ = _geometric(p_src, n_src, ref, T, prm)
    c = (np.minimum((r_g / tau_g) ** 2, 1).sum() + len(p_src) - len(r_g)) / max(len(p_src), 1)
    if prm.photometric_weight > 0 and ref.intensity is not None and src.intensity is not None:
        p_i, i_src = src.photometric_points(prm.min_gradient, prm.max_photo_points)
        if len(p_i):
            r_i, _ = _photometric(p_i, i_src, ref, T, prm)
            if len(r_i):
                r_i = r_i - np.median(r_i)
            c += (np.minimum((r_i / tau_i) ** 2, 1).sum() + len(p_i) - len(r_i)) / len(p_i)
    return float(c)


def _solve_level(src, ref, T, prm, iterations):
    last = None
    for _ in range(iterations):
        lin = _linearize(src, ref, T, prm)
        if lin is None:
            break
        H, b, info = lin
        last = (H, info)
        try:
            x = -np.linalg.solve(H + 1e-6 * np.trace(H) / 6 * np.eye(6), b)
        except np.linalg.LinAlgError:
            break
        T = _exp(x) @ T
        if np.linalg.norm(x[3:]) < 1e-5 and np.linalg.norm(x[:3]) < 1e-5:
            break
    return T, last


def register(src: list[DepthLevel], ref: list[DepthLevel], T_init: np.ndarray, iterations=(10, 10, 10),
             max_distance=(0.3, 0.15, 0.08), max_normal_angle_deg=40.0, min_inlier_ratio=0.3,
             min_conditioning=1e-3, photometric_weight=1.0, min_gradient=(0.01, 0.01, 0.01),
             max_photo_points=4000, hypotheses=True) -> IcpResult:
    """Align the source pyramid onto the reference one, starting at T_init (T_ref_src).

    With grey images in both pyramids a photometric term joins the point-to-plane one
    (`photometric_weight` scales it; 0 = geometry only)."""
    T = np.asarray(T_init, np.float64).copy()
    cos_max = np.cos(np.radians(max_normal_angle_deg))
    n = len(src)
    iterations, max_distance, min_gradient = (_per_level(x, n) for x in (iterations, max_distance, min_gradient))
    last = None
    for level, (s_lvl, r_lvl) in enumerate(zip(src, ref)):
        prm = _Params(max_distance[level], cos_max, photometric_weight, min_gradient[level], max_photo_points)
        if len(s_lvl.points()[0]) < 50:
            continue
        if level == 0 and hypotheses:
            cands = _hypotheses(T)
            best = None
            for T0 in cands:
                Tc, lc = _solve_level(s_lvl, r_lvl, T0, prm, iterations[level])
                c = _cost(s_lvl, r_lvl, Tc, prm, 0.02, 0.1)
                if best is None or c < best[0]:
                    best = (c, Tc, lc)
            _, T, lvl_last = best
        else:
            T, lvl_last = _solve_level(s_lvl, r_lvl, T, prm, iterations[level])
        last = lvl_last or last
    if last is None:
        return IcpResult(T, 0.0, np.inf, 0.0, False)
    H, info = last
    cond = _conditioning(H, info["ps"])
    r = info["r_g"]
    k = 3 * info["sg"]
    rmse = float(np.sqrt(np.mean(r[np.abs(r) <= k] ** 2))) if np.any(np.abs(r) <= k) else float("inf")
    ratio = info["n_g"] / max(info["N_g"], 1)
    ok = ratio >= min_inlier_ratio and cond >= min_conditioning
    return IcpResult(T, float(ratio), rmse, cond, bool(ok))


def _hypotheses(T: np.ndarray) -> list[np.ndarray]:
    rvec, _ = cv2.Rodrigues(T[:3, :3])
    half = make_pose(cv2.Rodrigues(rvec * 0.5)[0], T[:3, 3] * 0.5)
    return [T, half, np.eye(4)]


def _per_level(x, n):
    if np.isscalar(x):
        return (x,) * n
    x = tuple(x)
    if len(x) < n:
        x = x + (x[-1],) * (n - len(x))
    return x


def relative(T_w_ref: np.ndarray, T_w_cur: np.ndarray) -> np.ndarray:
    """T_ref_cur from two camera-to-world poses."""
    return invert(T_w_ref) @ T_w_cur
