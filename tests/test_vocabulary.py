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

from mnemoslam.client.datasets import open_dataset
from mnemoslam.client.kernel.frames import Calibration, PinholeCamera
from mnemoslam.client.synthetic import SyntheticDataset
from mnemoslam.service.config import load_config
from mnemoslam.service.memory.vocabulary import MissingWordsError, Vocabulary
from mnemoslam.service.runner import run_dataset
from mnemoslam.storage import KeyframeRecord, MapStore, UnknownIdError

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
from mnemoslam.client.kernel.frames import Calibration, PinholeCamera
from mnemoslam.service.memory.vocabulary import MissingWordsError, Vocabulary
from mnemoslam.storage import KeyframeRecord, MapStore
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


# -- working memory: nodes unloaded to long-term memory and reloaded ---------------------------

def _tables(v):
    """The hash tables and word states, up to the highest id."""
    k = v.state()["next_id"][0]
    return v._head.copy(), v._nxt[:k].copy(), v._prv[:k].copy(), v._live[:k].copy(), v._dormant[:k].copy()


def _same_tables(a, b):
    return all(np.array_equal(x, y) for x, y in zip(a, b))


def _index_snapshot(v, probe):
    """Everything the loop detector reads, and the search's answers."""
    from mnemoslam.service.mapping.loop_detection import LoopDetector
    ids = sorted(v.node_ids())
    det = LoopDetector(v)
    q = v.query(probe)
    nodes = {n: (v.node_words(n)[0].copy(), v.node_words(n)[1].copy(), v.node_size(n)) for n in ids}
    cand = np.asarray(ids, np.int64)
    lik = [det.raw_likelihood(np.repeat(*v.node_words(n)), cand, n) for n in ids[::5]]
    return ids, q, [a.copy() for a in v.postings(q)], nodes, lik, v.n_nodes, len(v)


def _same_snapshot(a, b):
    ids, q, post, nodes, lik, n_nodes, n_words = a
    ids2, q2, post2, nodes2, lik2, n_nodes2, n_words2 = b
    assert ids == ids2 and n_nodes == n_nodes2 and n_words == n_words2
    assert np.array_equal(q, q2)
    for x, y in zip(post, post2):
        assert np.array_equal(x, y)
    for n in ids:
        (w, c, s), (w2, c2, s2) = nodes[n], nodes2[n]
        assert np.array_equal(w, w2) and np.array_equal(c, c2) and s == s2, n
    for x, y in zip(lik, lik2):
        assert np.array_equal(x, y)  # bit-identical


def _check_consistent(v):
    """Invariants: postings = the nodes' words; every word a node in RAM has is live; live
    and dormant disjoint and counted; the tables are the canonical ones (from_state's)."""
    derived = {}
    for n in v.node_ids():
        for w, c in zip(*(a.tolist() for a in v.node_words(n))):
            derived.setdefault(w, {})[n] = c
    assert {w: v.word_nodes(w) for w in derived} == derived
    assert set(v._postings) == set(derived)
    k = v.state()["next_id"][0]
    live, dormant = v._live[:k], v._dormant[:k]
    assert not np.any(live & dormant) and not v._live[k:].any() and not v._dormant[k:].any()
    assert live.sum() == len(v) and dormant.sum() == v.dormant
    assert live[list(derived)].all()
    assert _same_tables(_tables(v), _tables(Vocabulary.from_state(v.state(), capacity=v._cap)))


