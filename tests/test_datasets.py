"""Dataset players: unit tests on tiny fake folders (no real data needed) and checks on the real
sequences in the data folder (skipped when absent)."""
from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import pytest

from mnemoslam.client.datasets import open_dataset
from mnemoslam.client.datasets.base import detect_format
from mnemoslam.client.datasets.euroc import read_sensor_yaml
from mnemoslam.client.datasets.kitti import read_calib
from mnemoslam.client.datasets.tum import associate
from mnemoslam.client.kernel.frames import DatasetError

from conftest import require

RNG = np.random.default_rng(0)


def write_png(path: Path, image: np.ndarray) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), image)
    return path


def texture(h: int = 12, w: int = 16, channels: int | None = 3) -> np.ndarray:
    shape = (h, w) if channels is None else (h, w, channels)
    return RNG.integers(0, 256, shape, dtype=np.uint8)


# ---------------------------------------------------------------- timestamp association

def greedy_reference(a, b, max_dt):
    """The textbook greedy: all pairs within max_dt by increasing |dt|, each stamp used once."""
    pairs = sorted((abs(x - y), i, j) for i, x in enumerate(a) for j, y in enumerate(b) if abs(x - y) <= max_dt)
    used_a, used_b, out = set(), set(), []
    for _, i, j in pairs:
        if i not in used_a and j not in used_b:
            used_a.add(i), used_b.add(j), out.append((i, j))
    return sorted(out)


def test_associate_with_gaps_is_one_to_one_and_within_max_dt():
    a = np.delete(np.arange(0, 3, 1 / 30), np.arange(20, 30))  # a 0.37 s gap in a
    b = np.delete(np.arange(0, 3, 1 / 30) + RNG.uniform(-0.015, 0.015, 90), np.arange(50, 56))  # and in b
    b = RNG.permutation(b)  # order must not matter
    ia, ib = associate(a, b, 0.02)
    assert len(np.unique(ia)) == len(ia) and len(np.unique(ib)) == len(ib)
    assert np.all(np.abs(a[ia] - b[ib]) <= 0.02)
    assert np.all(np.diff(a[ia]) > 0)  # ordered by a
    assert len(ia) == 90 - 10 - 6
    assert sorted(zip(ia.tolist(), ib.tolist())) == greedy_reference(a, b, 0.02)


@pytest.mark.parametrize("seed", range(5))
def test_associate_matches_greedy_on_dense_random_stamps(seed):
    rng = np.random.default_rng(seed)
    a, b = rng.uniform(0, 1, 60), rng.uniform(0, 1, 45)  # several candidates per stamp
    ia, ib = associate(a, b, 0.02)
    assert sorted(zip(ia.tolist(), ib.tolist())) == greedy_reference(a, b, 0.02)


def test_associate_falls_back_to_second_nearest_and_handles_empty():
    # a[1] takes b[0]; a[0] then pairs with its second-nearest b[1].
    ia, ib = associate([0.0, 0.006], [0.005, -0.012], 0.02)
    assert ia.tolist() == [0, 1] and ib.tolist() == [1, 0]
    assert [len(x) for x in associate([], [1.0], 0.02)] == [0, 0]
    assert [len(x) for x in associate([0.0], [0.5], 0.02)] == [0, 0]


# ---------------------------------------------------------------- TUM RGB-D

def make_tum(root: Path, name: str = "rgbd_dataset_freiburg1_xyz") -> Path:
    """Five rgb images (one without depth), depth 5 ms later, ground truth for four."""
    path = root / name
    rgb_t = [1.0, 1.033, 1.066, 1.5, 1.1]  # unsorted on purpose; 1.5 has no depth
    depth_t = [1.005, 1.038, 1.071, 1.105]
    raw = np.full((12, 16), 5000, np.uint16)
    raw[0, :] = 0
    for t in rgb_t:
        write_png(path / f"rgb/{t:.3f}.png", texture())
    for t in depth_t:
        write_png(path / f"depth/{t:.3f}.png", raw)
    (path / "rgb.txt").write_text("# color images\n# timestamp filename\n"
                                  + "".join(f"{t:.3f} rgb/{t:.3f}.png\n" for t in rgb_t))
    (path / "depth.txt").write_text("# depth maps\n" + "".join(f"{t:.3f} depth/{t:.3f}.png\n" for t in depth_t))
    (path / "groundtruth.txt").write_text("# timestamp tx ty tz qx qy qz qw\n"
                                          + "".join(f"{t + 0.002} {t} 0 0 0 0 0 1\n" for t in (1.0, 1.033, 1.1)))
    return path


