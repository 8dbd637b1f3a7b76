"""The SQLite long-term memory: real database files in tmp_path, no mocks."""
from __future__ import annotations

import dataclasses
import inspect
import json
import os
import re
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Protocol

import numpy as np
import pytest

from mnemoslam.client.kernel.frames import Calibration, PinholeCamera
from mnemoslam.client.kernel.trajectory import read_tum
from mnemoslam.storage import (
    ApiStore,
    GridStore,
    KeyframeLog,
    KeyframeRecord,
    LinkType,
    MapReader,
    MapStore,
    MapUpdateStore,
    ObjectRecord,
    SemanticStore,
    StoreError,
    UnknownIdError,
    WordStore,
)
from mnemoslam.storage.cli import db_export, db_info
from mnemoslam.storage.codec import pack, unpack
from mnemoslam.storage.connection import Connection
from mnemoslam.storage.grids import Grids
from mnemoslam.storage.nodes import Nodes
from mnemoslam.storage.objects import Objects
from mnemoslam.storage.queries import Queries
from mnemoslam.storage.sessions import Sessions
from mnemoslam.storage.words import Words

ROOT = Path(__file__).resolve().parents[1]
CAL = Calibration(PinholeCamera(525.0, 525.0, 319.5, 239.5, 640, 480), None, 5000.0)
STEREO = Calibration(PinholeCamera(718.856, 718.856, 607.19, 185.22, 1241, 376), 0.537, 1000.0)
JPEG = b"\xff\xd8\xff\xe0" + bytes(range(200)) + b"\xff\xd9"
PNG = b"\x89PNG\r\n\x1a\n" + bytes(range(256)) * 3


