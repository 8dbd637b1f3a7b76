"""Lens distortion, one way everywhere: the images stay raw (depth registered to the raw colour
image stays on its pixels), feature coordinates are undistorted, depth is read at the raw
pixel, dense code back-projects along undistorted rays; the calibration carries the
distortion from every source (TUM fr1/fr2, ROS CameraInfo, the wire protocol, storage, a
config override)."""
import dataclasses

import cv2
import numpy as np
import pytest

from mnemoslam.client.kernel.frames import Calibration, Frame, PinholeCamera
from mnemoslam.service.config import load_config
from mnemoslam.service.tracking import icp
from mnemoslam.service.tracking.features import FeatureExtractor

FR1_D = (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)  # TUM freiburg1's published distortion
CAM = PinholeCamera(517.3, 516.5, 318.6, 255.3, 640, 480, FR1_D)
PLANE_N = np.array([0.35, -0.2, 1.0]) / np.linalg.norm([0.35, -0.2, 1.0])  # a tilted wall n·X = d
PLANE_D = 1.2


def _project(X: np.ndarray, cam: PinholeCamera) -> np.ndarray:
    """Camera-frame points through the lens: cv2.projectPoints with the distortion."""
    uv, _ = cv2.projectPoints(X.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cam.K, np.array(cam.distortion))
    return uv.reshape(-1, 2)


def _plane_depth(cam: PinholeCamera) -> np.ndarray:
    """The depth image of the tilted wall as the distorted camera sees it: each raw pixel holds
    the z of the wall along that pixel's (undistorted) ray; rays from cv2 directly."""
    v, u = np.mgrid[0:cam.height, 0:cam.width].astype(np.float32)
    n = cv2.undistortPointsIter(np.stack([u.ravel(), v.ravel()], 1).reshape(-1, 1, 2), cam.K,
                                np.array(cam.distortion), None, None, (3, 30, 1e-9)).reshape(-1, 2)
    z = PLANE_D / (n @ PLANE_N[:2] + PLANE_N[2])
    return z.reshape(cam.height, cam.width).astype(np.float32)


def test_undistorted_points_match_the_pinhole_projection_of_a_distorted_projection():
    rng = np.random.default_rng(0)
    X = np.c_[rng.uniform(-0.55, 0.55, 500), rng.uniform(-0.4, 0.4, 500), np.ones(500)] * rng.uniform(1, 4, (500, 1))
    raw = _project(X, CAM)
    inside = (raw[:, 0] >= 0) & (raw[:, 0] < 640) & (raw[:, 1] >= 0) & (raw[:, 1] < 480)
    X, raw = X[inside], raw[inside]
    pinhole = X[:, :2] / X[:, 2:] * [CAM.fx, CAM.fy] + [CAM.cx, CAM.cy]
    und = CAM.undistort_points(raw)
    assert und.dtype == np.float32 and und.shape == raw.shape
    assert np.abs(und - pinhole).max() < 2e-3  # px
    assert np.abs(raw - pinhole).max() > 8  # the lens moves the corners by ~15 px: the test sees it
    # the per-pixel ray map agrees with the points
    rays = CAM.pixel_rays()
    u, v = 7, 473
    np.testing.assert_allclose(rays[v, u], (CAM.undistort_points([[u, v]])[0] - [CAM.cx, CAM.cy]) / [CAM.fx, CAM.fy],
                               atol=1e-6)
    # no distortion: the very same array of coordinates (bit for bit: undistorted runs unchanged)
    plain = CAM.pinhole
    xy = raw.astype(np.float32)
    assert not plain.distorted and np.array_equal(plain.undistort_points(xy), xy)
    assert PinholeCamera(1, 1, 0, 0, 4, 4, (0, 0, 0, 0, 0)).distortion == ()  # zeros: none
    with pytest.raises(ValueError, match="4, 5 or 8"):
        PinholeCamera(1, 1, 0, 0, 4, 4, (0.1, 0.2))
    with pytest.raises(ValueError, match="stereo"):
        Calibration(CAM, baseline=0.1)


def _wall_frame(cam: PinholeCamera) -> Frame:
    rng = np.random.default_rng(3)
    texture = cv2.GaussianBlur(rng.integers(0, 256, (cam.height, cam.width), dtype=np.uint8), (3, 3), 0)
    return Frame(0, 0.0, texture, depth=_plane_depth(cam))