def test_tum_lists_association_depth_and_ground_truth(tmp_path):
    ds = open_dataset(make_tum(tmp_path))
    assert (ds.format, ds.name, len(ds)) == ("tum", "rgbd_dataset_freiburg1_xyz", 4)
    np.testing.assert_allclose(ds.stamps, [1.0, 1.033, 1.066, 1.1])
    f = ds.frame(1)
    assert f.index == 1 and f.stamp == pytest.approx(1.033)
    assert f.image.shape == (12, 16, 3) and f.image.dtype == np.uint8
    assert f.depth.dtype == np.float32 and f.depth[0].max() == 0 and np.all(f.depth[1:] == 1.0)
    assert "rgb/1.033.png" in f.source and "depth/1.038.png" in f.source
    cam = ds.calibration.camera
    assert (cam.width, cam.height, ds.calibration.depth_scale, ds.calibration.kind) == (16, 12, 5000, "rgbd")
    np.testing.assert_allclose(ds.ground_truth.stamps, [1.0, 1.033, 1.1])  # 1.066 has no pose
    np.testing.assert_allclose(ds.ground_truth.positions[:, 0], [1.0, 1.033, 1.1])
    assert [f.index for f in ds] == [0, 1, 2, 3]

    short = open_dataset(ds.path, max_frames=2)
    assert len(short) == 2 and len(short.ground_truth) == 2


@pytest.mark.parametrize("name, fx, fy", [
    ("rgbd_dataset_freiburg1_desk", 517.3, 516.5),
    ("rgbd_dataset_freiburg2_xyz", 520.9, 521.0),
    ("rgbd_dataset_freiburg3_cabinet", 535.4, 539.2),
    ("my_kinect_recording", 525.0, 525.0),
])
def test_tum_intrinsics_from_folder_name(tmp_path, caplog, name, fx, fy):
    with caplog.at_level(logging.WARNING):
        cam = open_dataset(make_tum(tmp_path, name)).calibration.camera
    assert (cam.fx, cam.fy) == (fx, fy)
    assert ("default intrinsics" in caplog.text) == (name == "my_kinect_recording")


def test_tum_bad_list_names_the_file(tmp_path):
    path = make_tum(tmp_path)
    (path / "depth.txt").write_text("1.0 depth/a.png\nnot-a-stamp depth/b.png\n")
    with pytest.raises(DatasetError, match="depth.txt"):
        open_dataset(path)


def test_missing_image_names_the_file(tmp_path):
    ds = open_dataset(make_tum(tmp_path))
    (ds.path / "rgb/1.066.png").unlink()
    with pytest.raises(DatasetError, match=r"rgb/1\.066\.png.*missing"):
        ds.frame(2)


def test_corrupt_image_names_the_file(tmp_path):
    ds = open_dataset(make_tum(tmp_path))
    (ds.path / "depth/1.038.png").write_bytes(b"\x89PNG garbage" + bytes(range(256)))
    with pytest.raises(DatasetError, match=r"depth/1\.038\.png.*corrupt"):
        ds.frame(1)


def test_wrong_image_size_and_arguments(tmp_path):
    ds = open_dataset(make_tum(tmp_path))
    write_png(ds.path / "rgb/1.100.png", texture(10, 16))
    with pytest.raises(DatasetError, match=r"rgb/1\.100\.png.*16x10"):
        ds.frame(3)
    with pytest.raises(IndexError):
        ds.frame(4)
    assert ds.frame(-2).index == 2  # negative indices count from the end
    with pytest.raises(DatasetError, match="max_frames"):
        open_dataset(ds.path, max_frames=0)
    with pytest.raises(TypeError):
        open_dataset(ds.path, fps=30)


# ---------------------------------------------------------------- KITTI odometry

CALIB = """P0: 700 0 600 0 0 701 180 0 0 0 1 0
P1: 700 0 600 -350 0 701 180 0 0 0 1 0
P2: 700 0 600 45 0 701 180 0.2 0 0 1 0.003
Tr: 1 0 0 0 0 1 0 0 0 0 1 0
"""


