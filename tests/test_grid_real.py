"""Occupancy grids on real data (issue 25): the grid of 7-Scenes redkitchen (a person walking a
kitchen with a handheld Kinect) leaves the camera's own positions free; on TUM fr1/desk the up
direction found from the floor (and the desk) agrees with the Kinect's accelerometer.

Poses are the datasets' ground truth (the grid, not tracking, is under test here; SLAM's poses on
these sequences are within 3-4 cm of it, bench/run_sequences.py)."""
import itertools

import numpy as np
import pytest

from mnemoslam.client.datasets import open_dataset
from mnemoslam.client.datasets.subrange import FrameRange
from mnemoslam.client.datasets.tum import ACCEL_TO_CAMERA
from mnemoslam.service.config import GridConfig
from mnemoslam.service.evaluation import associate_stamps
from mnemoslam.service.grid.assembly import G_FREE, G_OCCUPIED, GlobalGrid
from mnemoslam.service.grid.local import ACCEL_MIN_READINGS, LocalGridMaker, StoredLocalGrid, angle_deg
from mnemoslam.service.runner import run_dataset
from mnemoslam.storage import LocalGridRecord, MapStore
from tests.conftest import require, slam_config

# ACCEL_TO_CAMERA (the TUM player's): the Kinect's accelerometer (TUM's accelerometer.txt, ax ay
# az) in the colour camera's axes (x right, y down, z forward), found from fr1/desk
# (`test_accelerometer_axes_found_from_the_data`): its x and y point opposite to the camera's.
# At rest it reads +g along up.


def _grid_of(ds, poses, every: int, cfg: GridConfig):
    mk = LocalGridMaker(ds.calibration.camera, cfg)
    grids, ids, kept = {}, [], []
    for k, i in enumerate(range(0, len(ds), every)):
        g = mk.make(ds.frame(i).depth, poses[i], 0)
        grids[k] = StoredLocalGrid(LocalGridRecord(k, g.cell_size, g.T_cam_local, g.origin_x, g.origin_y,
                                                   g.encode_cells(), g.up_source, g.floor_points))
        ids.append(k)
        kept.append(poses[i])
    G = GlobalGrid(cfg)
    G.update(ids, np.stack(kept), grids)
    return G.image()


def _states_at(img, points):
    out = np.full(len(points), -2)
    for j, p in enumerate(img.to_grid(points)):
        r, c = img.cell_of(p)
        if 0 <= r < img.height and 0 <= c < img.width:
            out[j] = img.states[r, c]
    return out


@pytest.fixture(scope="module")
def kitchen(data_dir):
    ds = open_dataset(require(data_dir / "7scenes_redkitchen"))
    poses = np.linalg.inv(ds.ground_truth.poses[0]) @ ds.ground_truth.poses  # the map frame: the first camera's
    return ds, poses


def test_redkitchen_camera_positions_are_free(kitchen):
    """≥ 90 % of the camera's 1,000 positions (every frame, the grid from every 10th) fall in free
    cells (measured 100 % with the default footprint of 0.2 m, RTAB-Map's GridGlobal/FootprintRadius);
    without the footprint, from what the depth saw alone: 72 % free, 15 % occupied (the camera held
    over the counter's edge), the rest never seen (behind the camera)."""
    ds, poses = kitchen
    cams = poses[:, :3, 3]
    img = _grid_of(ds, poses, 10, GridConfig())
    st = _states_at(img, cams)
    assert np.mean(st == G_FREE) >= 0.90
    # the floor is found (the grid's floor 1.2-1.6 m below the camera, a person's hands) and the
    # kitchen has walls and counters
    assert 1.2 < np.median(img.to_grid(cams)[:, 2]) < 1.6
    assert (img.states == G_OCCUPIED).sum() > 1000 and (img.states == G_FREE).sum() > 1500  # measured 2.4k, 3.4k
    bare = _grid_of(ds, poses, 10, GridConfig(footprint_radius=0.0))
    st = _states_at(bare, cams)
    assert np.mean(st == G_FREE) > 0.55 and np.mean(st == G_OCCUPIED) < 0.25  # measured 0.72, 0.15


