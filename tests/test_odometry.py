"""Tracking front end: PnP on synthetic correspondences, depth/stereo back-projection,
keyframe decisions and loss recovery."""
import cv2
import numpy as np
import pytest

from mnemoslam.client.kernel.frames import Calibration, Frame, PinholeCamera
from mnemoslam.client.kernel.geometry import invert, make_pose, rotation_angle
from mnemoslam.service.config import load_config
from mnemoslam.service.tracking.features import FeatureExtractor, FrameFeatures
from mnemoslam.service.tracking.keyframes import KeyframePolicy
from mnemoslam.service.tracking.odometry import Odometry, TrackResult

CAM = PinholeCamera(525.0, 525.0, 319.5, 239.5, 640, 480)


def _scene(n=400, seed=0):
    rng = np.random.default_rng(seed)
    pts = np.c_[rng.uniform(-2, 2, n), rng.uniform(-1.5, 1.5, n), rng.uniform(2, 5, n)]
    desc = rng.integers(0, 256, (n, 32), dtype=np.uint8)
    return pts, desc


def _observe(pts_w, desc, pose, noise=0.0, outliers=0.0, seed=1):
    """Features of a camera at `pose` seeing world points: pixels, camera-frame 3-D."""
    rng = np.random.default_rng(seed)
    T_cw = invert(pose)
    pc = pts_w @ T_cw[:3, :3].T + T_cw[:3, 3]
    uv = pc[:, :2] / pc[:, 2:] * [CAM.fx, CAM.fy] + [CAM.cx, CAM.cy]
    uv = uv + rng.normal(0, noise, uv.shape) if noise else uv
    bad = rng.random(len(uv)) < outliers
    uv[bad] = rng.uniform([0, 0], [640, 480], (bad.sum(), 2))
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < 640) & (uv[:, 1] >= 0) & (uv[:, 1] < 480)
    return FrameFeatures(uv[inside].astype(np.float32), desc[inside], pc[inside].astype(np.float32),
                         np.zeros(inside.sum(), np.int8)), bad[inside]


def test_pnp_recovers_known_motion_with_noise_and_outliers():
    pts, desc = _scene()
    cfg = load_config()
    odo = Odometry(CAM, cfg.odometry)
    f0, _ = _observe(pts, desc, np.eye(4))
    assert odo.track(f0, 0.0).status == "init"
    R, _ = cv2.Rodrigues(np.array([0.03, -0.05, 0.02]))
    truth = make_pose(R, [0.08, -0.02, 0.12])
    f1, bad = _observe(pts, desc, truth, noise=0.5, outliers=0.2)
    res = odo.track(f1, 1 / 30)
    assert res.status == "ok"
    err = invert(truth) @ res.pose
    assert np.linalg.norm(err[:3, 3]) < 0.005
    assert np.degrees(rotation_angle(err[:3, :3])) < 0.2
    # Outliers are rejected: almost no injected outlier counts as an inlier.
    assert (res.inlier_mask & bad).sum() <= 2
    assert res.inliers >= 0.7 * (~bad).sum()


def test_lost_then_new_segment():
    pts, desc = _scene()
    cfg = load_config(overrides={"odometry": {"lost_frames_reset": 2, "icp_fallback": False}})
    odo = Odometry(CAM, cfg.odometry)
    odo.track(_observe(pts, desc, np.eye(4))[0], 0.0)
    rng = np.random.default_rng(5)
    other = FrameFeatures(rng.uniform(0, 480, (300, 2)).astype(np.float32),
                          rng.integers(0, 256, (300, 32), dtype=np.uint8),
                          np.c_[rng.uniform(-1, 1, (300, 2)), rng.uniform(1, 3, 300)].astype(np.float32),
                          np.zeros(300, np.int8))
    assert odo.track(other, 0.1).status == "lost"
    second = odo.track(other, 0.2)
    assert second.status == "init" and second.segment == 1
    np.testing.assert_allclose(second.pose, np.eye(4))  # continues from the last known pose