def make_kitti(root: Path, n: int = 3) -> Path:
    path = root / "sequences" / "07"
    for i in range(n):
        write_png(path / f"image_0/{i:06d}.png", texture(channels=None))
        write_png(path / f"image_1/{i:06d}.png", texture(channels=None))
    (path / "calib.txt").write_text(CALIB)
    (root / "poses").mkdir()
    (root / "poses/07.txt").write_text("".join(f"1 0 0 {i} 0 1 0 0 0 0 1 0\n" for i in range(n)))
    return path


def test_kitti_calib_times_and_ground_truth(tmp_path):
    ds = open_dataset(make_kitti(tmp_path))
    cal = ds.calibration
    assert (ds.format, ds.name, len(ds)) == ("kitti", "07", 3)
    assert (cal.camera.fx, cal.camera.fy, cal.camera.cx, cal.camera.cy) == (700, 701, 600, 180)
    assert cal.baseline == pytest.approx(0.5) and cal.kind == "stereo" and cal.depth_scale == 1
    np.testing.assert_allclose(ds.stamps, [0, 0.1, 0.2])  # no times.txt: 10 Hz from 0
    np.testing.assert_allclose(ds.ground_truth.positions[:, 0], [0, 1, 2])
    f = ds.frame(2)
    assert f.image.shape == f.right.shape == (12, 16) and "image_1/000002.png" in f.source
    assert read_calib(ds.path / "calib.txt")["Tr"].shape == (3, 4)
    assert len(open_dataset(ds.path, max_frames=2).ground_truth) == 2


def test_kitti_errors_name_the_file(tmp_path):
    path = make_kitti(tmp_path)
    (path / "times.txt").write_text("0.0\n0.1\n")
    with pytest.raises(DatasetError, match="times.txt"):
        open_dataset(path)
    (path / "times.txt").unlink()
    (path / "calib.txt").write_text(CALIB.splitlines()[0] + "\n")
    with pytest.raises(DatasetError, match="calib.txt.*P1"):
        open_dataset(path)
    (path / "calib.txt").write_text(CALIB)
    (path / "image_1/000001.png").unlink()
    with pytest.raises(DatasetError, match="image_1/000001.png"):
        open_dataset(path).frame(1)


# ---------------------------------------------------------------- EuRoC MAV

def sensor_yaml(T_BS: np.ndarray, K=(40.0, 41.0, 15.5, 11.5), dist=(-0.1, 0.01, 0.001, -0.001), size=(32, 24)) -> str:
    return f"""%YAML:1.0
# General sensor definitions.
sensor_type: camera
T_BS:
  cols: 4
  rows: 4
  data: [{", ".join(map(str, T_BS.ravel()))}]
rate_hz: 20
resolution: [{size[0]}, {size[1]}]
camera_model: pinhole
intrinsics: [{", ".join(map(str, K))}] #fu, fv, cu, cv
distortion_model: radial-tangential
distortion_coefficients: [{", ".join(map(str, dist))}]
"""


def make_euroc(root: Path) -> Path:
    """cam1 0.1 m to the right of cam0; cam1 lacks one of cam0's four stamps; ground truth csv
    with the body turned 90 degrees about z (quaternion stored w, x, y, z)."""
    path = root / "MH_fake"
    T1 = np.eye(4)
    T1[0, 3] = 0.1
    ns = [1_000_000_000_000_000_000 + k * 50_000_000 for k in range(4)]
    for cam, T, stamps in (("cam0", np.eye(4), ns), ("cam1", T1, ns[:2] + ns[3:])):
        d = path / "mav0" / cam
        for t in stamps:
            write_png(d / f"data/{t}.png", texture(24, 32, None))
        (d / "data.csv").write_text("#timestamp [ns],filename\n" + "".join(f"{t},{t}.png\n" for t in stamps))
        (d / "sensor.yaml").write_text(sensor_yaml(T))
    imu = path / "mav0/imu0/data.csv"
    imu.parent.mkdir()
    imu.write_text("#timestamp [ns],w_x,w_y,w_z,a_x,a_y,a_z\n"
                   + "".join(f"{ns[0] + k * 5_000_000},0,0,0.1,9.8,0,0\n" for k in range(30)))
    gt = path / "mav0/state_groundtruth_estimate0/data.csv"
    gt.parent.mkdir()
    c = np.sqrt(0.5)
    gt.write_text("#timestamp,p_x,p_y,p_z,q_w,q_x,q_y,q_z,v_x,v_y,v_z,bw_x,bw_y,bw_z,ba_x,ba_y,ba_z\n"
                  + "".join(f"{t + 1000},1,2,3,{c},0,0,{c},0,0,0,0,0,0,0,0,0\n" for t in ns))
    return path


