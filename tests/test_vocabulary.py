"""Incremental vocabulary: word assignment (NNDR), inverted index, removal, persistence
(in memory and with the map's SQLite file), sub-linear search."""
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from client.datasets import open_dataset
from client.frames import Calibration, PinholeCamera
from client.synthetic import SyntheticDataset
from service.config import load_config
from service.runner import run_dataset
from service.vocabulary import Vocabulary
from storage import KeyframeRecord, MapStore, UnknownIdError

ROOT = Path(__file__).resolve().parents[1]


def _rand(rng, n):
    return rng.integers(0, 256, (n, 32), dtype=np.uint8)


def _flip(rng, desc, n_bits):
    """Flip exactly n_bits random bits of every descriptor."""
    bits = np.unpackbits(desc, axis=1)
    for row in bits:
        row[rng.choice(256, n_bits, replace=False)] ^= 1
    return np.packbits(bits, axis=1)


def test_identical_descriptors_same_word():
    rng = np.random.default_rng(1)
    v = Vocabulary()
    d = _rand(rng, 300)
    w1 = v.add(1, d)
    assert len(v) == 300 and len(np.unique(w1)) == 300
    w2 = v.add(2, d)
    assert np.array_equal(w1, w2)
    assert len(v) == 300
    assert np.array_equal(v.query(d), w1)


def test_far_descriptor_creates_new_word():
    rng = np.random.default_rng(2)
    v = Vocabulary(max_distance=70)
    d = _rand(rng, 50)
    v.add(1, d)
    far = _flip(rng, d[:1], 100)  # 100 bits from its closest word, ~128 from the rest
    w = v.add(2, far)
    assert w[0] == 50 and len(v) == 51
    assert v.query(far)[0] == 50


def test_repeated_descriptors_in_one_node_share_a_word():
    rng = np.random.default_rng(3)
    v = Vocabulary()
    d = _rand(rng, 10)
    w = v.add(1, np.concatenate([d, d, _flip(rng, d, 5)]))
    assert len(v) == 10
    assert np.array_equal(w[:10], w[10:20]) and np.array_equal(w[:10], w[20:])
    words, counts = v.node_words(1)
    assert np.all(counts == 3) and v.node_size(1) == 30


def test_nndr_ratio_on_crafted_descriptors():
    # Two words A and B differing in 40 bits; a query 20 bits from A and 20+... from B.
    rng = np.random.default_rng(4)
    a = _rand(rng, 1)
    bits_a = np.unpackbits(a, axis=1)[0]
    order = rng.permutation(256)
    b_bits = bits_a.copy()
    b_bits[order[:40]] ^= 1  # B = A with 40 bits flipped
    b = np.packbits(b_bits)[None]
    v = Vocabulary(nndr=0.8, max_distance=35, n_tables=32, key_bits=8)  # B (40 bits away) is new; both found surely
    wa, wb = v.add(1, a)[0], v.add(2, b)[0]
    assert wa != wb and len(v) == 2

    def query_with(n_to_a):
        # flip n_to_a of the 40 differing bits towards B: d(q,A)=n, d(q,B)=40-n
        q = bits_a.copy()
        q[order[:n_to_a]] ^= 1
        return np.packbits(q)[None]

    # d1=10, d2=30: 10 <= 0.8*30 -> votes for A
    assert v.query(query_with(10))[0] == wa
    # d1=18, d2=22: 18 > 0.8*22=17.6 -> ambiguous -> new word
    assert v.query(query_with(18))[0] == -1
    # n=22: d(q,B)=18, d(q,A)=22 -> ambiguous as well
    assert v.query(query_with(22))[0] == -1
    before = len(v)
    w = v.add(3, query_with(18))[0]
    assert w not in (wa, wb) and len(v) == before + 1
    # close to B
    assert v.query(query_with(35))[0] == wb


def test_inverted_index_counts():
    rng = np.random.default_rng(5)
    v = Vocabulary()
    d = _rand(rng, 20)
    v.add(10, np.concatenate([d[:10], d[:5]]))  # words 0..9, 0..4 twice
    v.add(11, d[5:20])
    assert v.word_nodes(0) == {10: 2}
    assert v.word_nodes(7) == {10: 1, 11: 1}
    assert v.word_nodes(15) == {11: 1}
    uw, df, idx, nodes, counts = v.postings([0, 7, 15, 7])
    assert list(uw) == [0, 7, 15] and list(df) == [1, 2, 1]
    got = sorted(zip(uw[idx].tolist(), nodes.tolist(), counts.tolist()))
    assert got == [(0, 10, 2), (7, 10, 1), (7, 11, 1), (15, 11, 1)]
    assert v.n_nodes == 2 and v.node_size(10) == 15