def test_unload_reload_round_trip_is_identical(orb_nodes):
    v = Vocabulary()
    for n, d in enumerate(orb_nodes[:-1]):
        v.add(n, d)
    probe = _flip(np.random.default_rng(12), orb_nodes[-1], 3)
    before, tables = _index_snapshot(v, probe), _tables(v)
    n_words = len(v)
    # To LTM: every third node, and a run of neighbours (words only they share go dormant).
    ltm = sorted(set(range(0, 40, 3)) | {20, 21, 22})
    held = {w: set(v.word_nodes(w)) for w in v.state()["word_ids"].tolist()}
    exclusive = np.array(sorted(w for w, ns in held.items() if ns <= set(ltm)), np.int64)
    shared = np.array(sorted(w for w, ns in held.items() if ns & set(ltm) and not ns <= set(ltm)), np.int64)
    assert len(exclusive) > 1000 and len(shared) > 1000
    out = {n: v.unload_node(n) for n in ltm}
    assert v.n_nodes == 40 - len(ltm) and not any(n in v for n in ltm)
    assert len(v) == n_words - len(exclusive) and v.dormant == len(exclusive)
    assert not v._live[exclusive].any() and v._live[shared].all()
    _check_consistent(v)
    # The dormant words are out of the search; the ones a WM node still has are found.
    assert not np.isin(v.query(v.descriptors(exclusive)), exclusive).any()
    assert np.isin(v.query(_flip(np.random.default_rng(1), orb_nodes[20], 3)), exclusive).sum() == 0
    assert (v.query(v.descriptors(shared)) == shared).mean() > 0.99
    assert all(not v.word_nodes(w) for w in exclusive[:100].tolist())
    uw, df, idx, nodes, counts = v.postings(np.concatenate([exclusive, shared]))
    assert not np.isin(nodes, ltm).any()
    assert len(v.unload_node(ltm[0])[0]) == 0  # not in RAM any more: nothing
    # Back, in another order: everything as it was, bit for bit.
    for n in reversed(ltm):
        v.reload_node(n, *out[n])
    assert v.dormant == 0
    _same_snapshot(before, _index_snapshot(v, probe))
    assert _same_tables(tables, _tables(v))
    # Stored word ids (repeats = counts, -1 = none) give the same node back.
    w, c = v.unload_node(5)
    stored = np.concatenate([np.repeat(w, c), [-1, -1]])
    v.reload_node(5, np.random.default_rng(0).permutation(stored))
    _same_snapshot(before, _index_snapshot(v, probe))
    with pytest.raises(ValueError, match="in RAM"):
        v.reload_node(5, stored)


def test_nodes_added_while_others_are_unloaded(orb_nodes):
    v = Vocabulary()
    for n, d in enumerate(orb_nodes[:20]):
        v.add(n, d)
    next_id = v.state()["next_id"][0]
    out = {n: v.unload_node(n) for n in range(0, 15)}  # the start of the loop goes to LTM
    dormant = np.nonzero(v._dormant)[0]
    assert len(dormant) == v.dormant > 0
    # The loop comes back to the start (last frames ≈ first ones): its words are dormant, so
    # they are not matched and new words are made, with new ids.
    for n in range(36, 40):
        v.add(n, orb_nodes[n])
        assert v.last_new_words.min() >= next_id
        _check_consistent(v)
    assert v._dormant[dormant].all()
    reference = Vocabulary.from_state(v.state())
    for n in sorted(out):  # retrieved: both copies of the place are searchable again
        v.reload_node(n, *out[n])
        reference.reload_node(n, *out[n])
        _check_consistent(v)
    assert v.dormant == 0 and v.n_nodes == 24
    _assert_same(v, reference, orb_nodes[0])
    assert _same_tables(_tables(v), _tables(reference))
    # The likelihood finds the start again from a revisit.
    from mnemoslam.service.mapping.loop_detection import LoopDetector
    w = v.query(orb_nodes[38])
    raw = LoopDetector(v).raw_likelihood(w, np.arange(0, 15), None)
    assert raw.argmax() <= 3 and raw.max() > 0
    # Both grow identically afterwards.
    probe = _flip(np.random.default_rng(2), orb_nodes[25], 5)
    assert np.array_equal(v.add(100, probe), reference.add(100, probe))


def test_state_round_trip_with_dormant_words():
    rng = np.random.default_rng(13)
    centres = _rand(rng, 500)
    v = Vocabulary(key_bits=12, n_tables=8, capacity=1 << 14)  # long buckets: chains matter
    for n in range(30):
        d = _rand(rng, 200)
        d[:100] = _flip(rng, centres[rng.integers(0, 500, 100)], 6)
        v.add(n, d)
    tables = _tables(v)
    out = {n: v.unload_node(n) for n in (3, 4, 5, 17, 29)}
    st = v.state()
    # Dormant words are persisted (the map has them) and flagged.
    assert len(st["word_ids"]) == len(v) + v.dormant and st["dormant"].sum() == v.dormant
    assert set(st["post_node"].tolist()) == set(range(30)) - set(out)
    v2 = Vocabulary.from_state(st, capacity=1 << 14)
    assert len(v2) == len(v) and v2.dormant == v.dormant and v2.n_nodes == v.n_nodes
    assert _same_tables(_tables(v), _tables(v2))
    probe = _flip(rng, v.descriptors(st["word_ids"]), 4)
    assert np.array_equal(v.query(probe), v2.query(probe))
    # A state without the flag (e.g. the store's) has every word searchable.
    v3 = Vocabulary.from_state({k: a for k, a in st.items() if k != "dormant"}, capacity=1 << 14)
    assert v3.dormant == 0 and len(v3) == len(v) + v.dormant == len(st["word_ids"])
    for n in (29, 3, 17, 5, 4):
        v.reload_node(n, *out[n])
        v2.reload_node(n, *out[n])
    assert _same_tables(tables, _tables(v2)) and v2.dormant == 0
    _assert_same(v, v2, probe)
    new = _rand(rng, 100)
    assert np.array_equal(v.add(99, new), v2.add(99, new))