def test_euroc_sensor_yaml(tmp_path):
    T = np.arange(16, dtype=float).reshape(4, 4)
    (tmp_path / "sensor.yaml").write_text(sensor_yaml(T))
    cam = read_sensor_yaml(tmp_path / "sensor.yaml")
    np.testing.assert_allclose(cam.K, [[40, 0, 15.5], [0, 41, 11.5], [0, 0, 1]])
    np.testing.assert_allclose(cam.dist, [-0.1, 0.01, 0.001, -0.001])
    np.testing.assert_allclose(cam.T_BS, T)
    assert cam.size == (32, 24)
    (tmp_path / "sensor.yaml").write_text(sensor_yaml(T).replace("intrinsics", "intrinsix"))
    with pytest.raises(DatasetError, match="sensor.yaml"):
        read_sensor_yaml(tmp_path / "sensor.yaml")
    (tmp_path / "sensor.yaml").write_text(sensor_yaml(T).replace("pinhole", "omni"))
    with pytest.raises(DatasetError, match="sensor.yaml.*unsupported"):
        read_sensor_yaml(tmp_path / "sensor.yaml")


def test_euroc_pairs_rectifies_and_converts_ground_truth(tmp_path):
    path = make_euroc(tmp_path)
    for spec in (path, path / "mav0"):
        ds = open_dataset(spec)
        assert (ds.format, ds.name, len(ds)) == ("euroc", "MH_fake", 3)
    assert ds.stamps[1] == pytest.approx(1e9 + 0.05)  # ns -> s; the unpaired stamp is dropped
    assert ds.calibration.baseline == pytest.approx(0.1) and ds.calibration.depth_scale == 1
    cam = ds.calibration.camera
    assert (cam.width, cam.height) == (32, 24)
    f = ds.frame(2)
    assert f.image.shape == f.right.shape == (24, 32) and f.image.dtype == np.uint8
    assert "cam0/data/1000000000150000000.png" in f.source and "cam1/data/1000000000150000000.png" in f.source
    assert ds.imu.shape == (30, 7) and ds.imu[1, 0] - ds.imu[0, 0] == pytest.approx(0.005)
    # Ground truth: body rotated +90 deg about z (w x y z order in the csv), camera = body here.
    gt = ds.ground_truth
    assert len(gt) == 3
    np.testing.assert_allclose(gt.stamps, ds.stamps)
    Rz = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]])
    np.testing.assert_allclose(gt.poses[0, :3, :3], Rz @ ds.T_B_cam[:3, :3], atol=1e-9)
    np.testing.assert_allclose(gt.positions[0], [1, 2, 3], atol=1e-9)
    assert len(open_dataset(path, max_frames=1).ground_truth) == 1
    T1 = np.eye(4)
    T1[0, 3] = -0.1  # cam1 on the left: not a left/right pair
    (path / "mav0/cam1/sensor.yaml").write_text(sensor_yaml(T1))
    with pytest.raises(DatasetError, match="not to the right"):
        open_dataset(path)


# ---------------------------------------------------------------- 7-Scenes

def make_sevenscenes(root: Path) -> Path:
    """A scene with seq-01 (three frames, pose 1 is -inf) and an empty seq-02."""
    scene = root / "office"
    seq = scene / "seq-01"
    raw = np.full((12, 16), 1500, np.uint16)
    raw[:, :4] = 65535
    for k in range(3):
        write_png(seq / f"frame-{k:06d}.color.png", texture())
        write_png(seq / f"frame-{k:06d}.depth.png", raw)
        pose = np.eye(4)
        pose[0, 3] = k
        text = "\n".join(" ".join(f"{v:.6e}" for v in row) for row in pose)
        (seq / f"frame-{k:06d}.pose.txt").write_text(text.replace("1.000000e+00", "-inf") if k == 1 else text)
    (scene / "seq-02").mkdir()
    (scene / "camera-intrinsics.txt").write_text("500 0 330\n0 501 250\n0 0 1\n")
    return scene


