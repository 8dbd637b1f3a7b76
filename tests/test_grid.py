"""Occupancy grids (issue 25): the local grid of a keyframe from its depth, its storage."""
import cv2
import numpy as np
import pytest

from mnemoslam.client.synthetic.dataset import SyntheticDataset
from mnemoslam.service.config import GridConfig
from mnemoslam.service.grid.assembly import G_OCCUPIED, GlobalGrid
from mnemoslam.service.grid.local import (
    FREE,
    OCCUPIED,
    LocalGrid,
    LocalGridMaker,
    StoredLocalGrid,
    angle_deg,
    fit_floor,
)
from mnemoslam.storage import LocalGridRecord, MapStore, UnknownIdError

Z_UP = np.array([0.0, 0.0, 1.0])


@pytest.fixture(scope="module")
def walk():
    return SyntheticDataset("walk_b", rate=5.0)


def _world_cells(g: LocalGrid, pose: np.ndarray, state: int) -> np.ndarray:
    """World (x, y) of the centres of a local grid's cells in `state` (z on the floor)."""
    iy, ix = np.nonzero(g.cells == state)
    local = np.stack([(ix + g.origin_x + 0.5) * g.cell_size, (iy + g.origin_y + 0.5) * g.cell_size,
                      np.zeros(len(ix)), np.ones(len(ix))])
    return ((pose @ g.T_cam_local) @ local)[:3].T


def _near_obstacle(scene, xy: np.ndarray, r: float) -> np.ndarray:
    """Whether a column within r of each floor point holds a wall or an object (0.1 to 1.8 m)."""
    out = np.zeros(len(xy), bool)
    for z in (0.1, 0.4, 0.8, 1.2, 1.7):
        for dx, dy in ((0, 0), (r, 0), (-r, 0), (0, r), (0, -r)):
            p = np.column_stack([xy[:, 0] + dx, xy[:, 1] + dy, np.full(len(xy), z)])
            out |= ~scene.inside_free_space(p)
    return out


def test_local_grid_matches_the_scene(walk):
    """Up within 0.3° of the truth, the camera height within 3 cm, and the cells where the scene
    has them: occupied cells at walls or furniture, free cells in the open (one cell's slack)."""
    mk = LocalGridMaker(walk.calibration.camera, GridConfig())
    T0 = walk.ground_truth.poses[0]
    occ_ok = free_ok = occ_n = free_n = 0
    for i in range(0, len(walk), 15):
        gt = walk.ground_truth.poses[i]
        g = mk.make(walk.frame(i).depth, np.linalg.inv(T0) @ gt, 0)
        assert g.up_source in ("floor", "session")
        assert angle_deg(g.up, gt[:3, :3].T @ Z_UP) < 0.3  # measured ≤ 0.12°
        assert abs(g.camera_height - gt[2, 3]) < 0.03  # measured ≤ 1 cm
        occ = _world_cells(g, gt, OCCUPIED)[:, :2]
        free = _world_cells(g, gt, FREE)[:, :2]
        assert len(occ) > 50 and len(free) > 500
        occ_ok += _near_obstacle(walk.scene, occ, 0.05).sum()
        free_ok += (~_near_obstacle(walk.scene, free, 0.0)).sum() + 0
        occ_n, free_n = occ_n + len(occ), free_n + len(free)
    # measured: occupied 99.5 %, free 97.6 % (free includes cells rays cross above low furniture)
    assert occ_ok / occ_n > 0.97
    assert free_ok / free_n > 0.93


def test_floor_found_by_a_camera_tilted_far_from_its_mounting(walk):
    """A camera pitched down 35° and rolled 12° (far from the configured level mounting) finds
    the floor from the surface normals; a wall alone is no floor."""
    from mnemoslam.client.kernel.geometry import make_pose

    cfg = GridConfig()
    p, b, a = np.array([3.0, 2.5, 1.4]), np.radians(35), np.radians(12)
    fwd = np.array([np.cos(b), 0, -np.sin(b)])  # looking +x and down
    R = np.column_stack([np.cross(fwd, Z_UP) / np.linalg.norm(np.cross(fwd, Z_UP)), None, fwd][::2])
    y = np.cross(fwd, R[:, 0])
    R = np.column_stack([R[:, 0], y, fwd])  # x right, y down, z forward
    Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    pose = make_pose(R @ Rz, p)
    depth = walk.scene.render(pose, walk.calibration.camera, rgb=False).depth
    g = LocalGridMaker(walk.calibration.camera, cfg).make(depth)
    up_true = pose[:3, :3].T @ Z_UP
    assert angle_deg(cfg.up, up_true) > 35
    assert g.up_source == "floor" and angle_deg(g.up, up_true) < 0.3 and abs(g.camera_height - 1.4) < 0.02
    rng = np.random.default_rng(1)
    wall = np.column_stack([rng.uniform(-2, 2, 3000), rng.uniform(-1, 1.3, 3000), np.full(3000, 2.0)])
    normals = np.tile([0.0, 0.0, -1.0], (3000, 1))
    assert fit_floor(wall, np.array([0.0, -1.0, 0.0]), cfg, normals) is None
    assert fit_floor(wall, np.array([0.0, -1.0, 0.0]), cfg) is None


