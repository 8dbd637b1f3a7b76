"""The synthetic scene camera: geometry exactness, labels, trajectories, texture quality, noise."""
import math

import cv2
import numpy as np
import pytest

from mnemoslam.client.datasets import open_dataset
from mnemoslam.client.kernel.frames import DatasetError, PinholeCamera
from mnemoslam.client.kernel.geometry import look_at, rotation_angle
from mnemoslam.client.synthetic import (
    CLASS_NAMES,
    TRAJECTORIES,
    SyntheticDataset,
    SyntheticScene,
    depth_sigma,
    get_scene,
    trajectory,
)

CAM = PinholeCamera(525.0, 525.0, 319.5, 239.5, 640, 480)
SMALL = PinholeCamera(262.5, 262.5, 159.5, 119.5, 320, 240)
TINY = PinholeCamera(65.625, 65.625, 39.5, 29.5, 80, 60)


@pytest.fixture(scope="module")
def scene():
    return get_scene(0)


def backproject(depth, pose, cam, vs, us):
    z = depth[vs, us].astype(np.float64)
    Xc = np.stack([(us - cam.cx) / cam.fx * z, (vs - cam.cy) / cam.fy * z, z], 1)
    return Xc @ pose[:3, :3].T + pose[:3, 3]


# ----------------------------------------------------------------------------- determinism
def test_same_seed_same_arrays_other_seed_other_textures(scene):
    pose = look_at((3.0, 2.5, 1.5), (6.5, 2.5, 1.3))
    a = scene.render(pose, SMALL)
    b = SyntheticScene(0).render(pose, SMALL)  # built from scratch
    for name in ("rgb", "depth", "labels", "instances"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    c = SyntheticScene(1).render(pose, SMALL)
    assert np.array_equal(a.depth, c.depth) and np.array_equal(a.labels, c.labels)  # same geometry
    assert np.abs(a.rgb.astype(int) - c.rgb.astype(int)).mean() > 10  # other textures


def test_render_outputs(scene):
    r = scene.render(look_at((3.0, 2.5, 1.5), (6.5, 2.5, 1.3)), CAM)
    assert r.rgb.shape == (480, 640, 3) and r.rgb.dtype == np.uint8
    assert r.depth.shape == (480, 640) and r.depth.dtype == np.float32
    assert r.labels.dtype == np.uint8 and r.instances.dtype == np.int32
    assert (r.depth > 0).all()  # closed rooms: every ray hits something, no cracks
    assert set(np.unique(r.labels)) <= set(CLASS_NAMES)
    ids = {o.instance_id for o in scene.objects}
    assert set(np.unique(r.instances)) - {0} <= ids


# ----------------------------------------------------------------------------- exact depth
def test_depth_of_a_wall_seen_head_on(scene):
    # living room south wall (y = 0) from 2 m, between the two windows
    pose = look_at((2.8, 2.0, 1.4), (2.8, -1.0, 1.4))
    r = scene.render(pose, CAM)
    wall = r.labels == 1
    assert wall.mean() > 0.5
    assert np.abs(r.depth[wall] - 2.0).max() < 1e-4  # z-depth of a fronto-parallel plane is constant
    assert abs(r.depth[240, 320] - 2.0) < 1e-4
    vs, us = np.nonzero(wall)
    pick = np.random.default_rng(0).choice(len(vs), 50, replace=False)
    X = backproject(r.depth, pose, CAM, vs[pick], us[pick])
    assert np.abs(X[:, 1]).max() < 1e-4


def test_backprojection_lies_on_the_plane_oblique_view(scene):
    # a tilted, rolled camera looking across the office at its east wall (x = 11.1)
    pose = look_at((7.5, 1.0, 1.3), (11.1, 3.5, 2.0), up=(0.1, 0.0, 1.0))
    r = scene.render(pose, CAM)
    q = scene.quads
    east = np.flatnonzero((q.axis == 0) & (np.abs(q.c - 11.1) < 1e-9) & (q.sign < 0) & (q.label_of[1:] == 1)) + 1
    m = np.isin(r.surface, east)
    assert m.mean() > 0.2
    vs, us = np.nonzero(m)
    pick = np.random.default_rng(1).choice(len(vs), 200, replace=False)
    X = backproject(r.depth, pose, CAM, vs[pick], us[pick])
    assert np.abs(X[:, 0] - 11.1).max() < 2e-4
    assert (X[:, 1] >= -1e-3).all() and (X[:, 1] <= 5.0 + 1e-3).all() and (X[:, 2] <= 2.6 + 1e-3).all()
    # incidence output agrees with the geometry (wall normal is -x)
    r2 = scene.render(pose, CAM, incidence=True)
    ray = (X - pose[:3, 3]) / np.linalg.norm(X - pose[:3, 3], axis=1, keepdims=True)
    assert np.allclose(r2.incidence[vs[pick], us[pick]], np.abs(ray[:, 0]), atol=1e-4)


# ----------------------------------------------------------------------------- labels
def test_objects_listed(scene):
    classes = {o.class_id for o in scene.objects}
    for cid in (9, 11, 15, 16, 20, 23, 24, 25):
        assert cid in classes, CLASS_NAMES[cid]
    assert len(scene.objects_of_class(15)) >= 4
    for o in scene.objects:
        assert np.all(np.array(o.bbox_min) < np.array(o.bbox_max)), o
        assert o.class_name == CLASS_NAMES[o.class_id]
    assert len({o.instance_id for o in scene.objects}) == len(scene.objects)


def test_door_visible_as_door(scene):
    door = scene.objects_of_class(15)[0]
    c = door.center
    # the door is on a wall: step 2 m out along the wall normal (the thin bbox axis)
    axis = int(np.argmin(np.subtract(door.bbox_max, door.bbox_min)))
    n = np.zeros(3)
    n[axis] = 1.0 if c[axis] < 1.0 else -1.0
    eye = c + 2.0 * n
    eye[2] = 1.5
    r = scene.render(look_at(eye, (c[0], c[1], 1.0)), CAM)
    assert r.labels[240, 320] == 15
    assert r.instances[240, 320] == door.instance_id
    assert (r.instances == door.instance_id).mean() > 0.15
    assert ((r.labels == 15) == (r.instances == door.instance_id)).all()


def test_floor_window_painting_ceiling_labels(scene):
    assert scene.render(look_at((3.5, 3.2, 1.5), (3.55, 3.2, 0.0)), CAM).labels[240, 320] == 4
    assert scene.render(look_at((3.0, 3.5, 1.5), (3.05, 3.5, 2.6)), CAM).labels[240, 320] == 6
    win = scene.objects_of_class(9)[0]
    c = win.center
    assert scene.render(look_at((c[0], 2.0, 1.5), (c[0], 0.0, c[2])), CAM).labels[240, 320] == 9
    art = scene.objects_of_class(23)[0]
    c = art.center
    assert scene.render(look_at((2.0, c[1], 1.5), (0.0, c[1], c[2])), CAM).labels[240, 320] == 23


# ----------------------------------------------------------------------------- trajectories
def test_loop_returns_to_its_start_pose():
    path = trajectory("loop")
    assert 50 <= path.duration <= 70
    a, b = path(0.0), path(path.duration)
    assert np.linalg.norm(a[:3, 3] - b[:3, 3]) < 0.01
    assert math.degrees(rotation_angle(a[:3, :3].T @ b[:3, :3])) < 0.5
    ds = SyntheticDataset("loop", rate=10.0)
    gt = ds.ground_truth
    assert gt.stamps[-1] == pytest.approx(path.duration)
    assert np.linalg.norm(gt.positions[0] - gt.positions[-1]) < 0.01
    assert gt.path_length() > 15


def test_figure8_revisits_places():
    path = trajectory("figure8")
    assert 80 <= path.duration <= 100
    t = np.arange(0, path.duration, 0.25)
    P = path(t)
    dpos = np.linalg.norm(P[:, None, :3, 3] - P[None, :, :3, 3], axis=-1)
    rel = np.einsum("aji,bjk->abik", P[:, :3, :3], P[:, :3, :3])
    ang = np.degrees(rotation_angle(rel))
    far_in_time = np.abs(t[:, None] - t[None, :]) >= 10.0
    revisit = far_in_time & (dpos < 0.3) & (ang < 20)
    assert revisit.sum() > 100
    # revisits spread over the path, not one spot
    assert len(np.unique(np.nonzero(revisit)[0] // 40)) >= 5


# walks (fastrot: its own test)
@pytest.mark.parametrize("name", [n for n, spec in TRAJECTORIES.items() if not spec.spin])
def test_trajectory_is_walkable(scene, name):
    path = trajectory(name)
    t = np.arange(0, path.duration + 1e-9, 0.1)
    P = path(t)
    pos = P[:, :3, 3]
    assert scene.inside_free_space(pos).all()
    assert scene.clearance(pos).min() > 0.3
    assert np.all(np.abs(pos[:, 2] - 1.5) < 0.1)
    speed = np.linalg.norm(np.diff(pos, axis=0), axis=1) / 0.1
    assert speed.max() < 0.8 and 0.25 < speed.mean() < 0.6
    turn = np.degrees(rotation_angle(np.einsum("nji,njk->nik", P[:-1, :3, :3], P[1:, :3, :3]))) / 0.1
    assert turn.max() < 45
    assert np.all(np.abs(P[:, 2, 2]) < math.sin(math.radians(15)))  # looking roughly horizontally
    # never facing a surface from too close: min depth over frames (every 0.5 s)
    mins = [scene.render(p, TINY, rgb=False).depth.min() for p in P[::5]]
    assert min(mins) > 0.5


def test_walks_start_apart_and_overlap():
    a, b = trajectory("walk_a"), trajectory("walk_b")
    pa = a.positions(np.arange(0, a.duration, 0.5))
    pb = b.positions(np.arange(0, b.duration, 0.5))
    assert np.linalg.norm(pa[0] - pb[0]) > 2.0
    d = np.linalg.norm(pa[:, None] - pb[None], axis=-1)
    assert (d.min(1) < 0.3).sum() >= 5  # shared stretches


def test_straight_is_straight_and_never_revisits():
    path = trajectory("straight")
    P = path(np.arange(0, path.duration, 0.5))
    pos = P[:, :3, 3]
    assert np.ptp(pos[:, 1]) < 0.05 and np.ptp(pos[:, 0]) > 7.0
    assert np.all(np.diff(pos[:, 0]) >= 0)


def test_straight_sees_the_repeated_poster(scene):
    posters = [o for o in scene.objects if o.name.startswith("poster")]
    assert len(posters) >= 5
    path = trajectory("straight")
    seen = set()
    for p in path(np.arange(0, path.duration, 1.0)):
        seen |= set(np.unique(scene.render(p, TINY, rgb=False).instances).tolist())
    assert {o.instance_id for o in posters} <= seen


# ----------------------------------------------------------------------------- texture quality
def _orb_pair(scene, p1, p2):
    orb = cv2.ORB_create(nfeatures=1000)
    g1 = cv2.cvtColor(scene.render(p1, CAM).rgb, cv2.COLOR_BGR2GRAY)
    g2 = cv2.cvtColor(scene.render(p2, CAM).rgb, cv2.COLOR_BGR2GRAY)
    k1, d1 = orb.detectAndCompute(g1, None)
    k2, d2 = orb.detectAndCompute(g2, None)
    matches = [m for m in cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(d1, d2) if m.distance < 50]
    return len(k1), len(matches) / max(1, len(k1))


def _step(path, t, dist=0.1):
    p0 = path(t)[:3, 3]
    dt = 0.02
    while np.linalg.norm(path(t + dt)[:3, 3] - p0) < dist:
        dt += 0.02
    return t + dt


@pytest.mark.parametrize("name,t", [("loop", 8.0), ("figure8", 30.0), ("walk_b", 12.0)])
def test_orb_features_and_matches_on_typical_frames(scene, name, t):
    path = trajectory(name)
    n, frac = _orb_pair(scene, path(t), path(_step(path, t)))
    assert n >= 500
    assert frac >= 0.3


@pytest.mark.parametrize("dist", [0.5, 1.0, 2.0, 4.0])
def test_orb_features_at_all_distances(scene, dist):
    # facing the living room's east wall (x = 6) head-on, then 10 cm to the side
    eye, tgt = np.array([6.0 - dist, 3.9, 1.5]), np.array([6.0, 3.9, 1.4])
    side = np.array([0.0, 0.1, 0.0])
    n, frac = _orb_pair(scene, look_at(eye, tgt), look_at(eye + side, tgt + side))
    assert n >= 500, f"{n} features at {dist} m"
    assert frac >= 0.3, f"{frac:.2f} matched at {dist} m"


def test_orb_features_far_down_the_hall(scene):
    n, frac = _orb_pair(scene, look_at((5.0, 6.2, 1.5), (11.1, 6.2, 1.3)), look_at((5.1, 6.2, 1.5), (11.1, 6.2, 1.3)))
    assert n >= 500 and frac >= 0.3


# ----------------------------------------------------------------------------- dataset
def test_dataset_basics():
    ds = open_dataset("synthetic:walk_a", rate=10.0, width=320, height=240, fx=262.5, max_frames=12)
    assert isinstance(ds, SyntheticDataset)
    assert ds.name == "synthetic-walk_a" and ds.format == "synthetic" and len(ds) == 12
    cal = ds.calibration
    assert cal.kind == "rgbd" and cal.depth_scale == 1000
    assert (cal.camera.fx, cal.camera.fy, cal.camera.cx, cal.camera.cy) == (262.5, 262.5, 159.5, 119.5)
    f = ds.frame(3)
    assert f.index == 3 and f.stamp == pytest.approx(0.3) and f.source == "synthetic:walk_a#3"
    assert f.image.shape == (240, 320, 3) and f.depth.dtype == np.float32
    assert f.extras["labels"].shape == (240, 320) and f.extras["instances"].dtype == np.int32
    assert np.allclose(ds.ground_truth.stamps, np.arange(12) / 10.0)
    assert np.array_equal(ds.ground_truth.poses[3], trajectory("walk_a")(0.3))
    with pytest.raises(IndexError):
        ds.frame(12)
    assert len(list(ds)) == 12
    full = SyntheticDataset("straight", rate=5.0, scene=ds.scene)
    assert len(full) == round(trajectory("straight").duration * 5) + 1


def test_duration_rescales_the_same_path():
    ds = SyntheticDataset("loop", rate=10.0, duration=30.0)
    assert len(ds) == 301
    gt = ds.ground_truth
    assert np.linalg.norm(gt.positions[0] - gt.positions[-1]) < 0.01
    assert gt.path_length() == pytest.approx(SyntheticDataset("loop", rate=20.0).ground_truth.path_length(), rel=0.02)


def test_unknown_trajectory_raises_dataset_error():
    with pytest.raises(DatasetError) as e:
        SyntheticDataset(trajectory="nowhere")
    for name in TRAJECTORIES:
        assert name in str(e.value)
    with pytest.raises(DatasetError):
        open_dataset("synthetic:nowhere")


def test_noise_model():
    clean = SyntheticDataset("loop", rate=10.0, max_frames=20)
    noisy = SyntheticDataset("loop", rate=10.0, max_frames=20, noise=True)
    a, b = clean.frame(15), noisy.frame(15)
    assert np.array_equal(b.depth, noisy.frame(15).depth)  # deterministic
    assert not np.array_equal(b.depth, SyntheticDataset("loop", rate=10.0, noise=True, seed=3).frame(15).depth)
    missing = (b.depth == 0) & (a.depth > 0)
    assert 0.015 < missing.mean() < 0.4
    ok = (a.depth > 0) & (b.depth > 0)
    assert np.allclose(b.depth[ok] * 1000, np.round(b.depth[ok] * 1000), atol=1e-3)  # 1 mm steps
    err = (b.depth - a.depth)[ok]
    z = a.depth[ok]
    for lo, hi in ((1.0, 2.0), (2.5, 4.0)):
        sel = (z >= lo) & (z < hi)
        assert sel.sum() > 2000
        expect = np.sqrt(np.mean(depth_sigma(z[sel]) ** 2) + 0.001 ** 2 / 12)
        assert abs(err[sel].mean()) < 0.2 * expect + 1e-4
        assert err[sel].std() == pytest.approx(expect, rel=0.2)
    # grazing surfaces lose their depth
    r = clean.scene.render(clean.pose(15), clean.camera, incidence=True)
    grazing = (r.incidence < math.cos(math.radians(75))) & (a.depth > 0)
    assert grazing.any() and (b.depth[grazing] == 0).all()
    d = b.image.astype(float) - a.image.astype(float)
    assert 1.5 < d.std() < 2.5 and abs(d.mean()) < 0.2


def test_frames_kept_on_disk_read_back_bit_for_bit(tmp_path, monkeypatch):
    """With CACHE_ENV set (the test suite's session sets it) a frame rendered is written once and
    read back by any later dataset of the same sequence, arrays and dtypes identical to a fresh
    render; a frame file that is not whole is rendered again; another seed, size, noise or a
    person is another sequence; a scene of one's own is never kept."""
    from mnemoslam.client.synthetic.dataset import CACHE_ENV, Walk

    specs = [dict(trajectory="loop", rate=10.0, max_frames=3, noise=True), dict(trajectory="loop", max_frames=3),
             dict(trajectory="walk_a", rate=5.0, max_frames=3, width=80, height=60, fx=65.625, noise="kinect"),
             dict(trajectory="loop", max_frames=3, person=Walk((0.5, 0.5), (2.0, 0.5), 0.5, 0.0), width=320,
                  height=240)]
    fresh = [[SyntheticDataset(**kw).frame(i) for i in range(3)] for kw in specs]  # (the variable unset here)
    monkeypatch.setenv(CACHE_ENV, str(tmp_path))
    for kw, ref in zip(specs, fresh):
        for _ in range(2):  # written, then read back
            for i, want in enumerate(ref):
                got = SyntheticDataset(**kw).frame(i)
                assert (got.index, got.stamp, got.source) == (want.index, want.stamp, want.source)
                for a, b in [(got.image, want.image), (got.depth, want.depth),
                             *((got.extras[k], want.extras[k]) for k in want.extras)]:
                    assert a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b) and a.flags.writeable
    folders = sorted(tmp_path.iterdir())
    assert len(folders) == len(specs) and all(len(list(f.glob("*.frame"))) == 3 for f in folders)
    assert not list(tmp_path.glob("*/.*"))  # no temporary file left
    key = SyntheticDataset(**specs[0])._cache_key
    kept = tmp_path / key / "0.frame"
    data = kept.read_bytes()
    kept.write_bytes(bytes(len(data)))  # read back, not rendered: a file of zeros gives a black frame
    assert not SyntheticDataset(**specs[0]).frame(0).image.any()
    kept.write_bytes(data[:-1])  # not whole: rendered again, and written whole
    assert np.array_equal(SyntheticDataset(**specs[0]).frame(0).depth, fresh[0][0].depth)
    assert kept.read_bytes() == data
    own = SyntheticDataset("loop", max_frames=2, scene=SyntheticScene(0))
    own.frame(0)
    assert len(list(tmp_path.iterdir())) == len(specs)  # its own scene: not kept