def test_sevenscenes_poses_depth_and_intrinsics(tmp_path):
    """The raw player (register=False): the depth camera's intrinsics, poses and depth as stored."""
    scene = make_sevenscenes(tmp_path)
    for spec in (scene, scene / "seq-01"):
        ds = open_dataset(spec, register=False)
        assert (ds.format, ds.name, len(ds)) == ("7scenes", "office/seq-01", 3)
    np.testing.assert_allclose(ds.stamps, np.arange(3) / 30)
    cam = ds.calibration.camera
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height) == (500, 501, 330, 250, 16, 12)
    assert ds.calibration.depth_scale == 1000
    gt = ds.ground_truth
    np.testing.assert_allclose(gt.stamps, [0, 2 / 30])  # the -inf pose is left out
    np.testing.assert_allclose(gt.positions[:, 0], [0, 2])
    f = ds.frame(0)
    assert f.image.shape == (12, 16, 3)
    assert np.all(f.depth[:, :4] == 0) and np.all(f.depth[:, 4:] == pytest.approx(1.5))


def test_sevenscenes_defaults_and_bad_pose(tmp_path):
    scene = make_sevenscenes(tmp_path)
    (scene / "camera-intrinsics.txt").unlink()
    (scene / "seq-01/frame-000002.pose.txt").unlink()  # missing pose: left out
    ds = open_dataset(scene / "seq-01", register=False)
    assert (ds.calibration.camera.fx, ds.calibration.camera.cx) == (585, 320)
    assert len(ds.ground_truth) == 1
    (scene / "seq-01/frame-000000.pose.txt").write_text("1 0 0\n0 1 0\n")
    with pytest.raises(DatasetError, match="frame-000000.pose.txt"):
        open_dataset(scene)


def test_sevenscenes_registers_depth_into_the_colour_camera_when_asked(tmp_path):
    """register=True: the Kinect v1 colour camera (525 px at 640 wide, scaled to the images),
    depth registered into it, and the ground truth moved to it (2.5 cm along the depth camera's x)."""
    from mnemoslam.client.datasets.registration import DepthRegistration

    scene = make_sevenscenes(tmp_path)
    raw, ds = open_dataset(scene, register=False), open_dataset(scene, register=True)
    cam = ds.calibration.camera
    assert (cam.width, cam.height) == (16, 12) and cam.fx == pytest.approx(525 * 16 / 640)
    assert isinstance(ds.registration, DepthRegistration) and ds.registration.depth_camera == raw.calibration.camera
    np.testing.assert_array_equal(ds.frame(0).depth, ds.registration.register(raw.frame(0).depth))
    shift = ds.ground_truth.positions - raw.ground_truth.positions
    np.testing.assert_allclose(shift, np.tile([0.025, 0, 0], (2, 1)), atol=1e-12)  # identity rotations


KINECT_AT_16 = "14.625 0 8\n0 14.625 6\n0 0 1\n"  # 585, 585, 320, 240 at 640 px wide, for 16 px wide images


@pytest.mark.parametrize("intrinsics,registered", [
    (None, True),  # no camera-intrinsics.txt: Microsoft's data, the 7-Scenes default
    (KINECT_AT_16, True),  # the Kinect v1 depth camera's
    ("14.625 0 8.0125\n0 14.625 6\n0 0 1\n", True),  # cx 320.5 at 640 wide: within 1 px
    ("500 0 330\n0 501 250\n0 0 1\n", False),  # another sensor's
    ("14.625 0 8.05\n0 14.625 6\n0 0 1\n", False),  # cx 322 at 640 wide: beyond the 1 px
])
def test_sevenscenes_registers_only_the_kinect_data_by_default(tmp_path, caplog, intrinsics, registered):
    """By default depth is registered only for Microsoft's 7-Scenes data (the Kinect v1 depth
    camera's intrinsics, or none given); any other sequence in the layout plays as given, with
    its own intrinsics. register=True / False overrides either way; one INFO line says which."""
    scene = make_sevenscenes(tmp_path)
    (scene / "camera-intrinsics.txt").unlink()
    if intrinsics is not None:
        (scene / "camera-intrinsics.txt").write_text(intrinsics)
    raw = open_dataset(scene, register=False)
    assert raw.registration is None
    with caplog.at_level(logging.INFO, logger="mnemoslam.client.datasets.sevenscenes"):
        ds = open_dataset(scene)
    lines = [r for r in caplog.records if "registered" in r.getMessage()]
    assert len(lines) == 1 and lines[0].levelno == logging.INFO
    assert (ds.registration is not None) == registered
    assert ("into the Kinect v1 colour camera" in lines[0].getMessage()) == registered, lines[0].getMessage()
    if registered:
        assert ds.calibration.camera.fx == pytest.approx(525 * 16 / 640)
        assert open_dataset(scene, register=False).registration is None
    else:
        assert ds.calibration.camera == raw.calibration.camera  # the sequence's own intrinsics
        np.testing.assert_array_equal(ds.frame(0).depth, raw.frame(0).depth)
        np.testing.assert_array_equal(ds.ground_truth.poses, raw.ground_truth.poses)
        assert open_dataset(scene, register=True).registration is not None


