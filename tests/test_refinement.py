"""Motion-only pose refinement with per-point uncertainty."""
import cv2
import numpy as np

from mnemoslam.client.kernel.geometry import invert, make_pose
from mnemoslam.service.tracking.refinement import mahalanobis2, refine_pose, sigma_from_hessian

K = np.array([[700.0, 0, 620], [0, 700.0, 185], [0, 0, 1]])


def _project(T_cw, X):
    p = X @ T_cw[:3, :3].T + T_cw[:3, 3]
    return (p[:, :2] / p[:, 2:]) * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]


def _camera(yaw=0.04, t=(0.05, -0.02, 1.0)):
    R, _ = cv2.Rodrigues(np.array([0.0, yaw, 0.0]))
    return make_pose(R, t)  # camera-to-world of the second view; the first is the identity


def _points(rng, n, zmin, zmax):
    z = rng.uniform(zmin, zmax, n)
    return np.c_[rng.uniform(-0.8, 0.8, n) * z, rng.uniform(-0.2, 0.2, n) * z, z]


def test_exact_observations_give_the_exact_pose():
    rng = np.random.default_rng(0)
    X = _points(rng, 200, 4, 30)
    pose = _camera()
    T_true = invert(pose)
    px = _project(T_true, X)
    start = make_pose(cv2.Rodrigues(np.array([0.01, -0.02, 0.005]))[0], T_true[:3, 3] + [0.1, -0.05, 0.2])
    rays = X / np.linalg.norm(X, axis=1, keepdims=True)
    T = refine_pose(start, K, X, px, np.ones(len(X)), rays, np.zeros(len(X)))
    np.testing.assert_allclose(T, T_true, atol=1e-7)
    assert np.all(mahalanobis2(T, K, X, px, np.ones(len(X)), rays, np.zeros(len(X))) < 1e-8)


def test_depth_uncertainty_only_widens_the_image_of_the_ray():
    """A far stereo point whose depth is 20 % off (2–3 σ) lands elsewhere on the image of its first
    ray (the epipolar line): with its depth uncertainty that is no outlier, while the same
    pixel error across the line still is."""
    rng = np.random.default_rng(1)
    X = _points(rng, 50, 25, 40)
    pose = _camera(t=(0.5, 0.0, 3.0))
    T = invert(pose)
    rays = X / np.linalg.norm(X, axis=1, keepdims=True)
    sigma_ray = X[:, 2] ** 2 * 1.0 / (700.0 * 0.54)  # 1 px disparity on a 0.54 m baseline
    px = _project(T, X * 1.2)  # observed where the true point (20 % farther) projects
    along = px - _project(T, X)
    across = along[:, ::-1] * [1, -1]  # the same offset, turned by 90°
    ones = np.ones(len(X))
    d_plain = mahalanobis2(T, K, X, px, ones, rays, np.zeros(len(X)))
    d_along = mahalanobis2(T, K, X, px, ones, rays, sigma_ray)
    d_across = mahalanobis2(T, K, X, _project(T, X) + across, ones, rays, sigma_ray)
    big = d_plain > 4  # more than 2 px off: an outlier without the depth uncertainty
    assert big.sum() > 10
    assert np.all(d_along[big] < 9) and np.all(d_along[big] < 0.5 * d_plain[big])  # within 3 σ
    np.testing.assert_allclose(d_across, d_plain, rtol=0.05)


def _pose_sigma(T_cw, X, px, ones, rays, zeros):
    """The σ the odometry takes: from the Hessian of the refinement at the pose."""
    return sigma_from_hessian(refine_pose(T_cw, K, X, px, ones, rays, zeros, hessian=True)[1])


def test_pose_sigma_matches_the_spread_of_refined_poses_and_grows_when_points_bunch():
    """The refinement's own uncertainty (its Hessian's inverse): over 200 noisy draws (1 px) the largest
    rotation / translation standard deviations of the refined poses are within 30 % of it; 40
    points bunched in one corner of the image give a larger σ than 40 spread over it (the
    odometry then also tries depth ICP: `odometry.confident_sigma_*`)."""
    rng = np.random.default_rng(3)
    T_true = invert(_camera())

    def spread(X, draws=200):
        rays = X / np.linalg.norm(X, axis=1, keepdims=True)
        px = _project(T_true, X)
        ones, zeros = np.ones(len(X)), np.zeros(len(X))
        rot, trans = [], []
        for _ in range(draws):
            T = refine_pose(T_true, K, X, px + rng.normal(0, 1.0, px.shape), ones, rays, zeros)
            D = T @ invert(T_true)
            rot.append(cv2.Rodrigues(D[:3, :3])[0].ravel())
            trans.append(T[:3, 3] - T_true[:3, 3])
        empirical = (np.sqrt(np.linalg.eigvalsh(np.cov(np.array(rot).T))[-1]),
                     np.sqrt(np.linalg.eigvalsh(np.cov(np.array(trans).T))[-1]))
        return empirical, _pose_sigma(T_true, X, px, ones, rays, zeros)

    wide = _points(rng, 40, 2, 6)
    (emp_r, emp_t), (sig_r, sig_t) = spread(wide)
    assert 0.7 < emp_r / sig_r < 1.3 and 0.7 < emp_t / sig_t < 1.3, (emp_r, sig_r, emp_t, sig_t)
    z = rng.uniform(2, 6, 40)
    bunched = np.c_[(0.3 + rng.uniform(-0.05, 0.05, 40)) * z, (0.1 + rng.uniform(-0.05, 0.05, 40)) * z, z]
    sig_r_b, sig_t_b = _pose_sigma(T_true, bunched, _project(T_true, bunched), np.ones(40),
                                   bunched / np.linalg.norm(bunched, axis=1, keepdims=True), np.zeros(40))
    assert sig_r_b > 3 * sig_r and sig_t_b > 3 * sig_t
