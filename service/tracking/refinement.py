"""Motion-only pose refinement with per-observation uncertainty (ORB-SLAM's pose
optimization, with the map points' own depth uncertainty).

Each local-map point is observed at a pixel whose noise grows with the keypoint's pyramid
level (σ = scale_factor^octave px). The point itself is only as good as the depth it was
created from: a stereo point 30 m away may be metres off along the ray it was seen on. That
error moves its projection along one image direction (the image of that ray), so it adds a
rank-one term to the pixel covariance:

    Σ = σ_px² I + σ_ray² m mᵀ,   m = ∂π(R X + t)/∂X · d  (d: unit ray of the first sighting)

A far point seen from almost the same direction has m ≈ 0 and keeps its full weight (it
fixes the rotation); once the camera has moved, its uncertain depth no longer pulls the
translation. The pose is refined by Gauss–Newton on the whitened residuals with Huber
weights, vectorized over the points.
"""
from __future__ import annotations

import cv2
import numpy as np

from mnemoslam.client.kernel.geometry import make_pose

HUBER_CHI = float(np.sqrt(5.991))  # Huber threshold on the Mahalanobis distance (χ², 2 dof, 95 %)


class _Observations:
    """Per-observation terms of the whitened problem at a pose: residuals r (n, k), Jacobians
    J (n, k, 6) with respect to a left perturbation ξ = (ω, τ), and the information
    Λ = diag(d) − c (d∘m)(d∘m)ᵀ (Sherman–Morrison of diag(1/d) + σ_ray² m mᵀ) kept factored.
    k = 2 (pixels) or 3 (pixels and the measured depth, weight 0 where none)."""

    def __init__(self, T_cw, K, X, px, sigma_px, rays, sigma_ray, z_meas=None, z_weight=None):
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        p = X @ T_cw[:3, :3].T + T_cw[:3, 3]
        x, y = p[:, 0], p[:, 1]
        z = np.maximum(p[:, 2], 1e-6)
        self.front = p[:, 2] > 1e-6
        iz = 1.0 / z
        xz, yz = x * iz, y * iz
        a, b = fx * iz, fy * iz
        rc = rays @ T_cw[:3, :3].T  # ray directions in the camera
        k = 2 if z_weight is None else 3
        n = len(p)
        r = np.empty((n, k))
        r[:, 0] = fx * xz + cx - px[:, 0]
        r[:, 1] = fy * yz + cy - px[:, 1]
        J = np.zeros((n, k, 6))
        J[:, 0, 0], J[:, 0, 1], J[:, 0, 2] = -fx * xz * yz, fx * (1 + xz * xz), -fx * yz
        J[:, 0, 3], J[:, 0, 5] = a, -a * xz
        J[:, 1, 0], J[:, 1, 1], J[:, 1, 2] = -fy * (1 + yz * yz), fy * xz * yz, fy * xz
        J[:, 1, 4], J[:, 1, 5] = b, -b * yz
        m = np.empty((n, k))
        m[:, 0] = a * (rc[:, 0] - xz * rc[:, 2])
        m[:, 1] = b * (rc[:, 1] - yz * rc[:, 2])
        d = np.empty((n, k))
        d[:, :2] = (1.0 / sigma_px ** 2)[:, None]
        if k == 3:
            r[:, 2] = p[:, 2] - z_meas
            J[:, 2, 0], J[:, 2, 1], J[:, 2, 5] = y, -x, 1.0
            m[:, 2] = rc[:, 2]
            d[:, 2] = z_weight
        self.r, self.J, self.d, self.m = r, J, d, m
        self.dm = d * m
        self.c = sigma_ray ** 2 / (1.0 + sigma_ray ** 2 * np.einsum("ni,ni->n", m, self.dm))

    def chi2(self) -> np.ndarray:
        r = self.r
        q = np.einsum("ni,ni->n", self.dm, r)
        return np.where(self.front, np.einsum("ni,ni,ni->n", self.d, r, r) - self.c * q * q, np.inf)

    def weights(self, chi: np.ndarray) -> np.ndarray:
        """Huber weights (n,) of the observations at Mahalanobis threshold `chi` (0 behind the camera)."""
        e = np.sqrt(np.maximum(self.chi2(), 0.0))
        return np.where(self.front, np.where(e <= chi, 1.0, chi / np.maximum(e, 1e-12)), 0.0)

    def normal_equations(self, w: np.ndarray, J: np.ndarray | None = None):
        """H, b of Σ w Jᵀ Λ J ξ = −Σ w Jᵀ Λ r; `J` (n, k, p) defaults to the pose Jacobian."""
        J = self.J if J is None else J
        n, k, p = J.shape
        wdJ = ((w[:, None] * self.d)[:, :, None] * J).reshape(n * k, p)  # w·diag(d)·J, stacked
        g = np.einsum("nk,nkj->nj", self.dm, J)  # Jᵀ d∘m
        q = np.einsum("ni,ni->n", self.dm, self.r)
        wcg = (w * self.c)[:, None] * g
        # the sums over observations as matrix products (BLAS), not one einsum over three operands
        H = wdJ.T @ J.reshape(n * k, p) - wcg.T @ g
        b = wdJ.T @ self.r.reshape(n * k) - wcg.T @ q
        return H, b