def test_depth_registration_is_a_7scenes_option_only(tmp_path):
    for path in (make_tum(tmp_path), "synthetic:loop"):
        with pytest.raises(DatasetError, match="applies to 7-Scenes only"):
            open_dataset(path, register=True)
    assert len(open_dataset(make_tum(tmp_path / "b"), register=None)) > 0  # None: every player's default


def write_sevenscenes(ds, root: Path) -> Path:
    """`ds` (RGB-D frames with ground truth) written in the 7-Scenes layout: seq-01 of colour
    PNGs, depth PNGs in millimetres and 4x4 pose files, with its own camera-intrinsics.txt."""
    seq = root / "seq-01"
    for i in range(len(ds)):
        f = ds.frame(i)
        write_png(seq / f"frame-{i:06d}.color.png", f.image)
        write_png(seq / f"frame-{i:06d}.depth.png", np.round(f.depth * 1000).astype(np.uint16))
        np.savetxt(seq / f"frame-{i:06d}.pose.txt", ds.ground_truth.poses[i])
    c = ds.calibration.camera
    np.savetxt(root / "camera-intrinsics.txt", [[c.fx, 0, c.cx], [0, c.fy, c.cy], [0, 0, 1]])
    return root


@pytest.mark.slow
def test_sevenscenes_layout_from_another_sensor_runs_with_its_own_intrinsics(tmp_path, capsys):
    """Issue 26: a sequence in the 7-Scenes layout from another RGB-D sensor (depth registered to
    colour, fx 600 px at 640 wide) played by `mnemoslam run` with its own intrinsics and no
    depth registration. Registered into a Kinect v1 colour camera (525 px, 2.5 cm baseline; the
    player's default before) the same frames gave 7.43 cm."""
    from mnemoslam.client.synthetic import SyntheticDataset
    from mnemoslam.service.cli import main
    from mnemoslam.service.evaluation import evaluate, read_trajectory

    syn = SyntheticDataset("loop", rate=10, width=320, height=240, fx=300.0, max_frames=100)  # exact depth, poses
    folder = write_sevenscenes(syn, tmp_path / "other_sensor")
    out = tmp_path / "out"
    assert main(["run", str(folder), "--out", str(out), "--set", "semantics.enabled=false", "-q"]) == 0
    ev = evaluate(read_trajectory(out / "groundtruth.tum"), read_trajectory(out / "trajectory.tum"))
    assert ev.matched == 100, capsys.readouterr().out
    assert ev.ate_rmse < 0.015, ev.ate_rmse  # measured 0.49 cm (the synthetic frames played directly: 0.50)
    ds = open_dataset(folder)
    assert ds.registration is None and ds.calibration.camera == syn.camera


# ---------------------------------------------------------------- layout detection

def test_detect_format_on_fake_layouts(tmp_path):
    assert detect_format(make_tum(tmp_path)) == "tum"
    assert detect_format(make_kitti(tmp_path)) == "kitti"
    euroc = make_euroc(tmp_path)
    assert detect_format(euroc) == detect_format(euroc / "mav0") == "euroc"
    scene = make_sevenscenes(tmp_path)
    assert detect_format(scene) == detect_format(scene / "seq-01") == "7scenes"
    with pytest.raises(DatasetError, match="unknown dataset layout"):
        detect_format(tmp_path)


