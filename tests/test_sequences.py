"""Whole real sequences through the offline runner: tracking and accuracy bounds.

The bounds are what the odometry achieves today with a margin; the product targets of
issue #2 that are not met yet are stated next to each bound."""
import shutil
import subprocess
import sys

import numpy as np
import pytest

from mnemoslam.client.datasets import open_dataset
from mnemoslam.client.kernel.trajectory import Trajectory
from mnemoslam.service.evaluation import evaluate, evaluate_map_links, evaluate_map_loops
from mnemoslam.service.runner import run_dataset

from conftest import require, run_tracked_once, slam_config

pytestmark = pytest.mark.data


def _run(path, **options):
    ds = open_dataset(path, **options)
    out = run_dataset(ds, slam_config(), progress=False)
    return ds, out, evaluate(ds.ground_truth, out.trajectory)


def test_7scenes_redkitchen_no_frame_lost_and_revisits_closed(data_dir, tmp_path):
    ds = open_dataset(require(data_dir / "7scenes_redkitchen"))
    # (no occupancy grid: what this checks is the map's links and poses, which the grids never
    # change; the grids of real frames are tests/test_grid_real.py's)
    cfg = slam_config({"grid": {"enabled": False}})
    out = run_dataset(ds, cfg, tmp_path, progress=False)
    assert out.summary.frames == 1000 and out.summary.lost == 0 and out.summary.segments == 1
    ev = evaluate(ds.ground_truth, out.trajectory)
    assert ev.matched == 1000
    # Loop links join true revisits. The KinectFusion ground truth drifts itself, so relative
    # poses between revisits disagree with it by up to ~6° / 10 cm even where the images agree
    # with the link (bench/gt_consistency.py: on loop and proximity links the ground truth
    # explains a median 2 % of the feature matches, the links 33 %); a false link (another
    # place) would be off by metres.
    loops = evaluate_map_loops(ds.ground_truth, tmp_path / "map.db", cfg.loop.min_age, true_link=(0.2, 12.0))
    assert out.summary.loops >= 5 and loops.false_links == 0, loops.format()
    # Depth registered into the colour camera (the player's default) makes the odometry links
    # agree better with the ground truth: measured median 0.53° (0.82° with the raw depth and
    # the depth camera's intrinsics), odometry alone ATE 3.68 cm (4.96 raw).
    links = evaluate_map_links(ds.ground_truth, tmp_path / "map.db").by_kind()
    assert links["odometry"].median_deg < 0.7, links["odometry"]
    # measured (se3 ATE, every frame at its final pose) with loops: 3.22 cm, odometry alone
    # 3.68 (issue 29: 4.71 while loop links took the two-view refinement's own σ as their
    # information; before that it moved between 3.6 and 4.7 cm with perturbations that change
    # nothing else, as the links between frames ~200 and ~800-890, whose ground truth is 5-6°
    # off the images, were made or refused). ORB-SLAM3 4.7 cm.
    assert ev.ate_rmse < 0.045, ev.ate_rmse


def _odometry(out) -> Trajectory:
    """Every tracked frame at its odometry pose (tracking never reads the map update, so this
    is the odometry-only run: test_tum_cabinet_loop_back_to_the_start_is_closed checks it)."""
    tracked = [r for r in out.results if r.tracked]
    return Trajectory(np.array([r.stamp for r in tracked]), np.stack([r.odometry_pose for r in tracked]))


def test_tum_fr1_desk_loops_help_and_link_refinement_never_hurts(data_dir):
    """Issue 29's guard, on motion-capture ground truth: with the default configuration the
    map with loops is more accurate than odometry alone, and the loop-link refinement makes it
    no worse than the verified links without it (by more than 2 %). With the refinement's own
    covariance as the links' information (its σ 5-20x below their real errors) 7-Scenes went
    3.20 -> 4.71 cm, worse than odometry alone (3.68), and an evaluation sequence 3.43 -> 5.40.
    The run without the refinement replays the first run's tracking (tests/conftest.py
    `run_tracked_once`: the two differ in the map update only)."""
    path = require(data_dir / "rgbd_dataset_freiburg1_desk")
    ds = open_dataset(path)
    key = ("folder", str(path))  # (a run of another test with this key plays the same frames)
    # (no occupancy grid: the ATE is the map's poses, which the grids never change)
    out = run_tracked_once(ds, slam_config({"grid": {"enabled": False}}), key=key, progress=False)
    off = run_tracked_once(ds, slam_config({"loop": {"link_refine": False}, "grid": {"enabled": False}}), key=key,
                           progress=False)
    assert out.summary.tracked == len(ds) and out.summary.lost == 0
    ate, ate_off, ate_odometry = (evaluate(ds.ground_truth, t).ate_rmse
                                  for t in (out.trajectory, off.trajectory, _odometry(out)))
    # measured 2026-11-27: odometry alone 4.24 cm, with loops 2.94 (refinement off: 2.97); with fr1's lens
    # distortion (undistorted feature coordinates, depth at the raw pixel) and issue 26's depth-time
    # compensation: 3.21 and 2.55 cm
    assert ate < ate_odometry and ate <= 1.02 * ate_off, (ate, ate_off, ate_odometry)
    assert ate < 0.035, ate