def test_local_grid_cost_and_size(walk):
    """A keyframe's grid is a few kB stored; its cost is bench/bench_grid.py's to measure."""
    mk = LocalGridMaker(walk.calibration.camera, GridConfig())
    g = mk.make(walk.frame(40).depth, np.eye(4), 0)
    blob = g.encode_cells()
    assert len(blob) < 4000
    np.testing.assert_array_equal(LocalGrid.decode_cells(blob), g.cells)


def _v6(path):
    """A database at schema v6 with one session and one keyframe with depth."""
    from mnemoslam.client.kernel.frames import Calibration, PinholeCamera
    from mnemoslam.storage import KeyframeRecord

    class V6(MapStore):
        MIGRATIONS = MapStore.MIGRATIONS[:6]

    png = cv2.imencode(".png", np.full((4, 4), 1500, np.uint16))[1].tobytes()
    with V6(path) as s:
        sid = s.begin_session("r1", Calibration(PinholeCamera(525, 525, 319.5, 239.5, 640, 480)))
        nid = s.add_keyframe(KeyframeRecord(sid, 0.0, np.eye(4), np.zeros((0, 2), np.float32),
                                            np.zeros((0, 32), np.uint8), np.zeros((0, 3), np.float32),
                                            depth_png=png))
        assert s.schema_version == 6
    return nid


def test_local_grids_storage_and_migration(tmp_path):
    nid = _v6(tmp_path / "m.db")
    with MapStore(tmp_path / "m.db") as s:
        assert s.schema_version == 7
        assert s.nodes_without_grid() == [nid]  # made from its stored depth when needed
        T = np.eye(4)
        T[:3, 3] = (0, 1.4, 0)
        rec = LocalGridRecord(nid, 0.05, T, -3, 2, b"png", "floor", 812)
        assert s.save_local_grids([rec]) == 1
        back = s.local_grids([nid, 999])[nid]
        np.testing.assert_array_equal(back.transform, T)
        assert (back.origin_x, back.origin_y, back.cells, back.up_source, back.floor_points) == (-3, 2, b"png",
                                                                                                    "floor", 812)
        assert s.nodes_without_grid() == []
        cols = s.grid_nodes()
        assert cols["id"].tolist() == [nid] and cols["has_grid"].tolist() == [True]
        with pytest.raises(UnknownIdError):
            s.save_local_grids([LocalGridRecord(999, 0.05, T, 0, 0, b"x")])
        with pytest.raises(ValueError):
            s.save_local_grids([LocalGridRecord(nid, 0.0, T, 0, 0, b"x")])


# -- the map's grid: assembly ----------------------------------------------------------------------
@pytest.fixture(scope="module")
def walk_grids(walk):
    """Local grids of every 4th frame of walk_b (true poses, in the first camera's frame)."""
    mk = LocalGridMaker(walk.calibration.camera, GridConfig())
    T0inv = np.linalg.inv(walk.ground_truth.poses[0])
    poses, grids = [], {}
    for k, i in enumerate(range(0, len(walk), 4)):
        pose = T0inv @ walk.ground_truth.poses[i]
        g = mk.make(walk.frame(i).depth, pose, 0)
        rec = LocalGridRecord(k + 1, g.cell_size, g.T_cam_local, g.origin_x, g.origin_y, g.encode_cells(),
                              g.up_source, g.floor_points)
        grids[k + 1] = StoredLocalGrid(rec)
        poses.append(pose)
    return np.arange(1, len(poses) + 1), np.stack(poses), grids