def _depth_terms(depth: np.ndarray, depth_sigma: np.ndarray):
    """The measured depths as a third residual: (depth with 0 where none, its weight 1/σ²
    (0 where none), Huber threshold per observation, mask of those with a depth)."""
    z = np.asarray(depth, np.float64)
    sz = np.asarray(depth_sigma, np.float64)
    has = np.isfinite(z) & np.isfinite(sz) & (sz > 0)
    weight = np.where(has, 1.0 / np.where(has, sz, 1.0) ** 2, 0.0)
    chi = np.where(has, np.sqrt(7.815), HUBER_CHI)  # χ² 95 %: 3 dof with a depth, 2 without
    return np.where(has, z, 0.0), weight, chi, has


def mahalanobis2(T_cw: np.ndarray, K: np.ndarray, world: np.ndarray, pixels: np.ndarray, sigma_px: np.ndarray,
                 rays: np.ndarray, sigma_ray: np.ndarray) -> np.ndarray:
    """Squared Mahalanobis distances (n,) of the pixel observations under the pose T_cw."""
    return _Observations(T_cw, K, np.asarray(world, np.float64), np.asarray(pixels, np.float64),
                         sigma_px, rays, sigma_ray).chi2()


def sigma_from_hessian(H: np.ndarray) -> tuple[float, float]:
    """(largest rotation σ in radians, largest translation σ in metres) of a 6×6 pose Hessian
    (rotation first), e.g. `refine_pose(..., hessian=True)`'s, Huber weights included;
    (inf, inf) when it is singular."""
    try:
        C = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return float("inf"), float("inf")
    var = np.linalg.eigvalsh(C[:3, :3])[-1], np.linalg.eigvalsh(C[3:, 3:])[-1]
    rotation, translation = (float(np.sqrt(v)) if v > 0 else float("inf") for v in var)
    return rotation, translation


def refine_pose(T_cw: np.ndarray, K: np.ndarray, world: np.ndarray, pixels: np.ndarray, sigma_px: np.ndarray,
                rays: np.ndarray, sigma_ray: np.ndarray, depth: np.ndarray | None = None,
                depth_sigma: np.ndarray | None = None, iterations: int = 10, hessian: bool = False):
    """Gauss–Newton refinement of the world-to-camera pose T_cw from 2-D observations of
    world points. `sigma_px` (n,) pixel noise, `rays` (n, 3) unit world directions along
    which each point is uncertain with `sigma_ray` (n,) metres. With `depth` (n,) and
    `depth_sigma` (n,) the depth this frame measured for an observation (NaN: none) is a
    third residual, as ORB-SLAM's stereo/RGB-D pose optimization uses it. Returns T_cw, or
    with `hessian` (T_cw, H): H the problem's 6×6 Hessian at the last iteration (None with
    fewer than 4 points), whose inverse is the pose's covariance (`sigma_from_hessian`)."""
    T = np.asarray(T_cw, np.float64).copy()
    X = np.asarray(world, np.float64)
    px = np.asarray(pixels, np.float64)
    H = None
    if len(X) < 4:
        return (T, H) if hessian else T
    z_meas = zw = None
    chi = np.full(len(X), HUBER_CHI)
    if depth is not None and depth_sigma is not None:
        z_meas, zw, chi, _ = _depth_terms(depth, depth_sigma)
    for _ in range(iterations):
        obs = _Observations(T, K, X, px, sigma_px, rays, sigma_ray, z_meas, zw)
        H, b = obs.normal_equations(obs.weights(chi))
        try:
            xi = -np.linalg.solve(H + 1e-9 * np.trace(H) * np.eye(6), b)
        except np.linalg.LinAlgError:
            break
        dR, _ = cv2.Rodrigues(xi[:3].reshape(3, 1))
        T = make_pose(dR, xi[3:]) @ T
        if np.linalg.norm(xi[:3]) < 1e-6 and np.linalg.norm(xi[3:]) < 1e-6:  # µrad, µm: converged
            break
    return (T, H) if hessian else T