def _desk(data_dir):
    path = require(data_dir / "rgbd_dataset_freiburg1_desk")
    ds = open_dataset(path)
    acc = np.loadtxt(path / "accelerometer.txt")
    return ds, acc


def test_accelerometer_axes_found_from_the_data(data_dir):
    """Of the 48 signed axis permutations, the one that makes the accelerometer's gravity steadiest
    in the world (ground-truth rotations) and up (+z of the motion-capture world: the specific
    force at rest points up) is ACCEL_TO_CAMERA. Steadiness alone cannot tell a convention from
    its negation (0.992 both; x negated next, 0.971); the mean then lies 3.1° from +z (the
    ground truth's camera orientation is ~3° off the Kinect's, docs/data.md)."""
    ds, acc = _desk(data_dir)
    ig, ie = associate_stamps(ds.ground_truth.stamps, acc[:, 0], max_dt=0.01)
    R = ds.ground_truth.poses[ig, :3, :3]
    a = acc[ie, 1:] / np.linalg.norm(acc[ie, 1:], axis=1, keepdims=True)
    best, score, best_mean = None, -1.0, None
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((-1.0, 1.0), repeat=3):
            M = np.zeros((3, 3))
            M[range(3), perm] = signs
            g = np.einsum("nij,nj->ni", R, a @ M.T).mean(axis=0)
            s = np.linalg.norm(g) if g[2] > 0 else -1.0  # 1 when gravity is one direction in the world
            if s > score + 1e-9:
                best, score, best_mean = M, s, g
    np.testing.assert_array_equal(best, ACCEL_TO_CAMERA)
    assert score > 0.98 and angle_deg(best_mean, [0.0, 0.0, 1.0]) < 5.0


def test_desk_up_from_the_floor_agrees_with_the_accelerometer(data_dir):
    """The map grid's up (`map_to_grid`'s z: the keyframes' up from the floors and desk tops seen,
    every 5th frame's local grid as the keyframe writer makes them) and the accelerometer's mean
    gravity, both in the ground truth's world, agree within 3° (measured 1.1°; the session's own
    floor estimate 1.05°). One frame's accelerometer is off the up of its keyframe by several
    degrees (median 4.0° where a floor was seen: a handheld camera accelerates). (The grids here
    are made without the accelerometer: the floor's up alone.)"""
    ds, acc = _desk(data_dir)
    gt = ds.ground_truth
    cfg = GridConfig()
    mk = LocalGridMaker(ds.calibration.camera, cfg)
    grids, ids, poses, g_sum, per_frame = {}, [], [], np.zeros(3), []
    for k, i in enumerate(range(0, len(ds), 5)):
        f = ds.frame(i)
        ig, _ = associate_stamps(gt.stamps, np.array([f.stamp]))
        if not len(ig):
            continue
        pose = gt.poses[ig[0]]
        a = acc[np.abs(acc[:, 0] - f.stamp) < 0.05, 1:].mean(axis=0)
        a_cam = ACCEL_TO_CAMERA @ a / np.linalg.norm(a)
        g_sum += pose[:3, :3] @ a_cam
        g = mk.make(f.depth, pose, 0)
        if g.floor_points:
            per_frame.append(angle_deg(g.up, a_cam))
        grids[k] = StoredLocalGrid(LocalGridRecord(k, g.cell_size, g.T_cam_local, g.origin_x, g.origin_y,
                                                   g.encode_cells(), g.up_source, g.floor_points))
        ids.append(k)
        poses.append(pose)
    G = GlobalGrid(cfg)
    G.update(ids, np.stack(poses), grids)
    assert len(per_frame) > 20 and sum(g.up_source == "floor" for g in grids.values()) >= 1  # measured 32
    assert angle_deg(G.map_to_grid[2, :3], g_sum) < 3.0
    assert angle_deg(mk.session_up, g_sum) < 2.0
    assert np.median(per_frame) > 2.0  # the single readings are what an average over the map fixes


