"""Incremental vocabulary: word assignment (NNDR), inverted index, removal, persistence,
sub-linear search."""
import numpy as np

from service.vocabulary import Vocabulary


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