def offset_information(T_cw: np.ndarray, K: np.ndarray, world: np.ndarray, pixels: np.ndarray, sigma_px: np.ndarray,
                       rays: np.ndarray, sigma_ray: np.ndarray, dworld: np.ndarray, depth: np.ndarray,
                       depth_sigma: np.ndarray, ddepth: np.ndarray) -> tuple[float, float]:
    """What the observations of a refined pose say about one more parameter δ that moves each
    world point along its ray by `dworld` (n,) metres per unit and each measured depth by
    `ddepth` (n,) (stereo: a disparity offset). Returns (g, I): the gradient and the
    information of δ with the pose marginalized (Schur complement), so that δ − g/I is this
    frame's estimate and I its weight. Same whitening and Huber weights as refine_pose."""
    X = np.asarray(world, np.float64)
    px = np.asarray(pixels, np.float64)
    z_meas, zw, chi, has = _depth_terms(depth, depth_sigma)
    obs = _Observations(np.asarray(T_cw, np.float64), K, X, px, sigma_px, rays, sigma_ray, z_meas, zw)
    # Jacobian of the residuals in δ: the point slides along its ray (image of the ray: m),
    # the measured depth moves too (the residual is predicted − measured).
    Jd = obs.m * np.asarray(dworld, np.float64)[:, None]
    Jd[:, 2] -= np.where(has, np.asarray(ddepth, np.float64), 0.0)
    H, b = obs.normal_equations(obs.weights(chi), np.concatenate([obs.J, Jd[:, :, None]], axis=2))  # (n, 3, 7)
    Hpp, Hpd = H[:6, :6], H[:6, 6]
    try:
        sol = np.linalg.solve(Hpp + 1e-9 * np.trace(Hpp) * np.eye(6), np.stack([Hpd, b[:6]], axis=1))
    except np.linalg.LinAlgError:
        return 0.0, 0.0
    info = float(H[6, 6] - Hpd @ sol[:, 0])
    grad = float(b[6] - Hpd @ sol[:, 1])
    return grad, max(info, 0.0)


def pose_normal_equations(T_cw: np.ndarray, K: np.ndarray, world: np.ndarray, pixels: np.ndarray,
                          sigma_px: np.ndarray, rays: np.ndarray, sigma_ray: np.ndarray,
                          chi: float | np.ndarray = HUBER_CHI, active: np.ndarray | None = None):
    """The whitened, Huber-weighted Gauss–Newton system of pixel observations of world points
    under the pose T_cw (same model as `refine_pose`: pixel noise `sigma_px`, each point
    uncertain along its unit ray `rays` by `sigma_ray` m), for solvers that join it with other
    terms. `active` (n,) bool leaves observations out (weight 0). Returns (H, b, chi2, w): H ξ
    = −b for a left perturbation ξ = (ω, τ) of T_cw, the squared Mahalanobis distances (n,)
    and the Huber weights (n,) used."""
    obs = _Observations(np.asarray(T_cw, np.float64), K, np.asarray(world, np.float64),
                        np.asarray(pixels, np.float64), sigma_px, rays, sigma_ray)
    w = obs.weights(np.broadcast_to(np.asarray(chi, np.float64), (len(obs.r),)))
    if active is not None:
        w = np.where(active, w, 0.0)
    H, b = obs.normal_equations(w)
    return H, b, obs.chi2(), w