def _corrected(poses: np.ndarray, metres: float) -> np.ndarray:
    """Poses bent as a loop closure corrects them: a yaw and a shift growing along the path."""
    out = poses.copy()
    for i in range(len(poses)):
        f = i / (len(poses) - 1)
        a = np.radians(2.0) * f
        R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])  # about the map's y
        out[i, :3, :3] = R @ poses[i, :3, :3]
        out[i, :3, 3] = R @ poses[i, :3, 3] + np.array([metres * f, 0, 0])
    return out


@pytest.mark.parametrize("update_error,share", [(0.0, 0.4), (0.01, 0.4), (0.0, 0.9)])
def test_grid_after_a_loop_closure_equals_one_from_scratch(walk_grids, update_error, share):
    """Keyframes added one by one, then the poses of the last `share` of them corrected (a 2° /
    10 cm bend): the grid updated incrementally (moved keyframes taken out and placed again,
    none added twice; when most moved, all placed again on empty counts) equals the grid
    assembled from scratch at the corrected poses: bit for bit with update_error 0, all but
    the cells of keyframes that moved < 1 cm with the default."""
    ids, poses, grids = walk_grids
    cfg = GridConfig(update_error=update_error, frame_nodes=3)
    g = GlobalGrid(cfg)
    for k in range(10, len(ids) + 1, 10):
        g.update(ids[:k], poses[:k], grids)
    g.update(ids, poses, grids)
    first = g.image()
    bent = _corrected(poses, 0.10)
    keep = int(len(ids) * (1 - share))
    bent[:keep] = poses[:keep]  # the older keyframes (and the grid frame's) stay
    bent[keep:] = poses[keep - 1] @ np.linalg.inv(bent[keep - 1]) @ bent[keep:]  # continuous at the bend
    stats = g.update(ids, bent, grids)
    assert stats["added"] == 0 and stats["moved"] >= 0.8 * share * len(ids)
    assert stats["rebuilt"] == (share > 0.5)  # most moved: placed again on empty counts
    assert g.image() is not first  # the image follows
    scratch = GlobalGrid(cfg)
    scratch.update(ids, bent, grids)
    h1, m1, o1 = g.counts()
    h2, m2, o2 = scratch.counts()
    if update_error == 0:
        assert o1 == o2
        np.testing.assert_array_equal(h1, h2)
        np.testing.assert_array_equal(m1, m2)
        np.testing.assert_array_equal(g.image().states, scratch.image().states)
    else:
        a, b = g.image(), scratch.image()
        assert a.states.shape == b.states.shape
        assert np.mean(a.states == b.states) > 0.995
    # a grid that did not follow the correction differs
    stale = GlobalGrid(cfg)
    stale.update(ids, poses, grids)
    assert stale.image().states.shape != scratch.image().states.shape or \
        np.mean(stale.image().states == scratch.image().states) < 0.97