def test_open_dataset_nonexistent_path(tmp_path):
    with pytest.raises(DatasetError, match="no_such_folder"):
        open_dataset(tmp_path / "no_such_folder")


# ---------------------------------------------------------------- real sequences

REAL = {  # folder: (format, frames, ground-truth poses, image shape)
    "rgbd_dataset_freiburg3_cabinet_keyframes": ("tum", 58, 58, (480, 640, 3)),
    "7scenes_redkitchen": ("7scenes", 1000, 1000, (480, 640, 3)),
    "kitti_odometry_snippets/sequences/a": ("kitti", 51, 51, (370, 1226)),
    "euroc_v101_head": ("euroc", 40, 40, (480, 752)),
}


def stereo_row_error(left: np.ndarray, right: np.ndarray) -> tuple[float, float]:
    """Median |dy| and median dx (left - right) of ORB matches between a stereo pair."""
    orb = cv2.ORB_create(1500)
    kl, dl = orb.detectAndCompute(left, None)
    kr, dr = orb.detectAndCompute(right, None)
    matches = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(dl, dr)
    assert len(matches) > 100
    d = np.array([np.subtract(kl[m.queryIdx].pt, kr[m.trainIdx].pt) for m in matches])
    return float(np.median(np.abs(d[:, 1]))), float(np.median(d[:, 0]))


