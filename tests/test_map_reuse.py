"""`odometry.map_reuse` (service/tracking/odometry.py: LocalMap's archive): points trimmed from
the local map come back when the camera looks at them again, and only then."""
import cv2
import numpy as np
import pytest

from mnemoslam.client.kernel.frames import PinholeCamera
from mnemoslam.client.kernel.geometry import invert, make_pose
from mnemoslam.service.config import load_config
from mnemoslam.service.tracking.features import FrameFeatures
from mnemoslam.service.tracking.matching import (
    match_descriptors,
    match_map_points,
    match_map_points_tiled,
    one_per_query,
)
from mnemoslam.service.tracking.odometry import _POINT_FIELDS, Odometry, PointArchive

CAM = PinholeCamera(525.0, 525.0, 319.5, 239.5, 640, 480)


def _world(n=2400, seed=0):
    """Points all around the camera (a shell 3-5 m away, within ±25° of the horizon), each with
    its own descriptor."""
    rng = np.random.default_rng(seed)
    az, el = rng.uniform(-np.pi, np.pi, n), rng.uniform(-0.45, 0.45, n)
    r = rng.uniform(3.0, 5.0, n)
    pts = np.c_[r * np.cos(el) * np.sin(az), r * np.sin(el), r * np.cos(el) * np.cos(az)]
    return pts, rng.integers(0, 256, (n, 32), dtype=np.uint8)


def _observe(pts, desc, pose):
    T_cw = invert(pose)
    pc = pts @ T_cw[:3, :3].T + T_cw[:3, 3]
    front = pc[:, 2] > 0.1
    uv = pc[:, :2] / np.where(front, pc[:, 2], 1.0)[:, None] * [CAM.fx, CAM.fy] + [CAM.cx, CAM.cy]
    ok = front & (uv[:, 0] >= 0) & (uv[:, 0] < 640) & (uv[:, 1] >= 0) & (uv[:, 1] < 480)
    return FrameFeatures(uv[ok].astype(np.float32), desc[ok], pc[ok].astype(np.float32), np.zeros(ok.sum(), np.int8))


def _heading(deg):
    R, _ = cv2.Rodrigues(np.array([0.0, np.radians(deg), 0.0]))
    return make_pose(R, np.zeros(3))


def _sweep(reuse: bool):
    """Turn 180° and back in 6° steps with a local map too small to hold the first view; returns
    the odometry, the ids of the points made at the first frame, the local map's ids at the far
    end of the sweep (with what the archive gives back there) and the last frame's inliers'
    point ids."""
    pts, desc = _world()
    cfg = load_config(overrides={"odometry": {"local_map_size": 300, "map_reuse": reuse, "icp_fallback": False}})
    odo = Odometry(CAM, cfg.odometry)
    headings = list(range(0, 181, 6)) + list(range(174, -1, -6))
    first, far, last = None, None, None
    for i, h in enumerate(headings):
        r = odo.track(_observe(pts, desc, _heading(h)), i / 30)
        assert r.tracked
        if i == 0:
            first = set(r.point_ids[r.point_ids >= 0].tolist())
        if h == 180:  # facing away from the first view: what the archive would give back here
            if reuse:
                odo.map.readmit(r.pose, CAM, 0, cfg.odometry.map_reuse_distance_ratio, cfg.odometry.map_reuse_angle)
            far = set(odo.map.ids.tolist())
        last = r
    assert last is not None and first is not None and far is not None
    return odo, first, far, last.point_ids[last.inlier_mask]


@pytest.mark.parametrize("reuse", [False, True])
def test_trimmed_points_come_back_when_the_camera_looks_at_them_again(reuse):
    """Back at the first heading, the frame tracks against the first frame's points again with
    map reuse (they were trimmed from the local map on the way out: the map holds 300 points,
    a view ~130); without, against points made anew on the way back. At the far end (facing
    away from the first view), none of the first frame's points is in the local map: an archived
    point comes back only in view."""
    odo, first, far, ids = _sweep(reuse)
    assert not (first & far)  # behind the camera: trimmed, and not brought back
    reused = np.isin(ids, list(first)).mean()
    if reuse:
        assert len(ids) >= 60 and reused >= 0.8
        assert len(odo.map.archive) > 0
        # the points that came back are marked so (`odometry.window_ba_hold: returned` holds them)
        assert odo.map.returned[np.isin(odo.map.ids, list(first))].all()
    else:
        assert reused == 0.0 and odo.map.archive is None and not odo.map.returned.any()