def test_grid_resampled_keeps_obstacles(walk_grids):
    ids, poses, grids = walk_grids
    g = GlobalGrid(GridConfig())
    g.update(ids, poses, grids)
    img = g.image()
    coarse = img.resampled(0.1)
    assert coarse.resolution == 0.1
    assert abs(coarse.width - img.width / 2) <= 1 and abs(coarse.height - img.height / 2) <= 1
    # every occupied 5 cm cell lies in an occupied 10 cm cell
    iy, ix = np.nonzero(img.states == G_OCCUPIED)
    cy = np.floor((img.origin[1] + (iy + 0.5) * 0.05 - coarse.origin[1]) / 0.1).astype(int)
    cx = np.floor((img.origin[0] + (ix + 0.5) * 0.05 - coarse.origin[0]) / 0.1).astype(int)
    assert np.all(coarse.states[cy, cx] == G_OCCUPIED)
    fine = img.resampled(0.025)
    assert np.mean(fine.states[1::2, 1::2][:img.height, :img.width] == img.states[:fine.height // 2,
                                                                                   :fine.width // 2]) > 0.99


def _store_with(path, walk_grids, sessions=1):
    """A store whose keyframes carry walk_b's local grids, chained by odometry links; with two
    sessions the second half is a second session (a second map until a link joins them)."""
    from mnemoslam.client.kernel.frames import Calibration, PinholeCamera
    from mnemoslam.storage import KeyframeRecord

    ids, poses, grids = walk_grids
    s = MapStore(path)
    cal = Calibration(PinholeCamera(525, 525, 319.5, 239.5, 640, 480))
    half = len(ids) // 2
    sid = s.begin_session("r1", cal)
    node_of, prev = {}, None
    for k, n in enumerate(ids):
        if sessions == 2 and k == half:
            sid, prev = s.begin_session("r2", cal), None
        link = None if prev is None else (prev, np.linalg.inv(poses[k - 1]) @ poses[k], None)
        nid = s.add_keyframe(KeyframeRecord(sid, float(k), poses[k], np.zeros((0, 2), np.float32),
                                            np.zeros((0, 32), np.uint8), np.zeros((0, 3), np.float32),
                                            odom_link=link))
        g = grids[int(n)]
        s.save_local_grids([LocalGridRecord(nid, g.cell_size, g.T_cam_local, g.origin_x, g.origin_y, g.encode_cells(),
                                            g.up_source, g.floor_points)])
        node_of[int(n)], prev = nid, nid
    return s, node_of


def test_map_grids_follow_the_store(tmp_path, walk_grids):
    """MapGrids: one grid per map; it follows poses moved in the store (as the map update
    writes them) and equals a fresh assembly; two maps until a link joins them."""
    from mnemoslam.service.grid.maps import MapGrids, NoMap
    from mnemoslam.storage import LinkType

    ids, poses, grids = walk_grids
    cfg = GridConfig(update_error=0.0, frame_nodes=5)
    s, node_of = _store_with(tmp_path / "a.db", walk_grids, sessions=2)
    with s:
        mg = MapGrids(s, cfg)
        assert sorted(mg.maps()) == [0, 1]
        a0, a1 = mg.grid(0), mg.grid(1)
        assert a0.keyframes + a1.keyframes == len(ids)
        assert mg.grid(0) is a0 and mg.last_update.get("unchanged")  # nothing committed since: no pose read
        with pytest.raises(NoMap, match="no map 7"):
            mg.grid(7)
        # a loop link joins the second session to the first: one map of every keyframe
        first, last = node_of[int(ids[0])], node_of[int(ids[len(ids) // 2])]
        s.add_link(first, last, int(LinkType.GLOBAL_CLOSURE), np.linalg.inv(poses[0]) @ poses[len(ids) // 2])
        assert sorted(mg.maps()) == [0]
        assert mg.grid(0).keyframes == len(ids) and not mg.last_update.get("unchanged")
        bent = _corrected(poses, 0.1)
        bent[:5] = poses[:5]
        s.update_poses({node_of[int(n)]: bent[k] for k, n in enumerate(ids)})
        img = mg.grid(0)
        assert mg.last_update["moved"] > len(ids) // 2 and mg.last_update["added"] == 0
        fresh = MapGrids(s, cfg).grid(0)
        np.testing.assert_array_equal(img.states, fresh.states)
        assert img.origin == fresh.origin


def test_background_assembly_serves_the_last_grid_then_follows(tmp_path, walk_grids):
    """With the background thread (grid.refresh_interval): a request after a loop closure does
    not wait for the re-placing (max_wait 0: the last grid, not current), the thread brings it
    up to date by itself (a periodic pass, no request), and then it equals a from-scratch
    assembly at the corrected poses."""
    import time

    from mnemoslam.service.grid.maps import MapGrids, NoMap

    ids, poses, grids = walk_grids
    cfg = GridConfig(update_error=0.0, frame_nodes=5, refresh_interval=0.2)
    s, node_of = _store_with(tmp_path / "b.db", walk_grids)
    with s:
        mg = MapGrids(s, cfg)
        try:
            first, current = mg.latest(0, max_wait=0)  # the first request waits for the first assembly
            assert current and first.keyframes == len(ids)
            with pytest.raises(NoMap, match="no map 3"):
                mg.latest(3, max_wait=0)
            bent = _corrected(poses, 0.1)
            bent[:5] = poses[:5]
            s.update_poses({node_of[int(n)]: bent[k] for k, n in enumerate(ids)})
            stale, current = mg.latest(0, max_wait=0)
            assert not current and stale is first  # served at once: the pass it started is under way
            fresh = MapGrids(s, cfg).grid(0)  # (refresh_interval plays no part in `grid`)
            assert not np.array_equal(stale.states, fresh.states) or stale.origin != fresh.origin
            deadline = time.monotonic() + 30
            while mg.published(0) is first and time.monotonic() < deadline:  # no request: the thread's own passes
                time.sleep(0.05)
            img = mg.published(0)
            np.testing.assert_array_equal(img.states, fresh.states)
            assert img.origin == fresh.origin
            again, current = mg.latest(0, max_wait=30)
            assert current and again is img  # nothing changed since: the same image
        finally:
            mg.close()
        assert mg._thread is not None and not mg._thread.is_alive()


def test_run_out_writes_grid_cloud_and_groundtruth(tmp_path):
    """`run --out DIR` (run_dataset) writes grid.pgm + grid.yaml, cloud.ply and, for the synthetic
    scene, groundtruth_grid.pgm + .yaml on the same cells; the grid agrees with it."""
    import yaml

    from mnemoslam.client.datasets import open_dataset
    from mnemoslam.service.config import load_config
    from mnemoslam.service.grid.cloud import read_ply
    from mnemoslam.service.grid.files import agreement, read_grid
    from mnemoslam.service.runner import run_dataset

    ds = open_dataset("synthetic:walk_b", rate=5, max_frames=50)
    out = run_dataset(ds, load_config(overrides={"semantics": {"enabled": False}}), tmp_path, progress=False)
    for name in ("grid.pgm", "grid.yaml", "cloud.ply", "groundtruth_grid.pgm", "groundtruth_grid.yaml"):
        assert (tmp_path / name).is_file(), name
    y = yaml.safe_load((tmp_path / "grid.yaml").read_text())
    assert y["image"] == "grid.pgm" and y["resolution"] == 0.05 and len(y["map_to_grid"]) == 16
    grid, truth = read_grid(tmp_path / "grid.yaml"), read_grid(tmp_path / "groundtruth_grid.yaml")
    np.testing.assert_allclose(truth.map_to_grid, grid.map_to_grid)
    a = agreement(grid, truth)
    assert a["observed"] > 5000 and a["agree"] > 0.93, a  # measured 96.8 % on the whole walk at 30 Hz
    assert out.grid["groundtruth_agree"] == pytest.approx(a["agree"])
    P, C = read_ply((tmp_path / "cloud.ply").read_bytes())
    assert len(P) > 10000 and C.shape == P.shape
    # `db export` writes the same grid (and the cloud) from the database
    from mnemoslam.service.cli import main

    assert main(["db", "export", str(tmp_path / "map.db"), "--out", str(tmp_path / "export")]) == 0
    again = read_grid(tmp_path / "export" / "grid.yaml")
    np.testing.assert_array_equal(again.states, grid.states)
    assert (tmp_path / "export" / "cloud.ply").is_file()


def test_up_from_the_mean_of_accelerometer_readings(walk):
    """Keyframes with an accelerometer reading (specific force in camera axes, each tilted 5° off
    gravity in a random direction, as a handheld camera's accelerations do): from the
    ACCEL_MIN_READINGS-th on, the grid's up is the session's mean reading turned into the
    odometry frame: within 1.5° of the truth where one reading is 5° off (measured 0.42° median,
    0.69° worst over 25 keyframes), and the floor still gives the camera height."""
    from mnemoslam.service.grid.local import ACCEL_MIN_READINGS

    mk = LocalGridMaker(walk.calibration.camera, GridConfig())
    rng = np.random.default_rng(3)
    T0 = walk.ground_truth.poses[0]
    errs, sources = [], []
    for k, i in enumerate(range(0, len(walk), 5)):
        gt = walk.ground_truth.poses[i]
        up = gt[:3, :3].T @ Z_UP
        axis = np.cross(up, rng.normal(size=3))
        axis /= np.linalg.norm(axis)
        t = np.radians(5.0)  # Rodrigues: `up` turned 5° about an axis perpendicular to it
        reading = 9.81 * (up * np.cos(t) + np.cross(axis, up) * np.sin(t))
        g = mk.make(walk.frame(i).depth, np.linalg.inv(T0) @ gt, 0, accel=reading)
        sources.append(g.up_source)
        if k >= ACCEL_MIN_READINGS - 1:
            errs.append(angle_deg(g.up, up))
            assert abs(g.camera_height - gt[2, 3]) < 0.05  # measured ≤ 2 cm
    assert sources[ACCEL_MIN_READINGS - 1:] == ["accelerometer"] * (len(sources) - ACCEL_MIN_READINGS + 1)
    assert set(sources[:ACCEL_MIN_READINGS - 1]) <= {"floor", "session", "accelerometer"}
    assert len(errs) >= 10 and max(errs) < 1.5, errs