def test_desk_player_gives_each_frame_its_accelerometer_reading(data_dir):
    """The TUM player reads accelerometer.txt: each frame's `extras["accel"]` is the reading at
    its stamp (linear between the two either side) in the camera's axes; a folder without the
    file gives frames without it."""
    ds, acc = _desk(data_dir)
    assert all("accel" in ds.frame(i).extras for i in range(0, len(ds), 50))
    f = ds.frame(100)
    j = np.searchsorted(acc[:, 0], f.stamp)
    lo, hi = ACCEL_TO_CAMERA @ acc[j - 1, 1:], ACCEL_TO_CAMERA @ acc[j, 1:]
    w = (f.stamp - acc[j - 1, 0]) / (acc[j, 0] - acc[j - 1, 0])
    np.testing.assert_allclose(f.extras["accel"], (1 - w) * lo + w * hi, atol=1e-12)
    assert 9.0 < np.linalg.norm(f.extras["accel"]) < 10.6
    assert f.extras["accel"][1] < -5.0  # the camera upright: up is its -y (specific force, +g along up)


@pytest.fixture(scope="module")
def desk_stretch(data_dir, tmp_path_factory):
    """fr1/desk frames 360-560 (the floor in view for most of it) through the pipeline: the
    camera's own poses (the ground truth's camera orientation is ~3° off the depth camera's,
    docs/data.md, which would blur a per-keyframe comparison)."""
    path = require(data_dir / "rgbd_dataset_freiburg1_desk")
    ds = FrameRange(open_dataset(path), 360, 560)
    out_dir = tmp_path_factory.mktemp("desk_stretch")
    return ds, run_dataset(ds, slam_config(), out_dir, progress=False), out_dir


def test_desk_grid_up_is_the_accelerometers_and_agrees_with_the_floor(desk_stretch):
    """With the accelerometer, the keyframes' grids take the session's accelerometer gravity as
    their up (`up_source` "accelerometer" once ACCEL_MIN_READINGS keyframes had a reading), and
    per keyframe where a floor is found in depth, the floor's normal agrees with that gravity
    (the session's mean reading, in its frame): median 1.4° measured, p90 2.7°, worst 7.5° (a
    small far floor patch); the session's mean floor 1.1°; one keyframe's own reading 4.3°
    median (a handheld camera accelerates: why the mean). A wrong axis convention finds fewer
    floors along it and disagrees more (bench/grid_up.py's replay of frames 360-560 at the full
    run's poses: -x -y z 37 floors of 40, median 1.2°; x negated 28, 2.3° (the camera's roll is
    within ±5° here: the 48-permutation test above tells the x sign best); y negated 3, 25°; z
    negated 12, 87°; y and z swapped 0)."""
    ds, out, out_dir = desk_stretch
    with MapStore(out_dir / "map.db") as s:
        ids = s.grid_nodes()["id"]
        sources = [r.up_source for r in s.local_grids(ids.tolist()).values()]
    # every keyframe has a reading: the accelerometer leads from the ACCEL_MIN_READINGS-th on
    assert len(sources) > 20 and sources.count("accelerometer") == len(sources) - (ACCEL_MIN_READINGS - 1)
    tr = out.trajectory
    it, idx = associate_stamps(tr.stamps, ds.stamps, max_dt=0.005)
    mk = LocalGridMaker(ds.calibration.camera, GridConfig())
    made = []
    for k, j in list(zip(it, idx))[::5]:
        f = ds.frame(int(j))
        g = mk.make(f.depth, tr.poses[k], 0, accel=f.extras["accel"])
        made.append((g, f.extras["accel"], tr.poses[k][:3, :3]))
    floors = [(g, a, R) for g, a, R in made if g.floor_up is not None]
    per_kf = np.array([angle_deg(g.floor_up, R.T @ mk.gravity_up) for g, _, R in floors])
    reading = np.array([angle_deg(g.floor_up, a) for g, a, _ in floors])
    print(f"{len(floors)} of {len(made)} with a floor; floor vs gravity median {np.median(per_kf):.2f} p90 "
          f"{np.percentile(per_kf, 90):.2f} worst "
          f"{per_kf.max():.2f}; vs own reading median {np.median(reading):.2f}; session floor vs gravity "
          f"{angle_deg(mk.floor_up, mk.gravity_up):.2f}")
    assert len(floors) >= 32  # measured 37 of 40
    assert np.median(per_kf) < 2.0 and np.percentile(per_kf, 90) < 6.0  # issue 25: within 3°
    assert angle_deg(mk.floor_up, mk.gravity_up) < 1.8
    assert np.median(reading) > np.median(per_kf)