def test_depth_backprojection_rejects_invalid_and_edges():
    cfg = load_config()
    ex = FeatureExtractor(Calibration(CAM), cfg.features, cfg.stereo)
    depth = np.full((480, 640), 2.0, np.float32)
    depth[:, 320:] = 4.0  # a depth edge at column 320
    depth[100:140, 100:140] = np.nan
    depth[300:340, 100:140] = 0.0
    xy = np.array([[200, 200], [320, 200], [120, 120], [120, 320], [500, 400]], np.float32)
    pts = ex._depth_points(depth, xy, xy)  # (no distortion: raw and undistorted pixels alike)
    assert np.allclose(pts[0], [(200 - CAM.cx) / CAM.fx * 2, (200 - CAM.cy) / CAM.fy * 2, 2.0], atol=1e-5)
    assert np.isnan(pts[1:4, 2]).all()  # edge, NaN, zero
    assert pts[4, 2] == pytest.approx(4.0)


def test_stereo_depth_from_shifted_texture():
    rng = np.random.default_rng(3)
    tex = cv2.GaussianBlur((rng.random((480, 700)) * 255).astype(np.uint8), (0, 0), 1.5)
    tex = cv2.equalizeHist(tex)
    disparity = 21
    left = tex[:, :640].copy()
    right = tex[:, disparity:disparity + 640].copy()  # x_right = x_left - disparity
    cal = Calibration(CAM, baseline=0.1, depth_scale=1.0)
    cfg = load_config()
    ex = FeatureExtractor(cal, cfg.features, cfg.stereo)
    f = ex.extract(Frame(0, 0.0, left, right=right))
    z = f.points[f.has_depth, 2]
    assert len(z) > 200
    expected = CAM.fx * 0.1 / disparity
    assert np.median(np.abs(z - expected)) < 0.02 * expected


def test_keyframe_policy():
    cfg = load_config()
    pol = KeyframePolicy(cfg.keyframe)
    assert pol.decide(TrackResult("init", np.eye(4), 300)) == "init"
    assert pol.decide(TrackResult("ok", make_pose(np.eye(3), [0.05, 0, 0]), 290)) is None
    assert pol.decide(TrackResult("ok", make_pose(np.eye(3), [0.11, 0, 0]), 290)) == "motion"
    R, _ = cv2.Rodrigues(np.array([0, 0.12, 0]))
    assert pol.decide(TrackResult("ok", make_pose(R, [0.11, 0, 0]), 280)) == "motion"
    assert pol.decide(TrackResult("ok", make_pose(R, [0.11, 0, 0]), 100)) == "quality"
    assert pol.decide(TrackResult("lost", None)) is None


def _look_at(eye, target):
    """Camera-to-world pose at `eye` whose optical axis points at `target` (y down)."""
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    return make_pose(np.stack([x, np.cross(z, x), z], axis=1), eye)


def test_map_point_fusion_averages_readings_and_gates_outliers():
    """`odometry.map_point_fusion` (LocalMap.fuse): a point refined by the depth readings of
    views 40° apart ends up far closer to the truth than its first reading (each reading is
    uncertain along its own ray: information rotated into the world, not averaged as
    isotropic points, the per-axis error bounds it); a reading 20σ off (a depth edge) is
    left out, and a point stops moving after `max_readings`."""
    rng = np.random.default_rng(3)
    n, sz = 300, 0.02  # depth σ (m), much larger than the lateral σ (~2-4 mm at 1-2 m)
    truth = np.c_[rng.uniform(-0.3, 0.3, n), rng.uniform(-0.3, 0.3, n), rng.uniform(1.8, 2.2, n)]
    desc = rng.integers(0, 256, (n, 32), dtype=np.uint8)
    centre = np.array([0.0, 0.0, 2.0])

    def reading(pose, bad=None):
        T_cw = invert(pose)
        pc = truth @ T_cw[:3, :3].T + T_cw[:3, 3]
        pc *= 1 + rng.normal(0, sz, (n, 1)) / pc[:, 2:]  # depth noise along the ray
        if bad is not None:
            pc[bad] *= 1 + 20 * sz / pc[bad, 2:]
        uv = pc[:, :2] / pc[:, 2:] * [CAM.fx, CAM.fy] + [CAM.cx, CAM.cy]
        return FrameFeatures(uv.astype(np.float32), desc, pc.astype(np.float32), np.zeros(n, np.int8),
                             depth_sigma=np.full(n, sz, np.float32))

    lmap = Odometry(CAM, load_config().odometry).map
    lmap.update(1, reading(np.eye(4)), np.eye(4), np.full(n, -1))
    first = np.abs(lmap.points - truth)
    poses = [_look_at(centre + 2 * np.array([np.sin(a), 0.0, -np.cos(a)]), centre)
             for a in np.radians([-40, 40, -20, 20, -30, 30, -10, 10])]
    for pose in poses:
        assert lmap.fuse(reading(pose), pose, np.arange(n), gate=3.0, max_readings=8) > 0.9 * n
    fused = np.abs(lmap.points - truth)
    # x and z: fused along the 9 rays (a first reading's error is all along z); y: lateral only
    assert np.median(fused[:, 2]) < 0.35 * np.median(first[:, 2])
    assert np.median(fused[:, 0]) < 0.006 and np.median(fused[:, 1]) < 0.002
    full = lmap.fused == 8  # a few readings fall beyond the 3σ gate (χ², 3 dof: ~3 %)
    assert full.mean() > 0.8 and lmap.fused.max() == 8 and np.all(lmap.sigma[full] < 0.5 * sz)
    # full: a 9th reading changes nothing
    before = lmap.points.copy()
    lmap.fuse(reading(poses[0]), poses[0], np.arange(n), gate=3.0, max_readings=8)
    assert np.array_equal(lmap.points[full], before[full])
    # a fresh map, one gross reading per point (20σ along the ray) after a good one: left out
    lmap.clear()
    lmap.update(1, reading(np.eye(4)), np.eye(4), np.full(n, -1))
    lmap.fuse(reading(poses[0]), poses[0], np.arange(n), gate=3.0, max_readings=8)
    good = lmap.points.copy()
    bad = np.ones(n, bool)
    assert lmap.fuse(reading(poses[1], bad), poses[1], np.arange(n), gate=3.0, max_readings=8) < 0.05 * n
    assert np.median(np.linalg.norm(lmap.points - good, axis=1)) < 1e-9


