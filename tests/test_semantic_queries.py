"""The semantic query layer (service.semantics.queries) on arrays shaped as
`MapStore.object_arrays()` returns them: answers checked against brute force, freshness
after the map changes, concurrent readers during rebuilds, paths along a small pose graph."""
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest

from mnemoslam.service.semantics.queries import NotFound, ObjectIndex, QueryError, RobotLocation, robot_location

LABELS = ["door", "chair", "table", "window"]


def arrays(n, seed=0, labels=LABELS, ids=None):
    rng = np.random.default_rng(seed)
    lab = np.array([labels[i] for i in rng.integers(0, len(labels), n)], dtype=object)
    return {
        "id": np.arange(1, n + 1, dtype=np.int64) if ids is None else np.asarray(ids, np.int64),
        "class_id": np.array([labels.index(x) for x in lab], np.int64),
        "labels": lab,
        "position": rng.uniform(-20, 20, (n, 3)),
        "extent": rng.uniform(0.2, 2, (n, 3)),
        "confidence": rng.uniform(0.3, 1, n),
        "observations": rng.integers(1, 50, n),
        "node_id": rng.integers(1, 100, n),
    }


class FakeStore:
    """object_arrays() plus a tiny pose graph: nodes on a line 0..9 at x = id, links i-(i+1),
    and node 20 off to the side, linked to nothing."""

    def __init__(self, a):
        self.a = a
        self.calls = 0
        self.node_pos = {i: (float(i), 0.0, 0.0) for i in range(10)} | {20: (5.0, 5.0, 0.0)}
        self.pairs = np.array([(i, i + 1) for i in range(9)], np.int64)

    def object_arrays(self, label=None):
        self.calls += 1
        return self.a

    def nodes(self, session_id=None, limit=100, offset=0, merged=None, **_):
        out = []
        for i, p in sorted(self.node_pos.items()):
            pose = np.eye(4)
            pose[:3, 3] = p
            out.append(SimpleNamespace(id=i, pose=pose, merged_into=None))
        return out[offset:None if limit is None else offset + limit]

    def count_nodes(self, session_id=None, merged=None, **_):
        return len(self.node_pos)

    def link_pairs(self, types=None):
        return self.pairs

    def get_node(self, node_id):
        return SimpleNamespace(id=node_id, merged_into=3) if node_id == 33 else None


def test_nearest_matches_brute_force():
    a = arrays(5000)
    index = ObjectIndex(FakeStore(a))
    rng = np.random.default_rng(1)
    for q in rng.uniform(-25, 25, (50, 3)):
        for label in LABELS:
            rows = np.flatnonzero(a["labels"] == label)
            d = np.linalg.norm(a["position"][rows] - q, axis=1)
            best = rows[np.argmin(d)]
            got = index.nearest(label, q)
            assert got.object.id == a["id"][best] and got.object.label == label
            assert got.distance == pytest.approx(d.min(), abs=1e-12)
            assert got.node_id == a["node_id"][best] == got.object.node_id
            assert got.object.position == pytest.approx(tuple(a["position"][best]))


def test_nearest_reasons_and_bad_points():
    index = ObjectIndex(FakeStore(arrays(100)))
    with pytest.raises(NotFound, match="no object labelled 'sofa'.*door"):
        index.nearest("sofa", (0, 0, 0))
    with pytest.raises(QueryError):
        index.nearest("door", (0, float("nan"), 0))
    with pytest.raises(QueryError):
        index.nearest("door", (0, 0))
    empty = ObjectIndex(FakeStore(arrays(0)))
    with pytest.raises(NotFound, match="no objects"):
        empty.nearest("door", (0, 0, 0))
    assert empty.labels() == [] and empty.find().total == 0


