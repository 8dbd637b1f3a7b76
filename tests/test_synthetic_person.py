"""The walking person of the synthetic scene (issue 24): a textured box labelled person that
moves between frames, drawn exactly where it is, and nothing else of the frame changed; off
unless asked for (`person=True`, `synthetic:loop?person`)."""
import numpy as np
import pytest

from mnemoslam.client.datasets import open_dataset
from mnemoslam.client.kernel.frames import DatasetError
from mnemoslam.client.synthetic import SyntheticDataset
from mnemoslam.client.synthetic.person import DEPTH, HEIGHT, PERSON, WIDTH, Walk

SMALL = dict(rate=5, width=320, height=240, fx=262.5, max_frames=11)


def _world(f, pose, camera, mask):
    v, u = np.nonzero(mask)
    z = f.depth[v, u].astype(np.float64)
    X = np.stack([(u - camera.cx) / camera.fx * z, (v - camera.cy) / camera.fy * z, z], 1)
    return X @ pose[:3, :3].T + pose[:3, 3]


def test_the_person_walks_where_it_is_drawn_and_changes_nothing_else():
    plain = SyntheticDataset("loop", **SMALL)
    ds = open_dataset("synthetic:loop?person", **SMALL)
    assert plain.person is None and ds.person is not None and "person" in repr(ds)
    ids = {o.instance_id for o in ds.scene.objects}
    walk = ds.person.walk
    centres = []
    for i in (0, 10):
        f, g = ds.frame(i), plain.frame(i)
        mine = f.extras["labels"] == PERSON
        assert mine.sum() > 500, mine.sum()
        assert set(np.unique(f.extras["instances"][mine])) == {ds.person.instance_id}
        assert ds.person.instance_id not in ids
        assert (f.depth[mine] < g.depth[mine]).all()  # in front of what it hides
        for a, b in ((f.image, g.image), (f.depth, g.depth), (f.extras["labels"], g.extras["labels"]),
                     (f.extras["instances"], g.extras["instances"])):
            assert np.array_equal(a[~mine], b[~mine])
        # its pixels lie on its box at the frame's time (world frame, exact depth)
        P = _world(f, ds.pose(i), ds.camera, mine)
        at = walk.position(f.stamp)
        half = np.array([DEPTH, WIDTH]) / 2  # walking along x: its depth along x
        assert (np.abs(P[:, :2] - at) <= half + 1e-3).all() and P[:, 2].min() > -1e-3 and P[:, 2].max() < HEIGHT + 1e-3
        centres.append(at)
    assert np.linalg.norm(centres[1] - centres[0]) > 0.5  # it walked


def test_the_loop_walk_keeps_clear_of_the_camera_and_goes_to_and_fro():
    ds = SyntheticDataset("loop", rate=20, width=32, height=24, fx=26.25, person=True)
    walk = ds.person.walk
    cam = ds.ground_truth.poses[:, :2, 3]
    at = np.array([walk.position(t) for t in ds.stamps])
    gap = np.maximum(np.abs(cam - at) - np.array([DEPTH, WIDTH]) / 2, 0)
    assert np.hypot(gap[:, 0], gap[:, 1]).min() >= 1.0  # never nearer than 1 m to the camera
    assert at[:, 0].min() == pytest.approx(walk.start[0], abs=0.06) and at[:, 0].max() == pytest.approx(walk.end[0],
                                                                                                    abs=0.06)
    w = Walk((0.0, 0.0), (2.0, 0.0), speed=0.5)
    assert [w.position(t)[0] for t in (0, 2, 4, 6, 8, 9)] == pytest.approx([0, 1, 2, 1, 0, 0.5])
    assert Walk((0.0, 0.0), (2.0, 0.0), speed=0.5, phase=4).position(0)[0] == pytest.approx(2)


def test_person_option_errors():
    with pytest.raises(DatasetError, match="unknown synthetic option"):
        open_dataset("synthetic:loop?dog")
    with pytest.raises(DatasetError, match="no person walk"):
        SyntheticDataset("walk_a", person=True)
    ds = SyntheticDataset("walk_a", rate=1, width=32, height=24, fx=26.25, person=Walk((3.0, 1.0), (5.0, 1.0)))
    assert ds.person.walk.end == (5.0, 1.0)