def pose(x=0.0, y=0.0, z=0.0, yaw=0.0) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    P = np.eye(4)
    P[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    P[:3, 3] = (x, y, z)
    return P


def record(rng, session_id, stamp=0.0, P=None, n=50, **kw) -> KeyframeRecord:
    pts = rng.normal(size=(n, 3)).astype(np.float32)
    pts[::7] = np.nan  # keypoints without depth
    return KeyframeRecord(
        session_id=session_id, stamp=stamp, pose=pose() if P is None else P,
        keypoints=(rng.random((n, 2)) * 640).astype(np.float32),
        descriptors=rng.integers(0, 256, (n, 32), dtype=np.uint8), points=pts, **kw)


def rows(path, sql, params=()):
    c = sqlite3.connect(path, isolation_level=None)  # autocommit; closed at once
    try:
        return c.execute(sql, params).fetchall()
    finally:
        c.close()


V = len(MapStore.MIGRATIONS)  # the current schema version


@pytest.fixture
def rng():
    return np.random.default_rng(7)


@pytest.fixture
def store(tmp_path):
    with MapStore(tmp_path / "map.db") as s:
        yield s


# -- the store's parts and roles ----------------------------------------------------------------

ROLES = (KeyframeLog, WordStore, MapUpdateStore, SemanticStore, MapReader, ApiStore, GridStore)
PARTS = (Connection, Sessions, Nodes, Queries, Words, Objects, Grids)


def _methods(cls) -> set[str]:
    """The public methods `cls` declares (with those of the protocols it extends)."""
    out = set()
    for c in cls.__mro__:
        if c in (object, Protocol) or c.__module__ == "typing":
            continue
        out |= {n for n, v in vars(c).items() if callable(v) and not n.startswith("_")}
    return out


def test_map_store_is_its_parts_each_method_unchanged(store):
    """MapStore is composed of its parts: every public method of every part is a MapStore
    method with the part's signature and docstring (calling it reaches the part)."""
    for part in PARTS:
        for name in sorted(_methods(part) - {"read", "write"}):  # (the parts' transactions)
            assert inspect.signature(getattr(MapStore, name)) == inspect.signature(getattr(part, name)), name
            assert getattr(MapStore, name).__doc__ == getattr(part, name).__doc__, name
    assert not isinstance(store, PARTS)  # composed, not inherited
    assert store.db.path == store.path


def test_map_store_implements_every_role(store):
    for role in ROLES:
        assert isinstance(store, role), role.__name__
        for name in sorted(_methods(role)):  # same parameters, defaults and annotations
            assert inspect.signature(getattr(MapStore, name)) == inspect.signature(getattr(role, name)), \
                (role.__name__, name)

    class Partial:  # any method missing: not a keyframe log
        begin_session = MapStore.begin_session
        end_session = MapStore.end_session
    assert not isinstance(Partial(), KeyframeLog)
    assert not isinstance(store, type("Other", (), {}))
    assert _methods(KeyframeLog) == {"begin_session", "end_session", "add_keyframe", "save_local_grids"}
    assert not _methods(MapReader) & {"add_keyframe", "add_link", "update_poses", "set_statistics", "merge_node",
                                      "set_label", "save_objects", "delete_objects", "mark_segmented"}


# Each caller's role, and the modules that call the store as that role.
CALLERS = {
    KeyframeLog: ["service/memory/keyframes.py"],
    MapUpdateStore: ["service/memory/manager.py", "service/memory/views.py", "service/memory/vocabulary.py"],
    SemanticStore: ["service/semantics/worker.py"],
    ApiStore: ["service/api/**/*.py", "service/viewer.py", "service/metrics.py", "service/semantics/queries.py"],
    GridStore: ["service/grid/*.py"],
}


def store_calls(source: str) -> set[str]:
    """The methods `source` calls on a map (`store.x(`, `self.store.x(`, `self._store.x(`)."""
    return {m.group(1) for m in re.finditer(r"(?<![\w])_?store(?:\(\))?\.(\w+)\(", source)}


def test_each_caller_calls_only_its_role():
    """What each module handed a map calls on it is in the role its annotation names: a new
    call outside the role fails here (add it to the role, or go through the right caller)."""
    assert store_calls("self.store.add_link(a, b)\nx = self._store.load_images(n)\nstore.stats()") == {
        "add_link", "load_images", "stats"}
    for role, patterns in CALLERS.items():
        files = sorted({p for pattern in patterns for p in ROOT.glob(pattern)})
        assert files, patterns
        called = set().union(*(store_calls(p.read_text()) for p in files))
        assert called and called <= _methods(role), (role.__name__, sorted(called - _methods(role)))


def test_the_map_update_reaches_the_store_through_memory_only():
    """RTAB-Map's Memory is the only path to its DBDriver: `service/mapping` calls no store
    method itself (the mapping child, which opens the file, only closes it); memory does."""
    for p in sorted((ROOT / "service" / "mapping").glob("*.py")):
        called = store_calls(p.read_text())
        assert called <= ({"close"} if p.name == "process.py" else set()), (p.name, sorted(called))


# -- round trip / encodings -----------------------------------------------------------------


def test_keyframe_round_trip_is_bit_exact(store, rng):
    sid = store.begin_session("r1", CAL, {"features": {"max_features": 500}})
    first = store.add_keyframe(record(rng, sid, 1.0))
    P = pose(0.1234567890123, -2.5e-9, 3.0, yaw=0.3)
    T = np.linalg.inv(pose()) @ P
    info = np.diag(np.arange(1.0, 7.0)) * 1e4
    rec = record(rng, sid, 1.5, P, n=500, weight=3, image_jpeg=JPEG, depth_png=PNG,
                 odom_link=(first, T, info), word_ids=rng.integers(0, 2**31 - 1, 500).astype(np.int32),
                 statistics={"inliers": np.int64(123), "ms": np.float32(4.5), "nan": float("nan"),
                             "arr": np.arange(3), "nested": {"ok": True}})
    nid = store.add_keyframe(rec)
    assert nid == first + 1

    node = store.get_node(nid)
    assert (node.id, node.session_id, node.robot, node.stamp, node.weight, node.label) == (nid, sid, "r1", 1.5, 3, None)
    assert node.pose.dtype == np.float64 and node.pose.tobytes() == P.tobytes()
    assert np.array_equal(node.position, P[:3, 3])

    kp, desc, pts, words = store.load_features(nid)
    for got, want in ((kp, rec.keypoints), (desc, rec.descriptors), (pts, rec.points), (words, rec.word_ids)):
        assert got.dtype == want.dtype and got.shape == want.shape
        assert got.tobytes() == want.tobytes()  # bit-exact, NaN rows included
        assert got.flags.writeable
    assert store.load_features(first)[3] is None

    assert store.load_images(nid) == (JPEG, PNG)
    assert store.load_images(first) == (None, None)
    assert store.statistics(nid) == {"inliers": 123, "ms": 4.5, "nan": None, "arr": [0, 1, 2], "nested": {"ok": True}}
    assert store.statistics(first) is None

    (link,) = store.links(node_ids=[nid])
    assert (link.from_id, link.to_id, link.type) == (first, nid, LinkType.NEIGHBOR)
    assert link.transform.tobytes() == T.tobytes() and link.information.tobytes() == info.tobytes()

    assert store.get_node(9999) is None
    with pytest.raises(UnknownIdError):
        store.load_features(9999)
    with pytest.raises(UnknownIdError):
        store.load_images(9999)


def test_pose_blob_layout_and_empty_features(store, rng, tmp_path):
    sid = store.begin_session("r1", CAL)
    P = pose(1, 2, 3, yaw=1.0)
    nid = store.add_keyframe(record(rng, sid, 0.0, P, n=0))
    kp, desc, pts, words = store.load_features(nid)
    assert kp.shape == (0, 2) and desc.shape == (0, 32) and pts.shape == (0, 3) and words is None
    blob, x, y, z = rows(tmp_path / "map.db", "SELECT pose, x, y, z FROM nodes WHERE id = ?", (nid,))[0]
    assert len(blob) == 128 and np.frombuffer(blob, "<f8").reshape(4, 4).tobytes() == P.tobytes()
    assert (x, y, z) == (1.0, 2.0, 3.0)


def test_pack_unpack_little_endian():
    a = np.arange(6, dtype=">f4").reshape(3, 2)  # big-endian input is stored little-endian
    blob = pack(a, np.float32)
    assert blob == np.arange(6, dtype="<f4").tobytes()
    b = unpack(blob, np.float32, (3, 2))
    assert b.dtype == np.float32 and np.array_equal(a, b)
    with pytest.raises(StoreError, match="corrupt blob"):
        unpack(blob[:-1], np.float32, (3, 2))


def test_change_counter_sees_every_commit(tmp_path):
    """The object index's freshness check: `PRAGMA data_version` on a connection of its own
    changes with each commit of the store's writer and of any other connection or process."""
    path = tmp_path / "a map #1?.db"  # characters a file: URI must escape
    with MapStore(path) as s:
        counter = s.change_counter()
        v0 = counter()
        assert counter() == v0 and s.sessions() == [] and counter() == v0  # reads change nothing
        s.begin_session("r1", CAL)  # the store's own writer
        v1 = counter()
        assert v1 != v0
        rows(path, "INSERT INTO admin (key, value) VALUES ('note', '1')")  # another connection
        assert counter() != v1
        counter.close()
        with pytest.raises(StoreError, match="change counter"):
            counter()


# -- bad input ------------------------------------------------------------------------------


def _bad(rng, sid, **change):
    rec = record(rng, sid, 1.0)
    for k, v in change.items():
        setattr(rec, k, v(rec) if callable(v) else v)
    return rec


BAD = {
    "keypoints float64": dict(keypoints=lambda r: r.keypoints.astype(np.float64)),
    "keypoints (N, 3)": dict(keypoints=lambda r: np.zeros((len(r.keypoints), 3), np.float32)),
    "descriptors (N, 31)": dict(descriptors=lambda r: r.descriptors[:, :31]),
    "descriptors float": dict(descriptors=lambda r: r.descriptors.astype(np.float32)),
    "points count": dict(points=lambda r: r.points[:-1]),
    "points list": dict(points=lambda r: r.points.tolist()),
    "word_ids int64": dict(word_ids=lambda r: np.zeros(len(r.keypoints), np.int64)),
    "pose 3x4": dict(pose=np.eye(4)[:3]),
    "pose NaN": dict(pose=np.full((4, 4), np.nan)),
    "pose bottom row": dict(pose=np.ones((4, 4))),
    "stamp NaN": dict(stamp=float("nan")),
    "stamp str": dict(stamp="1.0"),
    "weight float": dict(weight=1.5),
    "jpeg not jpeg": dict(image_jpeg=b"GIF89a..."),
    "png str": dict(depth_png="not bytes"),
    "odom_link short": dict(odom_link=(1,)),
    "odom_link transform": dict(odom_link=(1, np.eye(3), None)),
    "odom_link information": dict(odom_link=(1, np.eye(4), np.eye(5))),
    "statistics not JSON": dict(statistics={"bad": object()}),
    "statistics not dict": dict(statistics=[1, 2]),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_record_is_a_value_error_before_any_write(store, rng, tmp_path, case):
    sid = store.begin_session("r1", CAL)
    store.add_keyframe(record(rng, sid, 0.0))
    with pytest.raises(ValueError) as e:
        store.add_keyframe(_bad(rng, sid, **BAD[case]))
    assert str(e.value)
    assert store.count_nodes() == 1
    assert rows(tmp_path / "map.db", "SELECT COUNT(*) FROM features")[0][0] == 1


# -- atomicity ------------------------------------------------------------------------------


def _row_counts(path):
    return {t: rows(path, f"SELECT COUNT(*) FROM {t}")[0][0]
            for t in ("nodes", "features", "images", "links", "statistics")}


def test_failure_midway_leaves_no_partial_node(store, rng, tmp_path):
    db = tmp_path / "map.db"
    sid = store.begin_session("r1", CAL)
    a = store.add_keyframe(record(rng, sid, 0.0, image_jpeg=JPEG, statistics={"k": 1}))
    before = _row_counts(db)
    # The odometry link is inserted after node, features and images: an unknown from-node
    # fails its foreign key there and everything of the keyframe is rolled back.
    with pytest.raises(UnknownIdError, match="odometry link from node 777"):
        store.add_keyframe(record(rng, sid, 1.0, image_jpeg=JPEG, depth_png=PNG, statistics={"k": 2},
                                  odom_link=(777, np.eye(4), None)))
    assert _row_counts(db) == before
    assert store.integrity_check() == "ok"
    # The store keeps working and the id sequence was not advanced by the failed keyframe.
    b = store.add_keyframe(record(rng, sid, 1.0, odom_link=(a, np.eye(4), None)))
    assert b == a + 1


def test_failure_in_the_last_statement_rolls_back_everything(store, rng, tmp_path):
    db = tmp_path / "map.db"
    sid = store.begin_session("r1", CAL)
    a = store.add_keyframe(record(rng, sid, 0.0))
    before = _row_counts(db)
    # Inject a real SQLite failure into the statistics insert, the transaction's last one.
    rows(db, "CREATE TRIGGER boom BEFORE INSERT ON statistics BEGIN SELECT RAISE(ABORT, 'injected failure'); END")
    with pytest.raises(StoreError, match="injected failure"):
        store.add_keyframe(record(rng, sid, 1.0, image_jpeg=JPEG, odom_link=(a, np.eye(4), None), statistics={"x": 1}))
    assert _row_counts(db) == before
    rows(db, "DROP TRIGGER boom")
    store.add_keyframe(record(rng, sid, 1.0, odom_link=(a, np.eye(4), None), statistics={"x": 1}))
    assert _row_counts(db)["statistics"] == 1


# -- updates --------------------------------------------------------------------------------


def test_update_poses_moves_nodes_and_is_all_or_nothing(store, rng):
    sid = store.begin_session("r1", CAL)
    ids = [store.add_keyframe(record(rng, sid, i, pose(i, 0, 0))) for i in range(5)]
    new = {ids[1]: pose(10, 10, 10, yaw=0.5), ids[3]: pose(-5, 1, 2)}
    assert store.update_poses(new) == 2
    assert store.get_node(ids[1]).pose.tobytes() == new[ids[1]].tobytes()
    assert store.get_node(ids[0]).pose.tobytes() == pose(0, 0, 0).tobytes()
    # x, y, z (and the spatial index) follow the pose
    assert [n.id for n in store.nodes(bbox=((9, 9, 9), (11, 11, 11)))] == [ids[1]]
    assert [n.id for n in store.nodes(bbox=((0.5, -1, -1), (3.5, 1, 1)))] == [ids[2]]
    with pytest.raises(UnknownIdError, match="12345"):
        store.update_poses({ids[0]: pose(50, 0, 0), 12345: pose()})
    assert store.get_node(ids[0]).pose[0, 3] == 0.0  # rolled back
    with pytest.raises(ValueError):
        store.update_poses({ids[0]: np.eye(3)})
    assert store.update_poses({}) == 0


def test_labels_are_unique(store, rng):
    sid = store.begin_session("r1", CAL)
    a, b = (store.add_keyframe(record(rng, sid, i)) for i in range(2))
    store.set_label(a, "kitchen")
    assert store.get_node(a).label == "kitchen" and store.node_by_label("kitchen").id == a
    with pytest.raises(StoreError, match=f"already on node {a}"):
        store.set_label(b, "kitchen")
    store.set_label(a, None)
    store.set_label(b, "kitchen")
    assert store.node_by_label("kitchen").id == b
    with pytest.raises(UnknownIdError):
        store.set_label(999, "x")


def test_set_word_ids(store, rng):
    sid = store.begin_session("r1", CAL)
    a = store.add_keyframe(record(rng, sid, 0, n=20))
    w = np.arange(20, dtype=np.int32)
    store.set_word_ids(a, w)
    assert np.array_equal(store.load_features(a)[3], w)
    with pytest.raises(ValueError, match="19 word_ids"):
        store.set_word_ids(a, w[:19])
    store.set_word_ids(a, None)
    assert store.load_features(a)[3] is None


def test_save_node_words_writes_ids_and_words_in_one_transaction(store, rng, tmp_path):
    sid = store.begin_session("r1", CAL)
    a = store.add_keyframe(record(rng, sid, 0, n=6))
    b = store.add_keyframe(record(rng, sid, 1, n=4))
    desc = rng.integers(0, 256, (5, 32), dtype=np.uint8)
    store.save_node_words(a, np.array([0, 1, 2, -1, 3, 4]), np.arange(5), desc)
    assert np.array_equal(store.load_features(a)[3], [0, 1, 2, -1, 3, 4])
    ids, d = store.load_words()
    assert np.array_equal(ids, np.arange(5)) and np.array_equal(d, desc)
    assert rows(tmp_path / "map.db", "SELECT descriptor FROM words WHERE id = 3") == [(desc[3].tobytes(),)]
    # b refers to old words and one new one (sparse ids are fine)
    store.save_node_words(b, np.array([4, 10, 10, 0], np.int32), np.array([10]), desc[:1])
    assert store.count_words() == 6 and store.get_info("next_word_id") == 11
    st = store.load_vocabulary_state()
    assert np.array_equal(st["word_ids"], [0, 1, 2, 3, 4, 10]) and st["next_id"][0] == 11
    got = sorted(zip(st["post_node"].tolist(), st["post_word"].tolist(), st["post_count"].tolist()))
    assert got == [(a, 0, 1), (a, 1, 1), (a, 2, 1), (a, 3, 1), (a, 4, 1), (b, 0, 1), (b, 4, 1), (b, 10, 2)]
    assert dict(zip(st["node_ids"].tolist(), st["node_nfeat"].tolist())) == {a: 5, b: 4}

    before = rows(tmp_path / "map.db", "SELECT id, descriptor FROM words ORDER BY id")
    word_ids_b = store.load_features(b)[3]
    bad = [
        (ValueError, "3 word_ids for the 4 features", {"word_ids": np.array([0, 1, 2])}),
        (ValueError, "must be integers", {"word_ids": np.zeros(4)}),
        (ValueError, r"must be in \[-1, ", {"word_ids": np.array([0, -2, 1, 1])}),
        (ValueError, "must be in", {"word_ids": np.array([0, 2**31, 1, 1], np.int64)}),
        (ValueError, "go together", {"new_word_ids": np.array([11])}),
        (ValueError, "2 new_descriptors for 1", {"new_word_ids": np.array([11]), "new_descriptors": desc[:2]}),
        (ValueError, "must be uint8", {"new_word_ids": np.array([11]), "new_descriptors": desc[:1].astype(int)}),
        (ValueError, "duplicates", {"new_word_ids": np.array([11, 11]), "new_descriptors": desc[:2]}),
        (ValueError, r"in \[0, ", {"new_word_ids": np.array([-1]), "new_descriptors": desc[:1]}),
        # a word id that is neither stored nor new: nothing of it is written
        (ValueError, r"1 word\(s\) not in the map \(12\)",
         {"word_ids": np.array([11, 12, 0, 0]), "new_word_ids": np.array([11]), "new_descriptors": desc[:1]}),
        # ids are never reused
        (StoreError, r"word id\(s\) 3, 10 already stored",
         {"word_ids": np.array([3, 3, 3, 3]), "new_word_ids": np.array([3, 10, 11]), "new_descriptors": desc[:3]}),
    ]
    for exc, match, kw in bad:
        args = {"word_ids": np.array([0, 0, 0, 0])}
        args.update(kw)
        with pytest.raises(exc, match=match):
            store.save_node_words(b, args.pop("word_ids"), **args)
    with pytest.raises(UnknownIdError, match="no node 999"):
        store.save_node_words(999, np.zeros(4, np.int64))
    assert rows(tmp_path / "map.db", "SELECT id, descriptor FROM words ORDER BY id") == before
    assert np.array_equal(store.load_features(b)[3], word_ids_b) and store.get_info("next_word_id") == 11


def test_delete_and_prune_words(store, rng):
    sid = store.begin_session("r1", CAL)
    a = store.add_keyframe(record(rng, sid, 0, n=3))
    desc = rng.integers(0, 256, (6, 32), dtype=np.uint8)
    store.save_node_words(a, np.array([0, 1, 2]), np.arange(6), desc)  # 3, 4, 5: nobody's
    assert store.delete_words([5, 77]) == 1 and store.delete_words(np.zeros(0, np.int64)) == 0
    with pytest.raises(ValueError, match="must be integers"):
        store.delete_words([1.5])
    assert sorted(store.prune_words().tolist()) == [3, 4]
    assert np.array_equal(store.load_words()[0], [0, 1, 2])
    store.save_node_words(a, np.array([-1, 1, -1]))
    assert store.prune_words().tolist() == [0, 2]
    st = store.load_vocabulary_state()
    assert st["word_ids"].tolist() == [1] and st["next_id"][0] == 6  # ids 3..5 stay used
    assert st["node_nfeat"].tolist() == [1]


def test_vocabulary_state_skips_words_that_are_gone(store, rng):
    sid = store.begin_session("r1", CAL)
    a = store.add_keyframe(record(rng, sid, 0, n=4))
    store.add_keyframe(record(rng, sid, 1, n=4))  # no word ids: not indexed
    store.save_node_words(a, np.array([0, 1, 1, 2]), np.arange(3), rng.integers(0, 256, (3, 32), dtype=np.uint8))
    store.delete_words([1])  # e.g. deleted by hand: the node's references to it are skipped
    st = store.load_vocabulary_state()
    assert st["post_word"].tolist() == [0, 2] and st["post_count"].tolist() == [1, 1]
    assert st["node_ids"].tolist() == [a] and st["node_nfeat"].tolist() == [4]
    empty = MapStore(store.path.with_name("empty.db"))
    with empty:
        st = empty.load_vocabulary_state()
        assert st["descriptors"].shape == (0, 32) and st["next_id"][0] == 0 and len(st["node_ids"]) == 0


# -- queries --------------------------------------------------------------------------------


def test_bbox_and_paging(store, rng):
    sid = store.begin_session("r1", CAL)
    ids = [store.add_keyframe(record(rng, sid, i, pose(i % 10, i // 10, 0.5), n=4)) for i in range(100)]
    box = ((2, 3, 0), (4, 5, 1))  # bounds included: x in {2,3,4}, y in {3,4,5}
    inside = [n.id for n in store.nodes(bbox=box, limit=None)]
    assert inside == [ids[y * 10 + x] for y in (3, 4, 5) for x in (2, 3, 4)]
    assert store.count_nodes(bbox=box) == 9
    assert store.count_nodes(bbox=((2, 3, 0.6), (4, 5, 1))) == 0
    assert store.count_nodes(bbox=((-1e9,) * 3, (1e9,) * 3)) == 100
    # exact bounds even though the R*Tree stores float32
    assert store.count_nodes(bbox=((2.0000001, 3, 0), (4, 5, 1))) == 6

    pages = [store.nodes(session_id=sid, limit=30, offset=o) for o in range(0, 100, 30)]
    assert [len(p) for p in pages] == [30, 30, 30, 10]
    assert [n.id for p in pages for n in p] == ids
    assert len(store.nodes()) == 100 and len(store.nodes(limit=None)) == 100
    assert [n.id for n in store.nodes(bbox=box, limit=4, offset=4)] == inside[4:8]
    assert store.nodes(offset=1000) == []
    with pytest.raises(ValueError):
        store.nodes(bbox=((1, 1, 1), (0, 0, 0)))
    with pytest.raises(ValueError):
        store.nodes(bbox=((0, 0), (1, 1)))
    with pytest.raises(ValueError):
        store.nodes(offset=-1)
    # keyframes merged by rehearsal leave the R*Tree (the map's spatial index) and are still
    # found, by their exact position, by the queries that ask for them
    merged = [ids[3 * 10 + 2], ids[4 * 10 + 3]]
    for m in merged:
        store.merge_node(m, ids[0], pose(0.1), np.eye(6))
    if rows(store.path, "SELECT 1 FROM sqlite_master WHERE name = 'nodes_rtree'"):
        in_rtree = {r[0] for r in rows(store.path, "SELECT id FROM nodes_rtree")}
        assert not in_rtree & set(merged) and len(in_rtree) == 98
    assert [n.id for n in store.nodes(bbox=box, limit=None)] == inside
    assert [n.id for n in store.nodes(bbox=box, limit=None, merged=False)] == [i for i in inside if i not in merged]
    assert [n.id for n in store.nodes(bbox=box, limit=None, merged=True)] == merged
    assert store.count_nodes(bbox=box, merged=True) == 2 and store.count_nodes(bbox=box, merged=False) == 7
    store.update_poses({merged[0]: pose(50, 50, 0)})  # a merged keyframe's pose moves: still no R*Tree entry
    assert [n.id for n in store.nodes(bbox=((49, 49, -1), (51, 51, 1)), limit=None)] == [merged[0]]
    assert store.nodes(bbox=((49, 49, -1), (51, 51, 1)), merged=False) == []


def test_links_by_type(store, rng):
    s1 = store.begin_session("r1", CAL)
    s2 = store.begin_session("r2", CAL)
    a = [store.add_keyframe(record(rng, s1, i, odom_link=None)) for i in range(4)]
    b = [store.add_keyframe(record(rng, s2, i)) for i in range(2)]
    for x, y in zip(a, a[1:]):
        store.add_link(x, y, LinkType.NEIGHBOR, np.eye(4))
    store.add_link(a[3], a[0], LinkType.GLOBAL_CLOSURE, pose(0.1), np.eye(6) * 50)
    store.add_link(a[2], a[0], 2, pose(0.2))
    store.add_link(b[0], a[1], LinkType.GLOBAL_CLOSURE, pose(0.3))  # inter-session loop
    assert len(store.links()) == 6
    assert [(lk.from_id, lk.to_id) for lk in store.links(type=LinkType.GLOBAL_CLOSURE)] == [(a[3], a[0]), (b[0], a[1])]
    assert [lk.type for lk in store.links(type=2)] == [LinkType.LOCAL_SPACE]
    assert len(store.links(session_id=s1)) == 6 and len(store.links(session_id=s2)) == 1
    assert {(lk.from_id, lk.to_id) for lk in store.links(node_ids=[a[0]])} == {(a[0], a[1]), (a[3], a[0]), (a[2], a[0])}
    assert len(store.links(session_id=s1, type=LinkType.NEIGHBOR)) == 3
    loop = store.links(type=1, node_ids=[a[3]])[0]
    assert np.array_equal(loop.transform, pose(0.1)) and np.array_equal(loop.information, np.eye(6) * 50)
    assert store.stats()["links_by_type"] == {"odometry": 3, "loop": 2, "proximity": 1}

    with pytest.raises(StoreError, match="already exists"):
        store.add_link(a[3], a[0], LinkType.GLOBAL_CLOSURE, pose(0.5))
    store.add_link(a[3], a[0], LinkType.GLOBAL_CLOSURE, pose(0.5), replace=True)
    assert store.links(type=1, node_ids=[a[3]])[0].transform[0, 3] == 0.5
    with pytest.raises(UnknownIdError, match="no node 4242"):
        store.add_link(a[0], 4242, LinkType.USER, np.eye(4))
    with pytest.raises(ValueError, match="unknown link type"):
        store.add_link(a[0], a[1], 42, np.eye(4))
    with pytest.raises(ValueError):
        store.add_link(a[0], a[1], 4, np.eye(4), np.eye(4))
    assert len(store.links()) == 6
    # several links in one transaction: all of them, or none when one fails (a join's two)
    store.add_links([(b[1], a[2], LinkType.GLOBAL_CLOSURE, pose(0.4), None),
                     (b[1], a[3], LinkType.GLOBAL_CLOSURE, pose(0.6), np.eye(6) * 9)])
    assert len(store.links(session_id=s2, type=LinkType.GLOBAL_CLOSURE)) == 3
    for bad in ((b[0], 4242, LinkType.GLOBAL_CLOSURE, pose(0.7), None),  # no such node
                (b[1], a[2], LinkType.GLOBAL_CLOSURE, pose(0.8), None)):  # exists already
        with pytest.raises((UnknownIdError, StoreError)):
            store.add_links([(b[0], a[2], LinkType.GLOBAL_CLOSURE, pose(0.7), None), bad])
        assert len(store.links()) == 8  # the first of the two was not kept either


def test_trajectory_is_ordered_by_stamp(store, rng):
    sid = store.begin_session("r1", CAL)
    stamps = [3.0, 1.0, 2.5, 0.5, 2.0]
    for t in stamps:
        store.add_keyframe(record(rng, sid, t, pose(t, 2 * t, 0, yaw=t), n=3))
    traj = store.trajectory(sid)
    assert list(traj.stamps) == sorted(stamps)
    for t, P in zip(traj.stamps, traj.poses):
        assert P.tobytes() == pose(t, 2 * t, 0, yaw=t).tobytes()
    empty = store.begin_session("r1", CAL)
    assert len(store.trajectory(empty)) == 0
    with pytest.raises(UnknownIdError):
        store.trajectory(999)


def test_multi_session(store, rng):
    s1 = store.begin_session("alpha", CAL, {"seed": 1})
    s2 = store.begin_session("beta", STEREO)
    a = [store.add_keyframe(record(rng, s1, i)) for i in range(3)]
    b = [store.add_keyframe(record(rng, s2, i)) for i in range(2)]
    assert b[0] == a[-1] + 1  # node ids are global
    sessions = store.sessions()
    assert [(s.id, s.robot, s.map_id) for s in sessions] == [(s1, "alpha", 0), (s2, "beta", 1)]
    assert sessions[0].config == {"seed": 1} and sessions[1].config is None
    assert store.calibration(s1) == CAL and store.calibration(s2) == STEREO
    assert store.calibration(s2).kind == "stereo"
    assert json.loads(json.dumps(store.session(s2).to_dict()))["calibration"]["baseline"] == 0.537
    assert [n.id for n in store.nodes(robot="beta")] == b
    assert store.count_nodes(robot="alpha") == 3 and store.count_nodes(robot="nobody") == 0
    assert store.count_nodes(session_id=s2, robot="alpha") == 0
    assert [s.id for s in store.sessions(robot="beta")] == [s2]
    assert store.session(999) is None
    with pytest.raises(UnknownIdError):
        store.calibration(999)

    store.end_session(s1)
    ended = store.session(s1).ended_at
    assert ended is not None and store.session(s2).ended_at is None
    store.end_session(s1)
    assert store.session(s1).ended_at == ended
    with pytest.raises(StoreError, match="ended"):
        store.add_keyframe(record(rng, s1, 9))
    with pytest.raises(UnknownIdError):
        store.add_keyframe(record(rng, 999, 9))
    with pytest.raises(UnknownIdError):
        store.end_session(999)
    s3 = store.begin_session("alpha", CAL)
    assert store.session(s3).map_id == 2
    st = store.session_stats()
    assert st[s1] == {"nodes": 3, "first_stamp": 0.0, "last_stamp": 2.0} and st[s3]["nodes"] == 0


def test_sessions_record_how_they_ended(store, rng):
    s1, s2, s3 = (store.begin_session(r, CAL) for r in ("alpha", "beta", "gamma"))
    assert store.session(s1).end_reason is None and store.session(s1).to_dict()["end_reason"] is None
    store.end_session(s1)  # a normal end
    assert store.session(s1).end_reason == "stopped"
    store.end_session(s1, reason="other")  # the first end is kept
    assert store.session(s1).end_reason == "stopped"
    with pytest.raises(ValueError, match="end reason"):
        store.end_session(s2, reason="")
    a = [store.add_keyframe(record(rng, s2, i)) for i in range(3)]
    (last,), = rows(store.path, "SELECT MAX(time_enter) FROM nodes")
    ended = store.end_open_sessions("crashed")  # as the service does at start-up
    assert [(s.id, s.end_reason) for s in ended] == [(s2, "crashed"), (s3, "crashed")]
    assert ended[0].ended_at == last  # its last keyframe's time; without keyframes: its start
    assert ended[1].ended_at == store.session(s3).started_at
    assert {s.id: s.end_reason for s in store.sessions()} == {s1: "stopped", s2: "crashed", s3: "crashed"}
    assert json.loads(json.dumps(store.session(s2).to_dict()))["end_reason"] == "crashed"
    assert store.end_open_sessions() == []  # nothing open any more
    with pytest.raises(StoreError, match="ended"):
        store.add_keyframe(record(rng, s2, 9))
    assert store.count_nodes(session_id=s2) == len(a)


def test_map_updates_and_link_counts_for_metrics(store, rng):
    """What /metrics reads: a session's map updates after a node (time = the sum of its steps,
    memory sizes; missing fields are None) and its loop links by type."""
    s1, s2 = store.begin_session("alpha", CAL), store.begin_session("beta", CAL)
    a = [store.add_keyframe(record(rng, s1, i)) for i in range(3)]
    b = [store.add_keyframe(record(rng, s2, i)) for i in range(2)]
    store.set_statistics(a[0], {"timings_ms": {"graph": 1.5, "memory": 2.0},
                                "memory": {"stm": 1, "wm": 0, "ltm": 0, "words": 40}})
    store.set_statistics(a[1], {"decision": "none"})  # no timings, no memory
    store.set_statistics(b[0], {"timings_ms": {"rehearsal": 4.0}, "memory": {"stm": 1, "wm": 2, "ltm": 3, "words": 9}})
    assert store.map_updates(s1) == [(a[0], 3.5, 1, 0, 0, 40), (a[1], None, None, None, None, None)]
    assert store.map_updates(s1, after_node=a[0]) == [(a[1], None, None, None, None, None)]
    assert store.map_updates(s1, after_node=a[1]) == []
    assert store.map_updates(s2) == [(b[0], 4.0, 1, 2, 3, 9)]
    T = pose(0.1)
    store.add_link(a[0], a[2], LinkType.GLOBAL_CLOSURE, T)
    store.add_link(a[1], a[2], LinkType.LOCAL_SPACE, T)
    store.add_link(a[0], a[1], LinkType.LOCAL_SPACE, T)
    store.add_link(a[0], b[1], LinkType.GLOBAL_CLOSURE, T)  # ends in s2
    store.add_link(a[1], a[2], LinkType.LOCAL_TIME, T)
    loops = (LinkType.GLOBAL_CLOSURE, LinkType.LOCAL_SPACE)
    assert store.count_links(loops, session_id=s1) == {1: 1, 2: 2}
    assert store.count_links(loops, session_id=s2) == {1: 1, 2: 0}
    assert store.count_links(loops) == {1: 2, 2: 2}
    assert store.count_links([]) == {}


def test_unmapped_nodes_are_those_without_statistics(store, rng):
    s1, s2, s3 = (store.begin_session(r, CAL) for r in ("alpha", "beta", "gamma"))
    a = [store.add_keyframe(record(rng, s1, i)) for i in range(4)]
    b = [store.add_keyframe(record(rng, s2, i)) for i in range(3)]
    c = [store.add_keyframe(record(rng, s3, i)) for i in range(2)]
    for n in a[:2] + b + c[:1]:
        store.set_statistics(n, {"decision": "none"})  # the map update's last write
    assert store.unmapped_nodes() == {s1: a[2:], s3: c[1:]}  # s2 fully mapped: left out
    assert store.unmapped_nodes(session_ids=[s3, s2]) == {s3: c[1:]}
    store.end_session(s1)
    store.end_open_sessions("crashed")
    assert store.unmapped_nodes(end_reason="crashed") == {s3: c[1:]}
    assert store.unmapped_nodes(end_reason="stopped") == {s1: a[2:]}
    assert store.unmapped_nodes(session_ids=[s1], end_reason="crashed") == {}
    # what an interrupted map update wrote into a keyframe: its loop links (odometry stays)
    T = pose(0.1)
    store.add_link(a[0], a[3], LinkType.GLOBAL_CLOSURE, T)
    store.add_link(a[1], a[3], LinkType.LOCAL_TIME, T)
    store.add_link(a[0], a[2], LinkType.LOCAL_SPACE, T)
    store.add_link(a[2], a[3], LinkType.NEIGHBOR, T)
    store.add_link(a[3], a[0], LinkType.USER, T)
    assert store.delete_links([a[3]], [1, 2, 3]) == 2
    assert {(lk.from_id, lk.to_id, int(lk.type)) for lk in store.links(session_id=s1)} == {
        (a[0], a[2], 2), (a[2], a[3], 0), (a[3], a[0], 4)}


def test_migration_to_v2_marks_ended_sessions_stopped(tmp_path, rng):
    path = tmp_path / "map.db"

    class StoreV1(MapStore):
        MIGRATIONS = MapStore.MIGRATIONS[:1]

    with StoreV1(path) as s:
        s1, s2 = s.begin_session("alpha", CAL), s.begin_session("beta", CAL)
        s.add_keyframe(record(rng, s1, 0.0))
    rows(path, "UPDATE sessions SET ended_at = 1.0 WHERE id = ?", (s1,))  # as v1's end_session did
    assert "end_reason" not in {r[1] for r in rows(path, "PRAGMA table_info(sessions)")}
    with MapStore(path) as s:
        assert s.schema_version >= 2
        assert [(x.id, x.end_reason) for x in s.sessions()] == [(s1, "stopped"), (s2, None)]
        assert s.integrity_check() == "ok"


# -- schema ---------------------------------------------------------------------------------


def test_schema_version_and_migration(tmp_path, rng):
    path = tmp_path / "map.db"
    with MapStore(path) as s:
        assert s.schema_version == s.current_version == V
        assert s.get_info("schema_version") == V and s.get_info("created_at") > 0
        sid = s.begin_session("r1", CAL)
        nid = s.add_keyframe(record(rng, sid, 0.0))
        s.set_info("note", {"a": [1, 2]})
    assert rows(path, "PRAGMA user_version") == [(V,)]
    assert rows(path, "PRAGMA journal_mode") == [("wal",)]

    applied = []

    def m_next_fake(db):
        applied.append(1)
        db["nodes"].add_column("semantic_class", str)
        db["landmarks"].create({"id": int, "node_id": int, "name": str}, pk="id")
        db.execute("UPDATE nodes SET semantic_class = 'floor'")

    class StoreV2(MapStore):
        MIGRATIONS = MapStore.MIGRATIONS + (m_next_fake,)

    with StoreV2(path) as s:
        assert s.schema_version == V + 1 and s.get_info("schema_version") == V + 1
        assert s.get_node(nid) is not None and s.get_info("note") == {"a": [1, 2]}
    assert rows(path, "SELECT semantic_class FROM nodes") == [("floor",)]
    assert "landmarks" in {r[0] for r in rows(path, "SELECT name FROM sqlite_master")}
    with StoreV2(path):
        pass
    assert applied == [1]  # applied once

    # The current code refuses the newer file.
    with pytest.raises(StoreError, match=f"schema version {V + 1}, newer than this mnemoslam knows"):
        MapStore(path)


def test_failed_migration_keeps_previous_version(tmp_path):
    path = tmp_path / "map.db"
    MapStore(path).close()

    def m_next_broken(db):
        db["nodes"].add_column("half_done", int)
        raise RuntimeError("migration bug")

    class Broken(MapStore):
        MIGRATIONS = MapStore.MIGRATIONS + (m_next_broken,)

    with pytest.raises(RuntimeError, match="migration bug"):
        Broken(path)
    assert rows(path, "PRAGMA user_version") == [(V,)]
    assert "half_done" not in {r[1] for r in rows(path, "PRAGMA table_info(nodes)")}
    with MapStore(path) as s:
        assert s.integrity_check() == "ok"


def test_newer_schema_refused(tmp_path):
    path = tmp_path / "map.db"
    MapStore(path).close()
    rows(path, "PRAGMA user_version = 99")
    with pytest.raises(StoreError, match="schema version 99, newer"):
        MapStore(path)
    with pytest.raises(StoreError, match="newer"):
        db_info(path)


def test_open_errors(tmp_path):
    missing = tmp_path / "none.db"
    with pytest.raises(StoreError, match="no database"):
        MapStore(missing, create=False)
    with pytest.raises(StoreError, match="no database"):
        db_info(missing)
    with pytest.raises(StoreError, match="no database"):
        db_export(missing, tmp_path / "out")
    assert not missing.exists()

    junk = tmp_path / "junk.db"
    junk.write_bytes(b"this is not sqlite" * 100)
    with pytest.raises(StoreError, match="not a SQLite database"):
        MapStore(junk)
    foreign = tmp_path / "foreign.db"
    rows(foreign, "CREATE TABLE t (x)")
    with pytest.raises(StoreError, match="not a mnemoslam database"):
        MapStore(foreign)
    with pytest.raises(StoreError, match="directory"):
        MapStore(tmp_path)
    empty = tmp_path / "empty.db"
    empty.touch()
    with pytest.raises(StoreError, match="not a mnemoslam database"):
        MapStore(empty, create=False)
    with pytest.raises(ValueError):
        MapStore(":memory:")


def test_close(tmp_path, rng):
    s = MapStore(tmp_path / "sub" / "map.db")  # parents are created
    sid = s.begin_session("r1", CAL)
    s.count_nodes()
    s.close()
    s.close()
    assert s.closed
    with pytest.raises(StoreError, match="closed"):
        s.add_keyframe(record(rng, sid))
    with pytest.raises(StoreError, match="closed"):
        s.count_nodes()


# -- concurrency and crashes ----------------------------------------------------------------


def test_reader_thread_while_writers_add_keyframes(store):
    s1 = store.begin_session("r1", CAL)
    s2 = store.begin_session("r2", CAL)
    errors, seen = [], {0: [], 1: []}
    done = threading.Event()

    def write(sid, n, seed):
        try:
            rng = np.random.default_rng(seed)
            prev = None
            for i in range(n):
                prev = store.add_keyframe(record(rng, sid, i * 0.1, pose(i * 0.01), n=200, statistics={"i": i},
                                                 odom_link=None if prev is None else (prev, pose(0.01), None)))
        except Exception as e:  # pragma: no cover - reported below
            errors.append(e)

    def read(k):
        try:
            while not done.is_set():
                n = store.count_nodes()
                seen[k].append(n)
                if n:
                    last = store.nodes(limit=1, offset=n - 1)[0]
                    kp, desc, pts, _ = store.load_features(last.id)
                    assert len(kp) == len(desc) == len(pts) == 200
                    store.stats()
        except Exception as e:  # pragma: no cover
            errors.append(e)

    readers = [threading.Thread(target=read, args=(k,)) for k in range(2)]
    writers = [threading.Thread(target=write, args=(s1, 200, 1)), threading.Thread(target=write, args=(s2, 50, 2))]
    for t in readers + writers:
        t.start()
    for t in writers:
        t.join(60)
    done.set()
    for t in readers:
        t.join(10)
    assert not errors, errors
    assert store.count_nodes(session_id=s1) == 200 and store.count_nodes(session_id=s2) == 50
    assert len(store.links()) == 199 + 49
    for counts in seen.values():
        assert len(counts) > 5 and counts == sorted(counts)
    assert store.integrity_check() == "ok"


def test_reader_counts_are_monotonic(store):
    sid = store.begin_session("r1", CAL)
    seen, errors = [], []
    done = threading.Event()

    def read():
        try:
            while not done.is_set():
                seen.append(store.count_nodes())
        except Exception as e:  # pragma: no cover
            errors.append(e)

    t = threading.Thread(target=read)
    t.start()
    rng = np.random.default_rng(3)
    for i in range(200):
        store.add_keyframe(record(rng, sid, i, n=100))
        if i % 50 == 0:
            time.sleep(0.005)
    done.set()
    t.join(10)
    assert not errors
    assert len(seen) > 5 and seen == sorted(seen) and seen[-1] <= 200


CHILD = r"""
import sys
sys.path.insert(0, {root!r})
import numpy as np
from mnemoslam.client.kernel.frames import Calibration, PinholeCamera
from mnemoslam.storage import KeyframeRecord, MapStore
store = MapStore({path!r})
sid = store.begin_session("crash", Calibration(PinholeCamera(500, 500, 320, 240, 640, 480)))
rng = np.random.default_rng(0)
prev, i = None, 0
while True:
    P = np.eye(4); P[0, 3] = i * 0.01
    n = 500
    rec = KeyframeRecord(sid, i * 0.1, P, rng.random((n, 2), dtype=np.float32),
                         rng.integers(0, 256, (n, 32), dtype=np.uint8), rng.random((n, 3), dtype=np.float32),
                         image_jpeg=b"\xff\xd8\xff" + rng.bytes(20000), statistics={{"i": i}},
                         odom_link=None if prev is None else (prev, np.eye(4), None))
    prev = store.add_keyframe(rec)
    print(prev, flush=True)
    i += 1
"""


def test_kill_9_keeps_every_committed_keyframe(tmp_path):
    path = tmp_path / "crash.db"
    proc = subprocess.Popen([sys.executable, "-c", CHILD.format(root=str(ROOT), path=str(path))],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    printed = []
    deadline = time.monotonic() + 30
    try:
        while len(printed) < 50 and time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            printed.append(int(line))
    finally:
        proc.send_signal(signal.SIGKILL)
        out, err = proc.communicate(timeout=10)
    assert proc.returncode == -signal.SIGKILL
    assert len(printed) >= 50, err
    printed += [int(ln) for ln in out.split("\n")[:-1]]  # lines printed before the kill (complete ones only)
    assert rows(path, "PRAGMA integrity_check") == [("ok",)]
    with MapStore(path, create=False) as s:
        assert s.integrity_check() == "ok"
        ids = {n.id for n in s.nodes(limit=None)}
        assert set(printed) <= ids
        n = len(ids)
        st = s.stats()
        # no partial keyframe: every node has its features, image, statistics and odometry link
        assert st["features"] == st["images"] == st["statistics"] == n and st["links"] == n - 1
        kp, desc, pts, _ = s.load_features(max(ids))
        assert kp.shape == (500, 2) and desc.shape == (500, 32)


# -- export and CLI -------------------------------------------------------------------------


def test_export_writes_tum_that_read_tum_reads_back(store, rng, tmp_path):
    s1 = store.begin_session("r1", CAL)
    s2 = store.begin_session("r2", CAL)
    want = {}
    for sid in (s1, s2):
        prev = None
        for i in range(6):
            P = pose(0.1 * i + sid, 0.05 * i, -0.2 * i, yaw=0.2 * i)
            prev = store.add_keyframe(record(rng, sid, 100.0 + i * 0.5, P, n=5,
                                             odom_link=None if prev is None else (prev, pose(0.1), None)))
            want.setdefault(sid, []).append(P)

    files = store.export(tmp_path / "all")
    assert sorted(p.name for p in files) == ["graph.json", f"trajectory_{s1}.tum", f"trajectory_{s2}.tum"]
    for sid in (s1, s2):
        traj = read_tum(tmp_path / "all" / f"trajectory_{sid}.tum")
        assert len(traj) == 6
        assert np.allclose(traj.stamps, 100.0 + np.arange(6) * 0.5)
        assert np.allclose(traj.poses, np.array(want[sid]), atol=1e-6)
    graph = json.loads((tmp_path / "all" / "graph.json").read_text())
    assert len(graph["nodes"]) == 12 and len(graph["links"]) == 10 and len(graph["sessions"]) == 2
    n0 = graph["nodes"][0]
    assert np.array(n0["pose"]).reshape(4, 4).tobytes() == want[s1][0].tobytes()  # exact
    assert set(n0) >= {"id", "session", "stamp", "pose"}
    assert set(graph["links"][0]) >= {"from", "to", "type", "transform"}

    files = store.export(tmp_path / "one", session_id=s2)
    assert sorted(p.name for p in files) == ["graph.json", "trajectory.tum"]
    traj = read_tum(tmp_path / "one" / "trajectory.tum")
    assert np.allclose(traj.poses, np.array(want[s2]), atol=1e-6)
    graph = json.loads((tmp_path / "one" / "graph.json").read_text())
    assert {n["session"] for n in graph["nodes"]} == {s2} and len(graph["links"]) == 5


def test_db_info_and_export_text(tmp_path, rng):
    path = tmp_path / "map.db"
    with MapStore(path) as s:
        s1 = s.begin_session("robot_a", CAL)
        prev = None
        for i in range(7):
            prev = s.add_keyframe(record(rng, s1, 10.0 + i, n=11, image_jpeg=JPEG,
                                         odom_link=None if prev is None else (prev, np.eye(4), None)))
        s.add_link(prev, prev - 6, LinkType.GLOBAL_CLOSURE, np.eye(4))
        s.begin_session("robot_b", STEREO)
    text = db_info(path)
    for needle in (f"schema    v{V}", "sessions  2", "robot_a", "robot_b", "nodes     7",
                   "links     7 (odometry 6, loop 1)", "features  7 (77 keypoints)", "images    7", "words     0",
                   "integrity ok", "10.000000", "16.000000", "MB"):
        assert needle in text, (needle, text)
    out = db_export(path, tmp_path / "exp", session=s1)
    assert "trajectory.tum" in out and "graph.json" in out
    assert len(read_tum(tmp_path / "exp" / "trajectory.tum")) == 7
    with pytest.raises(StoreError, match="no session 42"):
        db_export(path, tmp_path / "exp2", session=42)


def test_stats_counts_and_file_size(store, rng):
    sid = store.begin_session("r1", CAL)
    store.add_keyframe(record(rng, sid, 0, n=10, image_jpeg=JPEG, statistics={"a": 1}))
    st = store.stats()
    assert {k: st[k] for k in ("schema_version", "sessions", "nodes", "links", "features", "keypoints", "words",
                               "images", "statistics")} == dict(schema_version=V, sessions=1, nodes=1, links=0,
                                                                features=1, keypoints=10, words=0, images=1,
                                                                statistics=1)
    assert st["file_bytes"] >= os.path.getsize(store.path) and st["wal_bytes"] > 0
    json.dumps(st)


def test_wal_restarts_after_a_checkpoint(tmp_path, monkeypatch):
    path = tmp_path / "wal.db"
    wal = Path(str(path) + "-wal")
    rng = np.random.default_rng(5)
    # only the explicit checkpoint below, for a deterministic WAL
    monkeypatch.setattr(Connection, "CHECKPOINT_COMMITS", 1e9)
    monkeypatch.setattr(Connection, "CHECKPOINT_PERIOD", 1e9)

    with MapStore(path) as s:
        assert rows(path, "PRAGMA journal_mode") == [("wal",)]
        sid = s.begin_session("r1", CAL)
        for i in range(100):  # ~27 kB each
            s.add_keyframe(record(rng, sid, i, n=500))
        pages, done = s.checkpoint()
        assert pages == done > 0
        size = wal.stat().st_size
        for i in range(100, 200):  # the same amount again goes to the start of the WAL
            s.add_keyframe(record(rng, sid, i, n=500))
        assert wal.stat().st_size <= size * 1.1  # (it would double without the restart)
        assert s.integrity_check() == "ok"
    assert not wal.exists()  # the last close checkpoints and removes it
    with MapStore(path, create=False) as s:
        assert s.count_nodes() == 200


def test_background_checkpointer_copies_the_wal(tmp_path, monkeypatch):
    monkeypatch.setattr(Connection, "CHECKPOINT_COMMITS", 4)
    path = tmp_path / "bg.db"
    rng = np.random.default_rng(5)
    with MapStore(path) as s:
        sid = s.begin_session("r1", CAL)
        for i in range(40):  # ~1 MB, all in the WAL at first
            s.add_keyframe(record(rng, sid, i, n=500))
        deadline = time.monotonic() + 10
        while path.stat().st_size < 0.8e6 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert path.stat().st_size >= 0.8e6  # copied into the database file by the checkpointer


# -- semantic objects (schema v4) -----------------------------------------------------------


def obj(node_id, centroid=(0.0, 0.0, 1.0), label="door", class_id=15, k=32, oid=None, **kw) -> ObjectRecord:
    hist = np.full(k, 0.01, np.float32)
    hist[class_id % k] = 1.0 - 0.01 * (k - 1)
    fields = dict(id=oid, node_id=node_id, class_id=class_id, label=label, confidence=float(hist[class_id % k]),
                  histogram=hist, centroid=np.array(centroid, float), extent=np.array([0.9, 2.0, 0.1]),
                  observations=3, keyframes=np.array([node_id, node_id + 1], np.int64))
    fields.update(kw)
    return ObjectRecord(**fields)


def test_objects_round_trip_and_follow_their_anchor(store, rng):
    sid = store.begin_session("r1", CAL)
    a = store.add_keyframe(record(rng, sid, 0.0, P=pose(1.0, 0.0, 2.0)))
    b = store.add_keyframe(record(rng, sid, 1.0, P=pose(0.0, 0.0, 0.0, yaw=np.pi / 2)))
    ids = store.save_objects([obj(a, (0.5, 0.0, 1.0)), obj(b, (0.0, 1.0, 2.0), label="chair", class_id=20)])
    assert len(ids) == 2 and store.count_objects() == 2
    o = store.get_object(ids[0])
    want = obj(a, (0.5, 0.0, 1.0))
    assert (o.id, o.node_id, o.class_id, o.label, o.observations) == (ids[0], a, 15, "door", 3)
    assert o.confidence == pytest.approx(want.confidence)
    assert o.histogram.dtype == np.float32 and np.array_equal(o.histogram, want.histogram)
    assert np.array_equal(o.centroid, want.centroid) and np.array_equal(o.extent, want.extent)
    assert o.keyframes.tolist() == [a, a + 1]
    np.testing.assert_allclose(o.position, [1.5, 0.0, 3.0])
    c = store.get_object(ids[1])  # yaw 90° about y: camera z -> world x
    np.testing.assert_allclose(c.position, [2.0, 1.0, 0.0], atol=1e-12)
    assert [x.id for x in store.objects()] == ids and [x.label for x in store.objects("chair")] == ["chair"]
    assert store.get_object(999) is None

    # a graph correction moves the anchor: the object follows without being rewritten
    store.update_poses({a: pose(-1.0, 0.5, 0.0, yaw=np.pi)})
    np.testing.assert_allclose(store.get_object(ids[0]).position, [-1.5, 0.5, -1.0], atol=1e-12)
    arr = store.object_arrays()
    np.testing.assert_allclose(arr["position"], [[-1.5, 0.5, -1.0], [2.0, 1.0, 0.0]], atol=1e-12)
    assert arr["id"].tolist() == ids and arr["labels"].tolist() == ["door", "chair"]
    assert arr["class_id"].tolist() == [15, 20] and arr["node_id"].tolist() == [a, b]
    assert arr["extent"].shape == (2, 3) and arr["observations"].tolist() == [3, 3]
    assert store.object_arrays("door")["id"].tolist() == [ids[0]]
    assert store.object_arrays("sofa")["position"].shape == (0, 3)

    # update in place (re-anchored), then delete
    o.node_id, o.centroid, o.observations = b, np.zeros(3), 4
    o.keyframes = np.arange(100, dtype=np.int64)  # keeps the most recent 64
    assert store.save_objects([o]) == [ids[0]]
    o2 = store.get_object(ids[0])
    assert o2.node_id == b and o2.observations == 4 and o2.keyframes.tolist() == list(range(36, 100))
    assert store.delete_objects([ids[0], 12345]) == 1 and store.count_objects() == 1


@pytest.mark.parametrize("change, match", [
    (dict(histogram=np.array([np.nan] * 32, np.float32)), "histogram has non-finite"),
    (dict(class_id=40), "outside the histogram"),
    (dict(label=""), "label must be"),
    (dict(confidence=1.5), "confidence must be in"),
    (dict(centroid=np.zeros(2)), "centroid must have shape"),
    (dict(extent=np.array([1.0, -1.0, 0.0])), "extent must be non-negative"),
    (dict(node_id="x"), "node_id must be an integer"),
    (dict(keyframes=np.array([1.5])), "keyframes must be"),
])
def test_bad_object_is_a_value_error_before_any_write(store, rng, change, match):
    sid = store.begin_session("r1", CAL)
    a = store.add_keyframe(record(rng, sid, 0.0))
    with pytest.raises(ValueError, match=match):
        store.save_objects([obj(a), dataclasses.replace(obj(a), **change)])
    assert store.count_objects() == 0
    with pytest.raises(UnknownIdError, match="no anchor node 999"):
        store.save_objects([obj(a), obj(999)])
    with pytest.raises(UnknownIdError, match="no object 77"):
        store.save_objects([obj(a), obj(a, oid=77)])
    assert store.count_objects() == 0


def test_objects_survive_their_anchor_being_merged(store, rng):
    sid = store.begin_session("r1", CAL)
    a = store.add_keyframe(record(rng, sid, 0.0))
    b = store.add_keyframe(record(rng, sid, 1.0, P=pose(0.2)))
    (oid,) = store.save_objects([obj(b)])
    store.merge_node(b, a, pose(0.2), np.eye(6))
    assert store.get_object(oid).node_id == b and store.count_objects() == 1


def test_object_arrays_at_100k_objects(store, rng):
    """100k objects as columns, positions from their anchors (speed: bench/bench_objects.py)."""
    sid = store.begin_session("r1", CAL)
    nodes = [store.add_keyframe(record(rng, sid, float(i), P=pose(i, 0, 0), n=5)) for i in range(200)]
    hist = np.full(32, 1 / 32, np.float32)
    cents = rng.normal(size=(100_000, 3))
    anchors = rng.integers(0, 200, 100_000)
    store.save_objects([ObjectRecord(None, nodes[anchors[i]], 0, "other", 1 / 32, hist, cents[i], np.ones(3), 1,
                                     np.array([nodes[anchors[i]]], np.int64)) for i in range(100_000)])
    arr = store.object_arrays()
    assert arr["id"].shape == (100_000,)
    np.testing.assert_allclose(arr["position"], cents + np.c_[anchors, np.zeros((100_000, 2))])


def test_migration_from_v3_adds_objects(tmp_path, rng):
    path = tmp_path / "map.db"

    class StoreV3(MapStore):
        MIGRATIONS = MapStore.MIGRATIONS[:3]

    with StoreV3(path) as s:
        sid = s.begin_session("r1", CAL)
        a = s.add_keyframe(record(rng, sid, 0.0))
    assert "objects" not in {r[0] for r in rows(path, "SELECT name FROM sqlite_master")}
    with MapStore(path) as s:
        assert s.schema_version == V >= 4 and s.count_objects() == 0
        s.save_objects([obj(a)])
        assert s.objects()[0].node_id == a and s.integrity_check() == "ok"
    assert {"idx_objects_label", "idx_objects_node"} <= {r[0] for r in rows(path, "SELECT name FROM sqlite_master")}


def test_v5_takes_merged_keyframes_out_of_the_rtree(tmp_path, rng):
    """A v4 map (merged keyframes still in the R*Tree) opened by v5: they leave it, and the
    trigger keeps later merges out."""
    path = tmp_path / "map.db"
    with MapStore(path) as s:
        sid = s.begin_session("r1", CAL)
        ids = [s.add_keyframe(record(rng, sid, i, pose(i, 0, 0), n=4)) for i in range(4)]
        s.merge_node(ids[1], ids[0], pose(0.1), np.eye(6))
    if not rows(path, "SELECT 1 FROM sqlite_master WHERE name = 'nodes_rtree'"):
        pytest.skip("this SQLite has no R*Tree")
    c = sqlite3.connect(path, isolation_level=None)  # back to v4: the merged keyframe in the R*Tree, no trigger
    c.execute("DROP TRIGGER nodes_rtree_merged")
    c.execute("DROP TABLE segmentations")  # (v6)
    c.execute("DROP TABLE local_grids")  # (v7)
    c.execute("INSERT INTO nodes_rtree VALUES (?, 1, 1, 0, 0, 0, 0)", (ids[1],))
    c.execute("PRAGMA user_version = 4")
    c.close()
    with MapStore(path) as s:
        assert s.schema_version == V
        s.merge_node(ids[2], ids[0], pose(0.1), np.eye(6))
        assert [n.id for n in s.nodes(bbox=((-1, -1, -1), (5, 1, 1)), merged=False)] == [ids[0], ids[3]]
    assert sorted(r[0] for r in rows(path, "SELECT id FROM nodes_rtree")) == [ids[0], ids[3]]


# -- which map each session is in (storage.connectivity.MapIndex, issue 22) ---------------------


def test_map_index_says_when_a_session_joined_an_older_map(store, rng):
    from mnemoslam.storage.connectivity import MapIndex

    info = np.eye(6)
    a = store.begin_session("A", CAL)
    na = [store.add_keyframe(record(rng, a, float(t), pose(x=t))) for t in range(3)]
    for p, q in zip(na, na[1:]):
        store.add_link(p, q, LinkType.NEIGHBOR, np.eye(4), info)
    b = store.begin_session("B", CAL)
    nb = [store.add_keyframe(record(rng, b, 10.0 + t, pose(x=t))) for t in range(3)]
    for p, q in zip(nb, nb[1:]):
        store.add_link(p, q, LinkType.NEIGHBOR, np.eye(4), info)
    index = MapIndex()
    assert index.refresh(store) == []
    j = index.join(b)
    assert (j.map, j.own_map, j.first_node, j.joined) == (1, 1, nb[0], False)
    assert index.map_of(nb[2]) == 1 and index.map_of(na[2]) == 0
    assert sorted(index.maps()) == [0, 1] and index.maps()[1]["sessions"] == [b]
    # B's third keyframe closes a loop to A's second: B is in map 0 from then on, and only then
    store.add_link(na[1], nb[2], LinkType.GLOBAL_CLOSURE, np.eye(4), info)
    store.add_link(na[0], nb[1], LinkType.GLOBAL_CLOSURE, np.eye(4), info)  # a second link: no second join
    new = index.refresh(store)
    assert [(x.session_id, x.map, x.node, x.peer, x.link, x.stamp) for x in new] == [
        (b, 0, nb[2], na[1], LinkType.GLOBAL_CLOSURE, 12.0)]
    assert index.refresh(store) == [] and index.join(b).joined and index.join(a).joined is False
    assert index.map_of(nb[0]) == 0
    m = index.maps()
    assert list(m) == [0] and m[0]["sessions"] == [a, b] and m[0]["robots"] == ["A", "B"]
    assert m[0]["keyframes"] == 6 and m[0]["last_change"] >= store.session(b).started_at
    assert f"joined map 0 at keyframe {nb[2]} (stamp 12.000)" in db_info(store.path)