def test_reload_into_a_vocabulary_that_never_had_the_words(tmp_path, orb_nodes):
    """A restarted process loads only working memory; nodes retrieved from LTM bring their
    words from the map (`store.load_words`)."""
    path = tmp_path / "map.db"
    v = Vocabulary()
    with MapStore(path) as store:
        sid = store.begin_session("r1", CAL)
        nodes = [_store_node(store, sid, d, k) for k, d in enumerate(orb_nodes[:30])]
        for n, d in zip(nodes, orb_nodes):
            v.add(n, d, store=store)
    ltm, wm = nodes[:20], nodes[20:]
    with MapStore(path, create=False) as store:
        st = store.load_vocabulary_state()
        keep = np.isin(st["post_node"], wm)
        wm_words = np.unique(st["post_word"][keep])
        has = np.isin(st["word_ids"], wm_words)
        partial = dict(st, word_ids=st["word_ids"][has], descriptors=st["descriptors"][has],
                       post_word=st["post_word"][keep], post_node=st["post_node"][keep],
                       post_count=st["post_count"][keep], node_ids=np.asarray(wm, np.int64),
                       node_nfeat=st["node_nfeat"][np.isin(st["node_ids"], wm)])
        restarted = Vocabulary.from_state(partial)
        full = Vocabulary.from_store(store)
        for n in ltm:
            full.unload_node(n)
        # Same searchable words and tables; the restarted one just has no dormant words.
        assert len(restarted) == len(full) and restarted.dormant == 0 < full.dormant
        t, t2 = _tables(restarted), _tables(full)
        assert all(np.array_equal(x, y) for x, y in zip(t[:4], t2[:4]))
        # A word created now never takes an id of the map's (dormant or not loaded).
        d = _rand(np.random.default_rng(4), 50)
        assert np.array_equal(restarted.add(10_000, d), full.add(10_000, d))
        assert restarted.last_new_words.min() >= st["next_id"][0]
        for k, n in enumerate(ltm):
            ids = store.load_features(n)[3]
            missing = restarted.missing_words(ids)
            assert len(missing) and not len(full.missing_words(ids))
            with pytest.raises(MissingWordsError) as err:
                restarted.reload_node(n, ids)
            assert np.array_equal(err.value.word_ids, missing) and n not in restarted
            if k % 2:  # the (ids, descriptors) pair of the store
                restarted.reload_node(n, ids, descriptors=store.load_words(missing))
            else:  # or descriptors of all the node's distinct words
                restarted.reload_node(n, ids, descriptors=store.load_words(ids)[1])
            full.reload_node(n, ids)
            _check_consistent(restarted)
        assert full.dormant == restarted.dormant == 0
        _assert_same(full, restarted, _flip(np.random.default_rng(5), orb_nodes[25], 3))
        assert _same_tables(_tables(full), _tables(restarted))
        with pytest.raises(MissingWordsError):
            restarted.reload_node(777, [restarted.state()["next_id"][0] + 5])


def test_dormant_words_removed_for_good():
    rng = np.random.default_rng(14)
    v = Vocabulary()
    d = _rand(rng, 30)
    v.add(1, d[:20])
    v.add(2, d[10:30])
    w, c = v.unload_node(1)
    assert v.dormant == 10 and len(v) == 20
    v.index_node(1, np.repeat(w, c))  # index_node (the loop detector's) wakes them too
    assert v.dormant == 0 and len(v) == 30 and np.array_equal(v.query(d), np.arange(30))
    _check_consistent(v)
    w, c = v.unload_node(1)
    assert np.all(v.query(d[:10]) == -1)
    v.remove_words(w[:5])  # e.g. pruned from the map with the node
    assert v.dormant == 5 and len(v) == 20 and len(v.missing_words(w)) == 5
    with pytest.raises(MissingWordsError):
        v.reload_node(1, w, c)
    v.remove_words(w)  # the shared ones are deleted from node 2
    assert v.dormant == 0 and len(v) == 10 and v.node_size(2) == 20
    assert np.array_equal(v.node_words(2)[0], np.arange(20, 30))
    _check_consistent(v)
    # counts form: duplicates are summed, order does not matter
    v.reload_node(3, [25, 21, 25, -1], [1, 2, 3, 9])
    assert np.array_equal(v.node_words(3)[0], [21, 25]) and np.array_equal(v.node_words(3)[1], [2, 4])
    assert v.node_size(3) == 6
    with pytest.raises(ValueError):
        v.reload_node(4, [21, 22], [1])