@pytest.fixture(scope="module")
def cabinet(data_dir, tmp_path_factory):
    """The TUM cabinet keyframes through the offline runner, default configuration (loop
    closure on), once for the two tests that check that run: `(path, dataset, RunOutput, out_dir)`."""
    path = require(data_dir / "rgbd_dataset_freiburg3_cabinet_keyframes")
    out_dir = tmp_path_factory.mktemp("cabinet")
    ds = open_dataset(path)
    return path, ds, run_dataset(ds, slam_config(), out_dir, progress=False), out_dir


def test_tum_cabinet_keyframes_all_tracked(cabinet):
    _, ds, out, _ = cabinet
    ev = evaluate(ds.ground_truth, out.trajectory)
    assert out.summary.tracked == 58 and out.summary.lost == 0
    # measured 2.11 cm (dense photometric + geometric registration, and where the one PnP pose
    # with 60 inliers has a 0.42° σ, odometry.confident_sigma_rotation sends it to ICP too:
    # 2.81 cm before)
    assert ev.ate_rmse < 0.025


def test_tum_cabinet_loop_back_to_the_start_is_closed(cabinet, tmp_path):
    """Textureless: bag-of-words finds nothing, proximity detection (dense registration from
    the graph's pose) links the last keyframes to the first ones."""
    from mnemoslam.storage import LinkType, MapStore

    path, ds, out, out_dir = cabinet  # loop closure on (the default configuration)
    cfg = slam_config()
    assert cfg.loop.enabled
    runs, dirs = {True: out}, {True: out_dir, False: tmp_path / "False"}
    off = slam_config({"loop": {"enabled": False}})
    runs[False] = run_dataset(open_dataset(path), off, dirs[False], progress=False)
    ate = {enabled: evaluate(ds.ground_truth, runs[enabled].keyframes).ate_rmse for enabled in (False, True)}
    # tracking never reads the map update: the odometry of a run with loop closure is the
    # odometry-only run, bit for bit (tests/test_loop_closure.py uses it as the baseline)
    odometry = np.stack([r.odometry_pose for r in runs[True].results if r.tracked])
    assert np.array_equal(odometry, runs[False].trajectory.poses)
    with MapStore(dirs[True] / "map.db", create=False) as store:
        n = store.count_nodes()
        links = store.links(type=LinkType.GLOBAL_CLOSURE) + store.links(type=LinkType.LOCAL_SPACE)
    assert any(x.from_id <= 5 and x.to_id >= n - 10 for x in links), [(x.from_id, x.to_id) for x in links]
    report = evaluate_map_loops(ds.ground_truth, dirs[True] / "map.db", cfg.loop.min_age)
    assert report.false_links == 0, report.format()  # measured: link errors 1-4 cm, <= 3.3°
    assert ate[True] < ate[False], ate  # measured keyframe ATE 2.40 -> 1.98 cm


@pytest.mark.parametrize("name,max_percent,min_tracked", [("a", 1.0, 51), ("b", 1.0, 51)])
def test_kitti_stereo(data_dir, name, max_percent, min_tracked):
    ds, out, ev = _run(require(data_dir / "kitti_odometry_snippets" / "sequences" / name))
    assert out.summary.tracked >= min_tracked
    # measured a: 0.12 %, b: 0.43 % of path (b: grass, trees and moving cars; before the online
    # disparity-offset estimate: 0.30 % and 1.58 %, b's stereo pair is off by ~1.5 px)
    assert ev.ate_percent_of_path < max_percent