def test_find_filters_orders_and_pages():
    a = arrays(3000)
    index = ObjectIndex(FakeStore(a))
    q = np.array([1.0, -2.0, 0.5])
    d = np.linalg.norm(a["position"] - q, axis=1)
    for label in (None, "chair"):
        keep = (d <= 8.0) & ((a["labels"] == label) if label else True)
        expect = a["id"][keep][np.lexsort((a["id"][keep], d[keep]))]
        page = index.find(label, q, 8.0, limit=7, offset=3)
        assert page.total == keep.sum() and [o.id for o in page.objects] == list(expect[3:10])
        every = index.find(label, q, 8.0, limit=10**6)
        assert [o.id for o in every.objects] == list(expect)
    by_id = index.find("door", limit=5, offset=2)
    assert [o.id for o in by_id.objects] == list(a["id"][a["labels"] == "door"][2:7])
    assert index.find("door", q, limit=5).objects[0].id == index.nearest("door", q).object.id
    assert index.find("door", offset=10**6).objects == [] and index.find("nothing").total == 0
    with pytest.raises(QueryError, match="radius needs a point"):
        index.find("door", radius=3.0)
    with pytest.raises(QueryError):
        index.find("door", q, radius=-1.0)


def test_get_and_labels():
    a = arrays(500, ids=np.arange(500)[::-1] * 3 + 7)  # unsorted ids
    index = ObjectIndex(FakeStore(a))
    row = 123
    o = index.get(int(a["id"][row]))
    assert o.label == a["labels"][row] and o.extent == pytest.approx(tuple(a["extent"][row]))
    assert o.observations == a["observations"][row] and o.confidence == pytest.approx(a["confidence"][row])
    with pytest.raises(NotFound, match="no object 8"):
        index.get(8)
    counts = dict(index.labels())
    assert counts == {k: int((a["labels"] == k).sum()) for k in LABELS}
    assert [n for _, n in index.labels()] == sorted(counts.values(), reverse=True)


def test_refreshes_when_the_version_changes():
    store = FakeStore(arrays(100))
    version = [0]
    index = ObjectIndex(store, version=lambda: version[0], check_interval=0.0, min_rebuild_interval=0.0)
    first = index.nearest("door", (0, 0, 0))
    assert index.nearest("door", (0, 0, 0)) == first and store.calls == 1  # unchanged: no rebuild
    moved = arrays(100)
    moved["position"] = moved["position"] + 100.0  # loop closure moved everything
    store.a = moved
    version[0] += 1
    index.nearest("door", (0, 0, 0))  # notices; rebuilds in the background
    deadline = time.monotonic() + 5
    while index.rebuilds < 2 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert index.nearest("door", (0, 0, 0)).distance == pytest.approx(
        np.linalg.norm(moved["position"][moved["labels"] == "door"], axis=1).min())
    store.a = arrays(0)
    index.refresh()  # explicit: at once
    with pytest.raises(NotFound):
        index.nearest("door", (0, 0, 0))


def test_real_sqlite_data_version_sees_other_connections(tmp_path):
    import sqlite3

    from mnemoslam.service.semantics.queries import data_version_of
    db = tmp_path / "a map #1?.db"  # characters a file: URI must escape
    w = sqlite3.connect(db)
    w.execute("PRAGMA journal_mode=WAL")
    w.execute("CREATE TABLE t (x)")
    w.commit()
    version = data_version_of(db)
    v0 = version()
    assert version() == v0
    w.execute("INSERT INTO t VALUES (1)")
    w.commit()
    assert version() != v0
    version.close()


def test_concurrent_queries_during_rebuilds():
    store = FakeStore(arrays(2000))
    version = [0]
    index = ObjectIndex(store, version=lambda: version[0], check_interval=0.0, min_rebuild_interval=0.0)
    errors, done = [], threading.Event()

    def reader(seed):
        rng = np.random.default_rng(seed)
        while not done.is_set():
            try:
                q = rng.uniform(-20, 20, 3)
                r = index.nearest("door", q)
                assert r.object.label == "door" and r.distance >= 0
                assert index.find("chair", q, 5.0, limit=3).total >= 0
            except Exception as e:  # noqa: BLE001
                errors.append(e)

    threads = [threading.Thread(target=reader, args=(s,)) for s in range(8)]
    for t in threads:
        t.start()
    for k in range(20):
        store.a = arrays(2000, seed=k)
        version[0] += 1
        time.sleep(0.01)
    done.set()
    for t in threads:
        t.join()
    assert not errors and index.rebuilds >= 2