def test_ransac_on_the_fine_keypoints_keeps_the_coarse_inliers(monkeypatch):
    """`odometry.pnp_ransac_max_sigma`: RANSAC samples and scores only the matches of fine
    keypoints (its one pixel threshold fits them), and the re-selection under the refined pose
    takes the coarse keypoints' matches in at their own σ: half the keypoints here sit at octave 4
    (σ 2.07 px) with 1.6 px of noise, a third of them beyond RANSAC's 2 px."""
    pts, desc = _scene(n=600)
    sizes = []
    real = cv2.solvePnPRansac

    def counted(world, pixels, *args, **kwargs):
        sizes.append(len(world))
        return real(world, pixels, *args, **kwargs)

    monkeypatch.setattr(cv2, "solvePnPRansac", counted)  # (the module the tracker calls it from)
    R, _ = cv2.Rodrigues(np.array([0.03, -0.05, 0.02]))
    truth = make_pose(R, [0.08, -0.02, 0.12])
    f0, _ = _observe(pts, desc, np.eye(4))
    f1, _ = _observe(pts, desc, truth, noise=0.3, seed=5)
    rng = np.random.default_rng(3)
    n = len(f1)
    octaves = np.where(rng.random(n) < 0.5, 4, 0).astype(np.int8)
    kp = f1.keypoints.astype(np.float64)
    kp[octaves == 4] += rng.normal(0, 1.6, ((octaves == 4).sum(), 2))
    bad = rng.random(n) < 0.15
    kp[bad] = rng.uniform([0, 0], [640, 480], (bad.sum(), 2))
    f1 = FrameFeatures(kp.astype(np.float32), f1.descriptors, f1.points, octaves)
    for max_sigma in (0.0, 1.45):
        cfg = load_config(overrides={"odometry": {"pnp_ransac_max_sigma": max_sigma, "icp_fallback": False}})
        odo = Odometry(CAM, cfg.odometry)
        assert odo.track(f0, 0.0).status == "init"
        sizes.clear()
        res = odo.track(f1, 1 / 30)
        assert res.status == "ok"
        err = invert(truth) @ res.pose
        assert np.linalg.norm(err[:3, 3]) < 0.01 and np.degrees(rotation_angle(err[:3, :3])) < 0.3
        matched = res.map_index >= 0
        # RANSAC saw the fine matches alone (all of them without the setting; the registration
        # with the most matches is the unguided one, the motion being beyond the guided radius)
        assert max(sizes) == int((matched & (octaves == 0 if max_sigma else True)).sum())
        good_coarse = (octaves == 4) & ~bad & matched
        assert res.inlier_mask[good_coarse].mean() > 0.85  # the coarse matches are inliers at their σ
        assert (res.inlier_mask & bad).sum() <= 3