@pytest.mark.parametrize("folder", REAL)
def test_real_sequence(data_dir, folder):
    fmt, n, n_gt, shape = REAL[folder]
    ds = open_dataset(require(data_dir / folder))
    assert ds.format == fmt and len(ds) == n
    gt = ds.ground_truth
    assert n_gt - 10 <= len(gt) <= n_gt and np.isin(gt.stamps, ds.stamps).all()
    assert np.all(np.diff(ds.stamps) > 0)
    cam = ds.calibration.camera
    for i in (0, n // 2, n - 1):
        f = ds.frame(i)
        assert f.image.shape == shape and f.image.dtype == np.uint8 and f.stamp == ds.stamps[i]
        assert (cam.height, cam.width) == shape[:2]
        if ds.calibration.kind == "rgbd":
            assert f.depth.shape == shape[:2] and f.depth.dtype == np.float32
            assert (f.depth > 0).mean() > 0.5 and 0.2 < np.median(f.depth[f.depth > 0]) < 8
        else:
            assert f.right.shape == shape


def test_real_calibrations(data_dir):
    tum = open_dataset(require(data_dir / "rgbd_dataset_freiburg3_cabinet_keyframes")).calibration
    cam = tum.camera
    assert (cam.fx, cam.fy, cam.cx, cam.cy, tum.depth_scale) == (535.4, 539.2, 320.1, 247.6, 5000)
    scenes = open_dataset(require(data_dir / "7scenes_redkitchen")).calibration
    assert (scenes.camera.fx, scenes.camera.cx, scenes.depth_scale) == (525, 319.5, 1000)  # the colour camera
    raw = open_dataset(data_dir / "7scenes_redkitchen", register=False).calibration
    assert (raw.camera.fx, raw.camera.cx) == (585, 320)  # camera-intrinsics.txt: the depth camera
    kitti = open_dataset(require(data_dir / "kitti_odometry_snippets/sequences/a")).calibration
    assert kitti.camera.fx == 707.0912 and kitti.baseline == pytest.approx(0.537, abs=1e-3)
    kitti_b = open_dataset(data_dir / "kitti_odometry_snippets/sequences/b").calibration
    assert kitti_b.camera.fx == 718.856 and (kitti_b.camera.width, kitti_b.camera.height) == (1241, 376)
    euroc = open_dataset(require(data_dir / "euroc_v101_head")).calibration
    assert euroc.baseline == pytest.approx(0.110, abs=2e-3) and 400 < euroc.camera.fx < 460


def test_real_euroc_rectification_and_frames(data_dir):
    path = require(data_dir / "euroc_v101_head")
    ds = open_dataset(path)
    f = ds.frame(0)
    dy, dx = stereo_row_error(f.image, f.right)
    assert dy < 1.0 and dx > 0  # rows align; the right camera is to the right (positive disparity)
    # The rectified right camera centre, seen from the body, is raw cam1's centre.
    cam1 = read_sensor_yaml(path / "mav0/cam1/sensor.yaml")
    np.testing.assert_allclose((ds.T_B_cam @ [ds.calibration.baseline, 0, 0, 1])[:3], cam1.T_BS[:3, 3], atol=1e-9)
    assert ds.imu.shape[1] == 7 and ds.imu[0, 0] <= ds.stamps[0] + 0.01 and ds.imu[-1, 0] >= ds.stamps[-1]


def test_real_kitti_rows_align_and_truncation(data_dir):
    ds = open_dataset(require(data_dir / "kitti_odometry_snippets/sequences/a"), max_frames=10)
    assert len(ds) == len(ds.ground_truth) == 10
    f = ds.frame(0)
    dy, dx = stereo_row_error(f.image, f.right)
    assert dy < 1.0 and dx > 0


def test_passes_play_back_and_forth_with_increasing_stamps_and_matching_ground_truth():
    from mnemoslam.client.datasets.passes import Passes

    ds = open_dataset("synthetic:loop", max_frames=6)
    p = Passes(ds, 3)
    assert [p.origin(j) for j in range(len(p))] == [0, 1, 2, 3, 4, 5, 4, 3, 2, 1, 0, 1, 2, 3, 4, 5]
    assert np.all(np.diff(p.stamps) > 0) and np.allclose(np.diff(p.stamps), 1 / 30)
    np.testing.assert_array_equal(p.stamps[:6], ds.stamps)  # pass 1 keeps the dataset's stamps
    np.testing.assert_array_equal(p.ground_truth.stamps, p.stamps)
    np.testing.assert_allclose(p.ground_truth.poses, ds.ground_truth.poses[[p.origin(j) for j in range(len(p))]])
    f = p.frame(7)  # pass 2, dataset frame 3
    assert (f.index, f.stamp) == (7, p.stamps[7])
    np.testing.assert_array_equal(f.image, ds.frame(3).image)
    assert len(Passes(ds, 1)) == len(ds) and Passes(ds, 1).name == ds.name
    with pytest.raises(ValueError):
        Passes(ds, 0)


def test_run_passes_writes_ground_truth_at_the_played_stamps(tmp_path):
    from mnemoslam.client.kernel.trajectory import read_tum
    from mnemoslam.service.cli import main

    assert main(["run", "synthetic:loop", "--max-frames", "20", "--passes", "3", "--out", str(tmp_path),
                 "--odometry-only", "-q"]) == 0
    gt = read_tum(tmp_path / "groundtruth.tum")
    est = read_tum(tmp_path / "trajectory.tum")
    assert len(gt) == 20 + 19 + 19 and np.all(np.diff(gt.stamps) > 0)
    np.testing.assert_allclose(est.stamps, gt.stamps)


# -- --frames START:END (issue 22): a sub-range, frames and stamps as in the full run -------------


def test_frames_range_parses_and_plays_the_full_runs_frames():
    from mnemoslam.client.datasets.subrange import frame_range, parse_frames

    assert parse_frames("0:500") == (0, 500) and parse_frames("300:") == (300, None) and parse_frames(":5") == (0, 5)
    for bad in ("5", "5:5", "-1:3", "a:b", "7:3"):
        with pytest.raises(ValueError):
            parse_frames(bad)
    full = open_dataset("synthetic:walk_a?rate=5")
    assert full.rate == 5.0 and len(full) == 181
    part = frame_range(full, "20:30")
    assert len(part) == 10 and part.name.endswith("[20:30]") and part.origin(0) == 20
    assert np.array_equal(part.stamps, full.stamps[20:30])
    f, g = part.frame(3), full.frame(23)
    assert (f.index, f.stamp) == (23, g.stamp) and np.array_equal(f.image, g.image) and np.array_equal(f.depth, g.depth)
    assert np.array_equal(part.ground_truth.stamps, full.stamps[20:30])
    assert np.array_equal(part.ground_truth.poses, full.ground_truth.poses[20:30])
    assert len(frame_range(full, "170:", max_frames=4)) == 4 and len(frame_range(full, "170:")) == 11
    assert frame_range(full, None) is full
    with pytest.raises(DatasetError):
        frame_range(full, "200:300")
    with pytest.raises(DatasetError, match="rate"):
        open_dataset("synthetic:walk_a?rate=fast")