def test_path_along_the_graph():
    a = arrays(3)
    a["position"] = np.array([[8.2, 0.3, 0.0], [5.0, 5.2, 0.0], [1.0, 0.0, 0.0]])
    index = ObjectIndex(FakeStore(a))
    p = index.path(1, RobotLocation("r1", (0.0, 0.0, 0.0), 2, "tracking"))
    assert p.start_node == 2 and p.goal_node == 8 and p.nodes == list(range(2, 9))
    assert p.positions[0] == (2.0, 0.0, 0.0) and p.length == pytest.approx(6.0)
    assert p.goal_distance == pytest.approx(np.hypot(0.2, 0.3))
    # node 20 sits next to object 2 but no link reaches it: the goal is the nearest reachable node
    p = index.path(2, RobotLocation("r1", (0.0, 0.0, 0.0), None, "tracking"))
    assert p.start_node == 0 and p.goal_node == 5 and p.nodes[0] == 0 and p.nodes[-1] == 5
    # a keyframe merged by rehearsal starts from its survivor
    assert index.path(3, RobotLocation("r1", (9.0, 0.0, 0.0), 33, "tracking")).nodes == [3, 2, 1]
    with pytest.raises(NotFound, match="no object 99"):
        index.path(99, RobotLocation("r1", (0.0, 0.0, 0.0), 2, "tracking"))


def test_robot_location():
    store = FakeStore(arrays(1))
    robots = [{"robot": "r1", "session_id": 1, "position": [1.0, 2.0, 3.0], "node_id": 4},
              {"robot": "r2", "session_id": 2, "pose": list(np.eye(4).reshape(-1))},
              {"robot": "r3", "session_id": 3},
              {"robot": "r4", "session_id": None}]
    assert robot_location(robots, "r1", store) == RobotLocation("r1", (1.0, 2.0, 3.0), 4, "tracking")
    assert robot_location(robots, "r2", store).position == (0.0, 0.0, 0.0)
    loc = robot_location(robots, "r3", store)  # no tracked pose reported: its session's latest keyframe
    assert loc.source == "keyframe" and loc.node_id == 20
    with pytest.raises(NotFound, match="no pose"):
        robot_location(robots, "r4", store)
    with pytest.raises(NotFound, match="unknown robot"):
        robot_location(robots, "r9", store)


def test_nearest_in_spatial_blocks_is_exact():
    """A label with many objects is searched block by block: the same answers as brute force,
    clustered or spread out, for points inside and far outside the map, ties to the lowest id."""
    rng = np.random.default_rng(5)
    for n, spread in ((3000, 20.0), (20_000, 2.0), (600, 500.0)):
        a = arrays(n, seed=n, labels=["door"])
        a["position"] = np.concatenate([rng.normal(0, spread, (n // 2, 3)),
                                        rng.normal(30, spread, (n - n // 2, 3))])
        a["position"][7] = a["position"][n - 3]  # two objects at the same place
        index = ObjectIndex(FakeStore(a))
        assert "door" in index.snapshot().label_blocks
        qs = np.concatenate([rng.uniform(-40, 70, (200, 3)), rng.uniform(-1e4, 1e4, (20, 3)),
                             a["position"][[7, n - 3, 0]]])
        for q in qs:
            d = np.linalg.norm(a["position"] - q, axis=1)
            got = index.nearest("door", q)
            assert got.object.id == a["id"][np.argmin(d)] and got.distance == pytest.approx(d.min())