def test_extractor_undistorts_keypoints_and_reads_depth_at_the_raw_pixel():
    """Keypoints on a textured tilted wall seen through fr1's lens: their coordinates are cv2's
    undistortion of the detected (raw) ones, and their 3-D points lie on the wall. Reading the
    depth at the undistorted pixel, or not undistorting, puts corner points centimetres off it."""
    cfg = load_config()
    frame = _wall_frame(CAM)
    f = FeatureExtractor(Calibration(CAM), cfg.features, cfg.stereo).extract(frame)
    raw = FeatureExtractor(Calibration(CAM.pinhole), cfg.features, cfg.stereo).extract(frame).keypoints
    assert len(f) == len(raw) > 300
    expected = cv2.undistortPointsIter(raw.reshape(-1, 1, 2), CAM.K, np.array(FR1_D), None, CAM.K,
                                       (3, 30, 1e-9)).reshape(-1, 2)
    assert np.abs(f.keypoints - expected).max() < 1e-2
    ok = f.has_depth
    assert ok.sum() > 0.9 * len(f)
    off_plane = np.abs(f.points[ok].astype(np.float64) @ PLANE_N - PLANE_D)
    assert np.median(off_plane) < 5e-4 and off_plane.max() < 3e-3, off_plane.max()  # metres
    # what plausible wrong implementations give, on the same keypoints: the test tells them apart
    depth = frame.depth
    z_raw = depth[np.rint(raw[ok, 1]).astype(int), np.rint(raw[ok, 0]).astype(int)]
    ku = np.clip(np.rint(f.keypoints[ok]).astype(int), 0, [639, 479])
    z_und = depth[ku[:, 1], ku[:, 0]]

    def off(xy, z):
        X = np.c_[(xy[:, 0] - CAM.cx) / CAM.fx * z, (xy[:, 1] - CAM.cy) / CAM.fy * z, z]
        return np.abs(X @ PLANE_N - PLANE_D).max()

    assert off(raw[ok], z_raw) > 0.01  # coordinates not undistorted
    assert off(f.keypoints[ok], z_und) > 0.005  # depth read at the undistorted pixel


def test_dense_back_projection_follows_the_undistorted_rays():
    """ICP's depth pyramid, the grid's cloud and local grid back-project the raw depth image
    onto the wall too (ICP on the image remapped to the pinhole camera, the others along the
    per-pixel rays)."""
    from mnemoslam.service.config import GridConfig
    from mnemoslam.service.grid.cloud import keyframe_points
    from mnemoslam.service.grid.local import LocalGridMaker

    depth = _plane_depth(CAM)
    for level in icp.depth_pyramid(depth, CAM):
        V = level.vertices.reshape(-1, 3)
        V = V[np.isfinite(V[:, 2])]
        assert len(V) > 0.8 * level.vertices.shape[0] * level.vertices.shape[1]
        assert np.abs(V @ PLANE_N - PLANE_D).max() < 1e-3
    naive = icp.depth_pyramid(depth, CAM.pinhole)[-1].vertices.reshape(-1, 3)
    naive = naive[np.isfinite(naive[:, 2])]
    assert np.abs(naive @ PLANE_N - PLANE_D).max() > 0.01  # ignoring the lens: off the wall
    P, _ = keyframe_points(None, depth, CAM, decimation=2)
    assert len(P) and np.abs(P @ PLANE_N - PLANE_D).max() < 1e-4
    P, _ = LocalGridMaker(CAM, GridConfig()).points(depth)
    assert len(P) and np.abs(P @ PLANE_N - PLANE_D).max() < 1e-4


def test_distortion_travels_through_protocol_storage_ros_and_config():
    from mnemoslam.client import ros_cdr
    from mnemoslam.client.kernel.protocol import ProtocolError, decode_info, encode_info
    from mnemoslam.service.builder import with_distortion
    from mnemoslam.service.config import ConfigError
    from mnemoslam.storage.records import calibration_from_dict, calibration_to_dict

    cal = Calibration(CAM, None, 5000.0)
    assert decode_info(encode_info("r1", cal))[1] == cal
    plain = Calibration(CAM.pinhole, None, 5000.0)
    assert b"distortion" not in encode_info("r1", plain)  # left out: older services read it as before
    assert decode_info(encode_info("r1", plain))[1] == plain
    import json

    msg = json.loads(encode_info("r1", cal))
    for bad in ([0.1, 0.2], ["a", 0, 0, 0], [True, 0, 0, 0], "0.1"):
        with pytest.raises(ProtocolError, match="distortion"):
            decode_info(json.dumps({**msg, "distortion": bad}).encode())
    assert calibration_from_dict(calibration_to_dict(cal)) == cal
    assert "distortion" not in calibration_to_dict(plain)
    # ROS CameraInfo: D into the calibration (K images); P (rectified) images have none
    info = ros_cdr.deserialize(ros_cdr.encode_camera_info(cal, 0), ros_cdr.CAMERA_INFO)
    assert ros_cdr.calibration(info).camera.distortion == FR1_D
    assert not ros_cdr.calibration(info, "p").camera.distorted
    # the config override: [] ignores the source's, a list replaces it, null keeps it
    assert with_distortion(cal, None) is cal
    assert with_distortion(cal, []).camera == CAM.pinhole
    assert with_distortion(plain, list(FR1_D)).camera == CAM
    assert load_config(overrides={"features": {"distortion": [0.1, 0, 0, 0]}}).features.distortion == [0.1, 0, 0, 0]
    with pytest.raises(ConfigError, match="features.distortion"):
        with_distortion(cal, [0.1])


def test_tum_player_knows_freiburg1_and_freiburg2_distortion(tmp_path):
    from mnemoslam.client.datasets.tum import distortion_for

    assert distortion_for("rgbd_dataset_freiburg1_desk") == FR1_D
    assert distortion_for("rgbd_dataset_freiburg2_xyz")[0] == 0.2312
    assert distortion_for("rgbd_dataset_freiburg3_cabinet") == ()
    scaled = CAM.scaled(0.5)
    assert scaled.distortion == FR1_D and (scaled.width, scaled.height) == (320, 240)
    assert dataclasses.replace(CAM, distortion=()) == CAM.pinhole