def test_remove_node_removes_orphan_words():
    rng = np.random.default_rng(6)
    v = Vocabulary()
    d = _rand(rng, 30)
    v.add(1, d[:20])
    v.add(2, d[10:30])
    removed = v.remove_node(1)
    assert sorted(removed.tolist()) == list(range(10))
    assert len(v) == 20
    assert np.all(v.query(d[:10]) == -1)  # gone from the search structure
    assert np.array_equal(v.query(d[10:30]), np.arange(10, 30))
    assert v.word_nodes(12) == {2: 1}
    v.remove_node(2)
    assert len(v) == 0 and v.n_nodes == 0
    # New words get new ids; removed ids are not reused.
    w = v.add(3, d[:5])
    assert w.min() == 30


def test_state_round_trip():
    rng = np.random.default_rng(7)
    v = Vocabulary()
    for n in range(20):
        v.add(n, _rand(rng, 100))
    v.remove_node(3)
    st = v.state()
    assert st["descriptors"].dtype == np.uint8 and st["descriptors"].shape == (len(v), 32)
    v2 = Vocabulary.from_state(st)
    st2 = v2.state()
    for k in st:
        assert np.array_equal(np.sort(st[k]), np.sort(st2[k])), k
    q = _flip(rng, v.descriptors(st["word_ids"][:200]), 6)
    assert np.array_equal(v.query(q), v2.query(q))
    assert len(v2) == len(v) and v2.n_nodes == v.n_nodes
    for w in st["word_ids"][:50].tolist():
        assert v.word_nodes(w) == v2.word_nodes(w)
    # both grow identically
    new = _rand(rng, 100)
    assert np.array_equal(v.add(99, new), v2.add(99, new))


def test_rebuilt_hash_tables_equal_the_incrementally_grown_ones():
    # from_state links all words in one table-major pass; the buckets' chains must be the
    # ones add() built node by node (same order, removed words left out), or a query
    # walking at most max_chain words could find different candidates after a reload.
    rng = np.random.default_rng(11)
    centres = _rand(rng, 300)
    for key_bits in (16, 20):
        v = Vocabulary(key_bits=key_bits, n_tables=8, capacity=1 << 14)
        for n in range(40):
            d = _rand(rng, 200)
            d[:100] = _flip(rng, centres[rng.integers(0, 300, 100)], 8)
            v.add(n, d)
        v.remove_node(7)
        v.remove_node(30)
        v2 = Vocabulary.from_state(v.state(), capacity=1 << 14)
        k = v.state()["next_id"][0]
        assert np.array_equal(v._head, v2._head)
        assert np.array_equal(v._nxt[:k], v2._nxt[:k]) and np.array_equal(v._prv[:k], v2._prv[:k])


def test_search_is_sublinear_at_50k_words():
    rng = np.random.default_rng(8)
    v = Vocabulary()
    centers = _rand(rng, 2000)
    for n in range(100):  # 50k words, half random, half clustered around centres
        d = _rand(rng, 500)
        c = centers[rng.integers(0, len(centers), 250)]
        d[:250] = _flip(rng, c, 40)
        v.add(n, d)
    assert len(v) > 40_000
    words = v.state()["word_ids"]
    q = _flip(rng, v.descriptors(rng.choice(words, 500, replace=False)), 10)
    w = v.query(q)
    per_query = v.last_candidates / v.last_queries
    assert per_query < 0.01 * len(v), per_query  # far below W exact distances per query
    assert per_query <= v.n_tables * v.max_chain
    assert (w >= 0).mean() > 0.9  # and still finds the word of a 10-bit-noisy descriptor


# -- persistence with the map (real SQLite files) --------------------------------------------

CAL = Calibration(PinholeCamera(525.0, 525.0, 319.5, 239.5, 640, 480), None, 1000.0)


@pytest.fixture(scope="module")
def orb_nodes():
    """ORB descriptors of 41 frames of the synthetic scene's loop (one per 1.5 s, so the
    end revisits the start): real, clustered descriptors with votes and new words."""
    ds = SyntheticDataset("loop", rate=1 / 1.5)
    orb = cv2.ORB_create(500)
    out = []
    for i in range(len(ds)):
        _, d = orb.detectAndCompute(ds.frame(i).grey, None)
        out.append(d)
    return out


def _store_node(store, sid, desc, stamp):
    n = len(desc)
    return store.add_keyframe(KeyframeRecord(sid, float(stamp), np.eye(4), np.zeros((n, 2), np.float32), desc,
                                             np.zeros((n, 3), np.float32)))


