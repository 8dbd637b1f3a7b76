"""Occupancy grids (issue 25): the local grid of a keyframe from its depth, its storage."""
import cv2
import numpy as np
import pytest

from client.synthetic.dataset import SyntheticDataset
from service.config import GridConfig
from service.grid.local import FREE, OCCUPIED, LocalGrid, LocalGridMaker, angle_deg, fit_floor
from storage import LocalGridRecord, MapStore, UnknownIdError

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
    from client.geometry import make_pose

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
    from client.frames import Calibration, PinholeCamera
    from storage import KeyframeRecord

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
