"""Dense RGB-D registration: coarse-to-fine point-to-plane ICP with projective data
association (KinectFusion-style) joined with a direct photometric term (DVO-style: the grey
value of each source pixel against the reference image at its warped position), solved by
robustly weighted Gauss–Newton, vectorized over whole images.

It tracks where features cannot: textureless scenes (a plain cabinet on a white floor)
still have planes, and the colour edges between surfaces pin the sliding directions the
planes leave free. The Hessian's smallest eigenvalue tells when neither the geometry nor the
image constrains all six degrees of freedom (a single untextured wall), so a degenerate
solution is reported rather than trusted.

Without grey images (`depth_pyramid(..., grey=None)`) the registration is geometric only.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from mnemoslam.client.kernel.frames import PinholeCamera
from mnemoslam.client.kernel.geometry import invert, make_pose


@dataclass
class DepthLevel:
    """Vertex and normal maps of one pyramid level (camera frame) and, when the pyramid was
    built with a grey image, the blurred grey level with its gradients at the same pixels."""

    step: int
    fx: float
    fy: float
    cx: float
    cy: float
    vertices: np.ndarray  # (h, w, 3) float32, NaN where invalid
    normals: np.ndarray  # (h, w, 3) float32, NaN where invalid
    intensity: np.ndarray | None = None  # (h, w, 3) float32: grey in [0, 1], d/du, d/dv per level pixel
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def valid(self) -> np.ndarray:
        return np.isfinite(self.normals[..., 0])

    def points(self) -> tuple[np.ndarray, np.ndarray]:
        """Vertices and normals (N, 3) of the pixels with a valid normal."""
        ok = self.valid.ravel()
        return self.vertices.reshape(-1, 3)[ok], self.normals.reshape(-1, 3)[ok]

    # -- arrays for the solver, built on first use (planar: one contiguous row per coordinate)
    def _source_geometry(self) -> tuple[np.ndarray, np.ndarray]:
        """Vertices and normals (3, N) of the valid pixels."""
        c = self._cache.get("src_geo")
        if c is None:
            idx = np.flatnonzero(self.valid.ravel())
            c = self._cache["src_geo"] = (np.ascontiguousarray(self.vertices.reshape(-1, 3)[idx].T),
                                          np.ascontiguousarray(self.normals.reshape(-1, 3)[idx].T))
        return c

    def _source_photometric(self, min_gradient: float, max_points: int) -> tuple[np.ndarray, np.ndarray]:
        """Vertices (3, N) and grey values (N,) of the pixels with a valid normal (depth, and
        no depth edge next to it: an edge pixel's grey mixes two surfaces that move apart
        with parallax) and a gradient of at least `min_gradient` per level pixel (the
        strongest `max_points` of them)."""
        key = ("src_photo", min_gradient, max_points)
        c = self._cache.get(key)
        if c is None:
            if self.intensity is None:
                c = (np.zeros((3, 0), np.float32), np.zeros(0, np.float32))
            else:
                g2 = (self.intensity[..., 1] ** 2 + self.intensity[..., 2] ** 2).ravel()
                idx = np.flatnonzero(self.valid.ravel() & (g2 >= min_gradient ** 2))
                if len(idx) > max_points:
                    idx = np.sort(idx[np.argpartition(-g2[idx], max_points)[:max_points]])
                c = (np.ascontiguousarray(self.vertices.reshape(-1, 3)[idx].T),
                     np.ascontiguousarray(self.intensity[..., 0].ravel()[idx]))
            self._cache[key] = c
        return c

    def _reference_geometry(self) -> np.ndarray:
        """(5, (h+2)·(w+2)): normal, plane offset n·q and depth of every pixel, with a NaN
        border so that clipped indices of points projecting outside gather invalid entries."""
        g = self._cache.get("ref_geo")
        if g is None:
            h, w = self.vertices.shape[:2]
            g = np.full((5, h + 2, w + 2), np.nan, np.float32)
            n = np.moveaxis(self.normals, -1, 0)
            g[:3, 1:-1, 1:-1] = n
            g[3, 1:-1, 1:-1] = np.einsum("kij,kij->ij", n, np.moveaxis(self.vertices, -1, 0))
            g[4, 1:-1, 1:-1] = self.vertices[..., 2]
            g = self._cache["ref_geo"] = g.reshape(5, -1)
        return g

    def _reference_photometric(self) -> np.ndarray:
        """(h, w, 4): grey, d/du, d/dv and depth (invalid = far), sampled by one remap."""
        g = self._cache.get("ref_photo")
        if g is None:
            z = self.vertices[..., 2]
            g = self._cache["ref_photo"] = np.ascontiguousarray(np.concatenate(
                [self.intensity, np.where(np.isfinite(z), z, 1e3)[..., None]], axis=-1), dtype=np.float32)
        return g


@dataclass
class IcpResult:
    pose: np.ndarray  # T_ref_cur
    inlier_ratio: float  # associated geometric inliers / source points with a normal
    rmse: float  # point-to-plane residual of the inliers, metres
    conditioning: float  # smallest / largest eigenvalue of the normalized Hessian (geometric + photometric)
    ok: bool


STEPS = (16, 8, 4)  # pyramid subsampling, coarse first: 40×30 … 160×120 at 640×480


def depth_pyramid(depth: np.ndarray, cam: PinholeCamera, steps=STEPS, min_depth=0.2, max_depth=6.0,
                  grey: np.ndarray | None = None) -> list[DepthLevel]:
    """Vertex + normal maps subsampled by each step (coarse first).

    With `grey` (H×W uint8 or float in [0, 1], or a BGR image; registered to the depth) every level also
    holds the Gaussian-pyramid grey image and its gradients, which enables the photometric
    term of `register`; the steps must then be powers of two. Level pixel x samples full
    image pixel step·x, the centre of a Gaussian pyramid's level pixel.

    A camera with lens distortion: the depth (nearest) and grey (bilinear) images are first
    remapped to its pinhole camera (`PinholeCamera.undistort_maps`, computed once), as ICP both
    back-projects pixels and projects points into the reference image; the levels then hold
    the pinhole geometry (a depth value stays the z of its own ray).
    """
    depth = np.where(np.isfinite(depth) & (depth >= min_depth) & (depth <= max_depth), depth, 0).astype(np.float32)
    if cam.distorted:
        maps = cam.undistort_maps()
        depth = cv2.remap(depth, *maps, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    images = {}
    if grey is not None:
        g = np.asarray(grey)
        if g.ndim == 3:
            g = cv2.cvtColor(g, cv2.COLOR_BGR2GRAY)
        g = g.astype(np.float32) / 255.0 if g.dtype == np.uint8 else g.astype(np.float32)
        if g.shape != depth.shape:
            raise ValueError(f"grey image {g.shape} does not match the depth image {depth.shape}")
        if cam.distorted:
            g = cv2.remap(g, *cam.undistort_maps(), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        bad = [s for s in steps if s < 1 or s & (s - 1)]
        if bad:
            raise ValueError(f"pyramid steps must be powers of two with a grey image, got {bad}")
        s, images[1] = 1, g
        while s < max(steps):
            g = cv2.pyrDown(g)
            s *= 2
            images[s] = g
    levels = []
    for s in steps:
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
            inten = np.stack([g, gx, gy], axis=-1)
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
        edge = ((np.linalg.norm(dx, axis=-1, keepdims=True) > 0.1 * z)
                | (np.linalg.norm(dy, axis=-1, keepdims=True) > 0.1 * z))
        flip = np.sum(n * V, axis=-1, keepdims=True) > 0
    n = np.where(flip, -n, n)
    return np.where(edge | ~np.isfinite(norm) | (norm == 0), np.nan, n).astype(np.float32)


# ---------------------------------------------------------------------------------------------
# Solver
# ---------------------------------------------------------------------------------------------

@dataclass
class _LevelConfig:
    iterations: int
    max_dist: float  # metres: association gate on the point-to-plane and the depth difference
    cos_max: float  # normal-angle gate
    photometric_weight: float
    min_gradient: float
    max_photo_points: int
    tolerance: float  # stop when the update is below this (metres and radians)
    sigma_g: float  # floor of the robust point-to-plane scale, metres
    sigma_i: float  # floor of the robust grey-value scale
    huber: float = 1.345  # Huber threshold of the geometric weights, in robust scales
    nu: float = 5.0  # Student-t degrees of freedom of the photometric weights


# Truncation of the cost that compares start hypotheses.
_COST_TAU_G = 0.02
_COST_TAU_I = 0.1


def _rows(p: np.ndarray, g: np.ndarray, r: np.ndarray, sw: np.ndarray) -> np.ndarray:
    """(7, N): sqrt(w)·[p × g; g; r], the whitened Jacobian of g·(exp(δ) p) with respect to
    the left perturbation δ = (ω, τ), and the whitened residual."""
    A = np.empty((7, p.shape[1]), np.float32)
    A[0] = p[1] * g[2] - p[2] * g[1]
    A[1] = p[2] * g[0] - p[0] * g[2]
    A[2] = p[0] * g[1] - p[1] * g[0]
    A[3:6] = g
    A[6] = r
    A *= sw
    return A


def _geometric(P, Nn, ref: DepthLevel, R, t, cfg: _LevelConfig):
    """Point-to-plane residuals n·(T p − q) of the source points associated projectively,
    gated on the residual, the depth difference and the normal angle. Returns the residuals,
    the transformed points (3, M) and the reference normals (3, M)."""
    p = R @ P + t[:, None]
    h, w = ref.vertices.shape[:2]
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        iz = 1.0 / p[2]
        iz[p[2] <= 0] = np.nan
        # Pixel + 1 in the padded map, rounded (truncation of u + 1.5 ≥ 0); NaN → clipped to the border.
        ui = np.clip((p[0] * iz * ref.fx + (ref.cx + 1.5)).astype(np.int32), 0, w + 1)
        vi = np.clip((p[1] * iz * ref.fy + (ref.cy + 1.5)).astype(np.int32), 0, h + 1)
    g = np.take(ref._reference_geometry(), vi * (w + 2) + ui, axis=1)
    r = g[0] * p[0] + g[1] * p[1] + g[2] * p[2] - g[3]
    n_s = R @ Nn
    cos = g[0] * n_s[0] + g[1] * n_s[1] + g[2] * n_s[2]
    with np.errstate(invalid="ignore"):
        ok = np.flatnonzero((np.abs(r) < cfg.max_dist) & (np.abs(p[2] - g[4]) < cfg.max_dist) & (cos > cfg.cos_max))
    return r[ok], np.take(p, ok, axis=1), np.take(g[:3], ok, axis=1)


def _photometric(P, I_src, ref: DepthLevel, R, t):
    """Grey-value residuals I_ref(π(T p)) − I_src (bilinear) of the source points that land
    inside the reference image and are not occluded there. Returns the residuals, the
    transformed points (3, M) and the image gradient as a 3-D gradient dI/dp (3, M)."""
    p = R @ P + t[:, None]
    with np.errstate(invalid="ignore", divide="ignore"):
        iz = 1.0 / p[2]
        iz[p[2] <= 0.05] = np.nan
        u = (p[0] * iz * ref.fx + ref.cx).reshape(-1, 1)
        v = (p[1] * iz * ref.fy + ref.cy).reshape(-1, 1)
    s = cv2.remap(ref._reference_photometric(), u, v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                  borderValue=(np.nan,) * 4).reshape(-1, 4)
    r = s[:, 0] - I_src
    with np.errstate(invalid="ignore"):
        # Inside the image, and the reference does not see a clearly nearer surface there.
        ok = np.flatnonzero(np.isfinite(r) & np.isfinite(iz) & (p[2] <= s[:, 3] * 1.05 + 0.02))
    s, p, iz = np.take(s, ok, axis=0), np.take(p, ok, axis=1), iz[ok]
    gx, gy = s[:, 1] * (ref.fx * iz), s[:, 2] * (ref.fy * iz)
    return r[ok], p, np.stack([gx, gy, -(gx * p[0] + gy * p[1]) * iz])


def _median(a: np.ndarray) -> float:
    k = len(a) // 2
    return float(np.partition(a, k)[k]) if len(a) else 0.0


def _normal_equations(src: DepthLevel, ref: DepthLevel, T: np.ndarray, cfg: _LevelConfig):
    """The robustly weighted Gauss–Newton system (H, b: H x = -b) of the joint problem at T
    and its statistics, or None when too few points associate. Each term is whitened by its
    own robust scale (MAD, floored), so `photometric_weight` is the relative weight of
    equally noisy residuals: Huber weights on the point-to-plane residuals, Student-t weights
    on the grey-value ones (after removing their median, a global brightness change)."""
    R, t = T[:3, :3].astype(np.float32), T[:3, 3].astype(np.float32)
    P, Nn = src._source_geometry()
    r_g, ps, n = _geometric(P, Nn, ref, R, t, cfg)
    if len(r_g) < 30:
        return None
    a = np.abs(r_g)
    sg = max(1.4826 * _median(a), cfg.sigma_g)
    k = cfg.huber * sg
    sw = np.sqrt(np.minimum(1.0, k / np.maximum(a, 1e-12)), dtype=np.float32) * np.float32(1 / sg)
    blocks = [_rows(ps, n, r_g, sw)]
    st = {"n_g": len(r_g), "N_g": P.shape[1], "r_g": r_g, "ps": ps, "sg": sg, "n_i": 0,
          "cost": (np.minimum(r_g * r_g / _COST_TAU_G ** 2, 1).sum() + P.shape[1] - len(r_g)) / P.shape[1]}
    if cfg.photometric_weight > 0 and ref.intensity is not None and src.intensity is not None:
        Pi, I_src = src._source_photometric(cfg.min_gradient, cfg.max_photo_points)
        if Pi.shape[1] >= 30:
            r_i, pi, gp = _photometric(Pi, I_src, ref, R, t)
            if len(r_i) >= 30:
                r_i = r_i - _median(r_i)
                a = np.abs(r_i)
                si = max(1.4826 * _median(a), cfg.sigma_i)
                sw = np.sqrt((cfg.nu + 1) / (cfg.nu + (a / si) ** 2) * (cfg.photometric_weight / si ** 2),
                             dtype=np.float32)
                blocks.append(_rows(pi, gp, r_i, sw))
                st["cost"] += (np.minimum(r_i * r_i / _COST_TAU_I ** 2, 1).sum() + Pi.shape[1] - len(r_i)) / Pi.shape[1]
                st.update(n_i=len(r_i), si=si)
    A = blocks[0] if len(blocks) == 1 else np.concatenate(blocks, axis=1)
    M = (A @ A.T).astype(np.float64)
    return M[:6, :6], M[:6, 6], st


def _solve_level(src: DepthLevel, ref: DepthLevel, T: np.ndarray, cfg: _LevelConfig, iterations: int):
    """Gauss–Newton at one level. Returns the pose and the last system (H, stats) or None."""
    last = None
    for _ in range(iterations):
        ne = _normal_equations(src, ref, T, cfg)
        if ne is None:
            break
        H, b, st = ne
        last = (H, st)
        try:
            x = -np.linalg.solve(H + (1e-9 * np.trace(H)) * np.eye(6), b)
        except np.linalg.LinAlgError:
            break
        T = _exp(x) @ T
        if np.linalg.norm(x[3:]) < cfg.tolerance and np.linalg.norm(x[:3]) < cfg.tolerance:
            break
    return T, last


def _conditioning(H: np.ndarray, ps: np.ndarray) -> float:
    """Smallest / largest eigenvalue of H with rotation scaled to the scene's size."""
    scale = float(np.sqrt(np.mean(np.sum(ps.astype(np.float64) ** 2, axis=0))))
    d = 1.0 / np.array([scale] * 3 + [1.0] * 3)
    eig = np.linalg.eigvalsh(H * d[:, None] * d[None, :])
    return float(max(eig[0], 0.0) / eig[-1]) if eig[-1] > 0 else 0.0