def test_matching_from_the_map_keeps_the_oldest_of_duplicate_points():
    """Two map points of one surface point (made on two passes) and one keypoint: the ratio test
    among map points (today's direction) refuses the keypoint, the ratio test per map point over
    the keypoints takes it, and the older map point keeps it; by projection (tiles) the same."""
    rng = np.random.default_rng(3)
    query = rng.integers(0, 256, (50, 32), dtype=np.uint8)
    xy = rng.uniform(0, 640, (50, 2)) * [1, 0.75]
    train = np.concatenate([query[:10], query[:10]])  # ids 0-9 old, 10-19 their newer duplicates
    train[:, 0] ^= 0xFF  # the newer 8 bits from the keypoint's descriptor, the older 9 (the
    train[:10, 1] ^= 1  # closest is not the one kept)
    uv = np.concatenate([xy[:10], xy[:10]]) + 1.0
    q, _ = match_descriptors(query, train, 0.8, 80)
    assert len(q) == 0
    for qi, ti, d in (match_map_points(query, train, 0.8, 80),
                      match_map_points_tiled(query, xy, train, uv, 20.0, 0.8, 80)):
        assert len(qi) == 20
        qk, tk = one_per_query(qi, ti, d, prefer=np.arange(20))
        assert np.array_equal(np.sort(qk), np.arange(10)) and np.array_equal(tk[np.argsort(qk)], np.arange(10))


def test_archive_keeps_what_a_plain_list_of_points_keeps():
    """The archive stores its points in preallocated rows (a point brought back leaves a dead
    row, compacted later): after any sequence of archiving, bringing back and overflowing its
    capacity it holds the same points as plain arrays concatenated and cut would, in the same
    order, and `in_view` never gives a dead row."""
    assert set(_FIELD_SHAPES) == set(_POINT_FIELDS)
    rng = np.random.default_rng(7)
    capacity = 3000
    archive = PointArchive(capacity)
    ref: dict[str, np.ndarray] | None = None
    next_id, stamp = 0, 0
    for step in range(300):
        stamp += 1
        k = int(rng.integers(1, 400))
        batch = {f: np.zeros((k,) + shape, dtype) for f, (shape, dtype) in _FIELD_SHAPES.items()}
        batch["ids"] = np.arange(next_id, next_id + k)
        batch["last_seen"] = stamp - rng.integers(0, 50, k)  # some older than points already in
        batch["points"] = rng.normal(0, 3, (k, 3))
        batch["origins"] = np.zeros((k, 3))
        next_id += k
        archive.add({f: v.copy() for f, v in batch.items()})
        ref = batch if ref is None else {f: np.concatenate([ref[f], batch[f]]) for f in ref}
        if len(ref["ids"]) > capacity:
            keep = np.sort(np.argsort(-ref["last_seen"], kind="stable")[:capacity])
            ref = {f: v[keep] for f, v in ref.items()}
        if step % 3 == 0:  # bring back the points a random camera sees
            pose = make_pose(cv2.Rodrigues(rng.normal(0, 1, 3))[0], rng.normal(0, 0.5, 3))
            idx = archive.in_view(pose, CAM, 2.0, 60.0)
            assert archive.arrays is not None
            popped = archive.pop(idx)
            gone = np.isin(ref["ids"], popped["ids"])
            assert gone.sum() == len(idx)  # every row given was a living one
            ref = {f: v[~gone] for f, v in ref.items()}
        assert len(archive) == len(ref["ids"])
        assert archive.arrays is not None
        living = archive.arrays["ids"][archive.in_view(np.eye(4), CAM, 1e9, 180.0)]
        seen = ref["ids"][_in_front(ref["points"])]
        assert np.array_equal(np.sort(living), np.sort(seen))
    # the living rows, compacted, are the plain arrays (same order)
    archive._compact()
    assert archive.arrays is not None
    for f in ("ids", "last_seen", "points"):
        assert np.array_equal(archive.arrays[f], ref[f])


_FIELD_SHAPES = {"points": ((3,), np.float64), "descriptors": ((32,), np.uint8), "observations": ((), np.int32),
                 "last_seen": ((), np.int64), "rays": ((3,), np.float64), "sigma": ((), np.float64),
                 "origins": ((3,), np.float64), "disparity": ((), np.float64), "cos0": ((), np.float64),
                 "ids": ((), np.int64), "info": ((3, 3), np.float64), "info_x": ((3,), np.float64),
                 "fused": ((), np.int32), "returned": ((), bool)}


def _in_front(points):
    """Which world points a camera at the origin sees inside its image (any distance or angle)."""
    z = points[:, 2]
    zs = np.where(z > 0.05, z, 1.0)
    u, v = points[:, 0] / zs * CAM.fx + CAM.cx, points[:, 1] / zs * CAM.fy + CAM.cy
    return (z > 0.05) & (u >= 0) & (u < CAM.width) & (v >= 0) & (v < CAM.height)