def _assert_same(v, v2, probe):
    """Same words, same inverted index, same answers."""
    assert len(v2) == len(v) and v2.n_nodes == v.n_nodes
    assert sorted(v2.node_ids()) == sorted(v.node_ids())
    st, st2 = v.state(), v2.state()
    assert np.array_equal(st["word_ids"], st2["word_ids"])
    assert np.array_equal(st["descriptors"], st2["descriptors"])
    assert st["next_id"][0] == st2["next_id"][0]
    for n in v.node_ids():
        (w, c), (w2, c2) = v.node_words(n), v2.node_words(n)
        assert np.array_equal(w, w2) and np.array_equal(c, c2), n
        assert v.node_size(n) == v2.node_size(n), n
    for w in st["word_ids"].tolist():
        assert v.word_nodes(w) == v2.word_nodes(w), w
    q, q2 = v.query(probe), v2.query(probe)
    assert (q >= 0).mean() > 0.5 and np.array_equal(q, q2)
    for a, b in zip(v.postings(q), v2.postings(q2)):
        assert np.array_equal(a, b)


def test_saved_incrementally_and_reloaded_answers_identically(tmp_path, orb_nodes):
    path = tmp_path / "map.db"
    v = Vocabulary()
    with MapStore(path) as store:
        sid = store.begin_session("r1", CAL)
        for k, desc in enumerate(orb_nodes[:-1]):
            nid = _store_node(store, sid, desc, k)
            before = len(v)
            words = v.add(nid, desc, store=store)
            assert len(v.last_new_words) == len(v) - before
            assert np.all(v.last_new_words >= 0) and set(v.last_new_words.tolist()) <= set(words.tolist())
            assert np.array_equal(store.load_features(nid)[3], words)  # committed before add returns
        assert store.count_words() == len(v) > 5000
    probe = _flip(np.random.default_rng(9), orb_nodes[-1], 3)
    with MapStore(path, create=False) as store:
        v2 = Vocabulary.from_store(store)
        _assert_same(v, v2, probe)
        # Both grow identically, and the reloaded one keeps saving.
        sid = store.begin_session("r1", CAL)
        nid = _store_node(store, sid, orb_nodes[-1], 99)
        w = v.add(nid, orb_nodes[-1])
        assert np.array_equal(v2.add(nid, orb_nodes[-1], store=store), w)
        assert np.array_equal(v2.last_new_words, v.last_new_words) and len(v.last_new_words)
    with MapStore(path, create=False) as store:
        _assert_same(v, Vocabulary.from_store(store), probe)


def test_failed_save_takes_the_node_back_out(tmp_path, orb_nodes):
    with MapStore(tmp_path / "map.db") as store:
        sid = store.begin_session("r1", CAL)
        v = Vocabulary()
        a = _store_node(store, sid, orb_nodes[0], 0)
        v.add(a, orb_nodes[0], store=store)
        n_words = len(v)
        with pytest.raises(UnknownIdError):
            v.add(12345, orb_nodes[1], store=store)  # no such node in the map
        assert len(v) == n_words and 12345 not in v and store.count_words() == n_words
        b = _store_node(store, sid, orb_nodes[1], 1)
        v.add(b, orb_nodes[1], store=store)  # later nodes still save (no dangling words)
        assert store.count_words() == len(v) > n_words
        _assert_same(v, Vocabulary.from_store(store), orb_nodes[1])


def test_pruned_words_leave_the_database_and_their_ids_stay_used(tmp_path, orb_nodes):
    path = tmp_path / "map.db"
    with MapStore(path) as store:
        sid = store.begin_session("r1", CAL)
        v = Vocabulary()
        nodes = [_store_node(store, sid, d, k) for k, d in enumerate(orb_nodes[:6])]
        for n, d in zip(nodes, orb_nodes):
            v.add(n, d, store=store)
        next_id = v.state()["next_id"][0]
        # The newest node goes: its words no other node has are removed, from the DB too.
        orphans = v.remove_node(nodes[-1])
        assert len(orphans) > 0 and orphans.max() == next_id - 1
        store.save_node_words(nodes[-1], np.full(len(orb_nodes[5]), -1, np.int64))  # the node is gone
        assert store.delete_words(orphans) == len(orphans)
        assert store.count_words() == len(v)
        ids, _ = store.load_words(orphans)
        assert len(ids) == 0
        v2 = Vocabulary.from_store(store)
        assert len(v2) == len(v) and np.all(v2.query(v.descriptors(orphans)) != orphans)
        # Pruning the newest words does not free their ids.
        assert v2.state()["next_id"][0] == next_id
        n = _store_node(store, sid, orb_nodes[6], 6)
        v2.add(n, orb_nodes[6], store=store)
        assert len(v2.last_new_words) and v2.last_new_words.min() >= next_id
        # DB-side pruning: words no stored node refers to.
        store.save_node_words(nodes[0], np.full(len(orb_nodes[0]), -1, np.int64))
        only_0 = [w for w in v2.node_words(nodes[0])[0].tolist() if set(v2.word_nodes(w)) == {nodes[0]}]
        pruned = store.prune_words()
        assert sorted(pruned.tolist()) == sorted(only_0) and len(only_0) > 0
        assert store.count_words() == len(v2) - len(only_0)
        assert len(store.prune_words()) == 0