def _exp(x: np.ndarray) -> np.ndarray:
    Rd, _ = cv2.Rodrigues(np.asarray(x[:3], np.float64).reshape(3, 1))
    return make_pose(Rd, x[3:])


def _hypotheses(T: np.ndarray) -> list[np.ndarray]:
    """The prediction, half of it and no motion (only the prediction when it is no motion)."""
    rvec, _ = cv2.Rodrigues(T[:3, :3])
    if np.linalg.norm(T[:3, 3]) < 1e-3 and np.linalg.norm(rvec) < 1e-3:
        return [T]
    half = make_pose(cv2.Rodrigues(rvec * 0.5)[0], T[:3, 3] * 0.5)
    return [T, half, np.eye(4)]


def _per_level(x, n: int) -> tuple:
    if np.isscalar(x):
        return (x,) * n
    x = tuple(x)
    return x + (x[-1],) * (n - len(x)) if len(x) < n else x


def register(src: list[DepthLevel], ref: list[DepthLevel], T_init: np.ndarray, iterations=(10, 15, 20),
             max_distance=(0.3, 0.15, 0.08), max_normal_angle_deg=40.0, min_inlier_ratio=0.3,
             min_conditioning=1e-3, *, photometric_weight=(3.0, 3.0, 1.0), min_gradient=0.01,
             max_photo_points=4000, tolerance=(1e-3, 5e-4, 1e-4), geometric_sigma=(0.01, 0.005, 0.002),
             photometric_sigma=(0.03, 0.02, 0.008), hypotheses=True, hypothesis_iterations=3) -> IcpResult:
    """Align the source pyramid onto the reference one, starting at T_init (T_ref_src).

    Per-level arguments (coarse first) take a tuple or one value for all levels; a short
    tuple repeats its last value.

    - With grey images in both pyramids a photometric term joins the point-to-plane one;
      `photometric_weight` is its weight relative to the geometric term once both are
      whitened by their robust scales (0: geometry only). `min_gradient` (grey levels / 255
      per level pixel) and `max_photo_points` select its source pixels.
    - `geometric_sigma` (metres) and `photometric_sigma` (grey / 255) floor the robust scales.
    - `tolerance`: a level stops when the update is below it (metres, radians).
    - With `hypotheses` the coarsest level also starts from half of T_init and from no motion;
      after `hypothesis_iterations` the start with the lowest truncated cost goes on.
    - `ok` means enough associated points (`min_inlier_ratio`) and a well-conditioned joint
      Hessian (`min_conditioning`).
    """
    T = np.asarray(T_init, np.float64).copy()
    cos_max = float(np.cos(np.radians(max_normal_angle_deg)))
    n = len(src)
    per = [_per_level(x, n) for x in (iterations, max_distance, photometric_weight, min_gradient, tolerance,
                                      geometric_sigma, photometric_sigma)]
    last = None
    first = True
    for level, (s_lvl, r_lvl) in enumerate(zip(src, ref)):
        it, md, pw, mg, tol, sgm, sim = (x[level] for x in per)
        cfg = _LevelConfig(int(it), md, cos_max, pw, mg, max_photo_points, tol, sgm, sim)
        if cfg.iterations <= 0 or s_lvl._source_geometry()[0].shape[1] < 50:
            continue
        if first and hypotheses:
            probe = min(hypothesis_iterations, cfg.iterations)
            best: tuple | None = None
            for T0 in _hypotheses(T):
                Tc, lc = _solve_level(s_lvl, r_lvl, T0, cfg, probe)
                c = lc[1]["cost"] if lc else np.inf
                if best is None or c < best[0]:
                    best = (c, Tc, lc)
            assert best is not None  # _hypotheses gives one at least
            _, T, lvl_last = best
            if cfg.iterations > probe:
                T, lc = _solve_level(s_lvl, r_lvl, T, cfg, cfg.iterations - probe)
                lvl_last = lc or lvl_last
        else:
            T, lvl_last = _solve_level(s_lvl, r_lvl, T, cfg, cfg.iterations)
        first = False
        last = lvl_last or last
    if last is None:
        return IcpResult(T, 0.0, np.inf, 0.0, False)
    H, st = last
    cond = _conditioning(H, st["ps"])
    r = st["r_g"]
    inl = np.abs(r) <= 3 * st["sg"]
    rmse = float(np.sqrt(np.mean(r[inl] ** 2))) if inl.any() else float("inf")
    ratio = st["n_g"] / max(st["N_g"], 1)
    ok = ratio >= min_inlier_ratio and cond >= min_conditioning
    return IcpResult(T, float(ratio), rmse, cond, bool(ok))


def relative(T_w_ref: np.ndarray, T_w_cur: np.ndarray) -> np.ndarray:
    """T_ref_cur from two camera-to-world poses."""
    return invert(T_w_ref) @ T_w_cur