def _yaw_degrees(poses: np.ndarray) -> np.ndarray:
    """Each camera's rotation about its own y axis (pan, image x) relative to the first camera,
    in degrees (the y component of the relative rotation vector)."""
    import cv2

    return np.array([np.degrees(cv2.Rodrigues((poses[0, :3, :3].T @ p[:3, :3]).astype(np.float64))[0][1, 0])
                     for p in poses])


def test_euroc_stereo_still_vehicle(data_dir):
    """The EuRoC head's vehicle moves 2 mm in all (1.4 mm first to last), so a tracker that
    never moves has an ATE of 0.66 mm and passes any ATE bound this test could set. What the
    head does show is the camera panning to and fro by up to 0.16° (frames 6-20; the images
    shift by 1.2 px against frame 0 at frame 15, phase correlation). The tracker must follow
    that pan: its frame-to-frame pan error well below the pan itself (which is the error of a
    frozen tracker: checked here as the negative control). Pitch and roll are left out: the
    ground truth drifts 0.11° in pitch over the head while the images move by < 0.01° in
    pitch, and the tracker follows the images."""
    ds, out, ev = _run(require(data_dir / "euroc_v101_head"))
    assert out.summary.tracked == 40
    assert ev.ate_rmse < 0.002, ev.ate_rmse  # measured 0.57 mm (a frozen tracker 0.66)
    est = out.trajectory
    at = np.searchsorted(ds.ground_truth.stamps, est.stamps)
    np.testing.assert_array_equal(ds.ground_truth.stamps[at], est.stamps)
    pan = _yaw_degrees(ds.ground_truth.poses[at])
    assert np.abs(pan).max() > 0.1, pan  # the motion the test relies on (measured 0.16°)

    def rms(x):
        return float(np.sqrt(np.mean(np.square(x))))

    def pan_error(poses):
        """rms error of the frame-to-frame pan against the ground truth's, as a share of the
        ground truth's rms frame-to-frame pan."""
        return rms(np.diff(_yaw_degrees(poses)) - np.diff(pan)) / rms(np.diff(pan))

    frozen = np.repeat(np.eye(4)[None], len(est), axis=0)
    assert pan_error(frozen) == pytest.approx(1.0)  # the negative control: a tracker that never moves
    # measured 0.34 (0.0096° rms against the truth's 0.028°; the pan against frame 0 correlates
    # 0.95, the tracker's 0.61 of the truth's: it under-follows sub-pixel motion)
    assert pan_error(est.poses) < 0.6, pan_error(est.poses)
    assert np.corrcoef(_yaw_degrees(est.poses), pan)[0, 1] > 0.8  # measured 0.95 (frozen: no pan at all)


def test_same_input_same_trajectory_bit_for_bit(data_dir):
    path = require(data_dir / "7scenes_redkitchen")
    a = run_dataset(open_dataset(path, max_frames=120), slam_config(), progress=False).trajectory
    b = run_dataset(open_dataset(path, max_frames=120), slam_config(), progress=False).trajectory
    assert len(a) == 120
    assert np.array_equal(a.poses, b.poses) and np.array_equal(a.stamps, b.stamps)


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "mnemoslam.service.cli", *args], capture_output=True, text=True,
                          timeout=300)


def test_cli_wrong_path_is_one_line(tmp_path):
    r = _cli("run", str(tmp_path / "nope"), "--out", str(tmp_path / "o"))
    assert r.returncode == 2
    assert "no such file or directory" in r.stderr and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


def test_cli_run_with_corrupt_image_names_file_and_goes_on(data_dir, tmp_path):
    src = require(data_dir / "rgbd_dataset_freiburg3_cabinet_keyframes")
    seq = tmp_path / "rgbd_dataset_freiburg3_cabinet_keyframes"
    shutil.copytree(src, seq)
    for p in seq.rglob("*"):
        p.chmod(0o644 if p.is_file() else 0o755)
    victim = sorted((seq / "rgb").iterdir())[3]
    victim.write_bytes(b"not a jpeg")
    r = _cli("run", str(seq), "--out", str(tmp_path / "o"), "-q", "--max-frames", "10",
             "--set", "semantics.enabled=false")
    assert r.returncode == 0, r.stderr
    assert victim.name in r.stderr
    assert "1 unreadable" in r.stdout
    lines = (tmp_path / "o" / "trajectory.tum").read_text().splitlines()
    assert len(lines) == 9