def test_mappers_of_one_store_share_its_vocabulary(tmp_path, orb_nodes):
    path = tmp_path / "map.db"
    with MapStore(path) as store:
        v = Vocabulary.for_store(store)
        assert Vocabulary.for_store(store) is v and len(v) == 0
        sid = store.begin_session("r1", CAL)
        v.add(_store_node(store, sid, orb_nodes[0], 0), orb_nodes[0], store=store)
    with MapStore(path, create=False) as store:  # reopened: loaded once, then shared
        v2 = Vocabulary.for_store(store)
        assert v2 is not v and len(v2) == len(v) and Vocabulary.for_store(store) is v2


def test_offline_run_leaves_the_live_vocabulary_in_map_db(tmp_path):
    ds = open_dataset("synthetic:loop", rate=5, max_frames=80)
    out = run_dataset(ds, load_config(), tmp_path, progress=False)
    assert out.summary.keyframes > 5
    with MapStore(tmp_path / "map.db", create=False) as store:
        nodes = [n.id for n in store.nodes(limit=None)]
        assert len(nodes) == out.summary.keyframes
        # The live vocabulary, replayed: the mapper adds each keyframe's stored descriptors.
        live = Vocabulary(nndr=load_config().loop.nndr_ratio)
        for n in nodes:
            _, desc, _, word_ids = store.load_features(n)
            assert word_ids is not None, n
            assert np.array_equal(live.add(n, desc), word_ids), n
        loaded = Vocabulary.from_store(store)
        assert len(loaded) == len(live) == store.count_words() > 0
        _assert_same(live, loaded, _flip(np.random.default_rng(3), live.descriptors(live.state()["word_ids"][:300]), 4))


_CHILD = """
import sys
sys.path.insert(0, {root!r})
import numpy as np
from client.frames import Calibration, PinholeCamera
from service.vocabulary import Vocabulary
from storage import KeyframeRecord, MapStore
rng = np.random.default_rng(0)
centres = rng.integers(0, 256, (3000, 32), dtype=np.uint8)
store = MapStore({path!r})
sid = store.begin_session("crash", Calibration(PinholeCamera(500.0, 500.0, 320.0, 240.0, 640, 480), None, 1000.0))
v = Vocabulary()
for k in range(100000):
    d = rng.integers(0, 256, (500, 32), dtype=np.uint8)
    d[:250] = centres[rng.integers(0, len(centres), 250)]
    nid = store.add_keyframe(KeyframeRecord(sid, float(k), np.eye(4), np.zeros((500, 2), np.float32), d,
                                            np.zeros((500, 3), np.float32)))
    v.add(nid, d, store=store)
    print(nid, len(v), flush=True)
"""


def test_kill_9_never_leaves_word_ids_without_their_words(tmp_path):
    path = tmp_path / "crash.db"
    proc = subprocess.Popen([sys.executable, "-c", _CHILD.format(root=str(ROOT), path=str(path))],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    printed = []
    deadline = time.monotonic() + 60
    try:
        while len(printed) < 30 and time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            printed.append(tuple(map(int, line.split())))
    finally:
        proc.send_signal(signal.SIGKILL)
        out, err = proc.communicate(timeout=10)
    assert proc.returncode == -signal.SIGKILL
    assert len(printed) >= 30, err
    printed += [tuple(map(int, line.split())) for line in out.split("\n")[:-1]]
    with MapStore(path, create=False) as store:
        assert store.integrity_check() == "ok"
        st = store.load_vocabulary_state()
        referenced = [store.load_features(n)[3] for n in st["node_ids"].tolist()]
        referenced = np.unique(np.concatenate(referenced))
        assert np.isin(referenced, st["word_ids"]).all()  # no id points at an unsaved word
        assert set(st["word_ids"].tolist()) == set(referenced.tolist())  # and no word saved without its node
        indexed = set(st["node_ids"].tolist())
        assert {n for n, _ in printed} <= indexed  # every reported add() is in the file
        _, n_words = printed[-1]
        assert len(Vocabulary.from_store(store)) >= n_words
        assert store.count_nodes() - len(indexed) <= 1  # at most the node stored but not yet quantized
