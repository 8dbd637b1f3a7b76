"""Incremental visual vocabulary over binary (ORB, 256-bit) descriptors.

RTAB-Map's incremental dictionary (VWDictionary) searches a FLANN index and rebuilds it
every time the dictionary doubles; its users see 500-600 ms freezes (introlab/rtabmap#982).
This one never rebuilds: nearest neighbours come from a fixed set of bit-sampling LSH
tables (L tables, each keyed on k sampled bits). Every table is a chained hash table held
in numpy arrays: `head[table, key]` is the newest word of the bucket and per-word
`next`/`prev` links (doubly linked, so removal is O(L) per word). Insertion of a batch and
the chain walk of a query batch are vectorized over descriptors × tables; a query walks at
most `max_chain` words per table, so its work is bounded whatever the vocabulary size, and
the exact Hamming distances (np.bitwise_count on uint64 views) are computed on that
candidate set only.

Arrays are preallocated with `np.zeros` (calloc: pages are only touched as words arrive),
so growth costs nothing until `capacity` is exceeded (then one doubling copy).

Links store slot+1, 0 meaning "none". A word's id is its slot; ids are never reused.

Word assignment (RTAB-Map's rule, `Kp/NndrRatio`): a descriptor whose nearest word is
farther than `nndr` × the second-nearest distance, or farther than `max_distance`, or with no
word found, makes a new word; otherwise it votes for the nearest word. Descriptors of the
same batch that would all make new words are first matched among themselves (brute force,
bounded by the batch size) so that repeated descriptors of one node share a word.

Persistence with the map (its role `storage.WordStore`, which `MapStore` implements):
`add(..., store=)` commits the node's word ids and the words it created in
one transaction, `from_store` rebuilds the vocabulary of a reopened map from the `words`
table and the nodes' word ids without any search, and `for_store` gives the one vocabulary
that every mapper of a map shares (word ids are the map's, so two vocabularies must not
write to one file). Callers sharing a vocabulary between threads hold its `lock`.

Working memory (RTAB-Map's WM/LTM): the vocabulary holds the nodes in RAM (WM), and only
their words are searched. `unload_node` takes a node moving to long-term memory out of the
inverted index; the words no node in RAM references any more become *dormant*: unlinked
from the hash tables (neither `query` nor `add` finds them, so search cost and the
likelihood's candidates stay bounded by WM) but their descriptors kept. `reload_node`
brings the node back: its dormant words are linked again, at their place (every bucket's
chain is in descending id order whatever was unlinked and relinked in between, so the
tables are exactly those of a vocabulary that never unloaded anything) and its postings are
restored. Words the vocabulary never held (a restarted process that loaded only WM) come
with the call (`descriptors=store.load_words(...)`). Nothing is deleted and ids are never
reused: words created while others are dormant get new ids. `len()` counts the searchable
words, `dormant` the others.
"""
from __future__ import annotations

import threading
import weakref
from typing import Any

import numpy as np

from mnemoslam.storage import WordStore

_NONE_DIST = 257  # larger than any 256-bit Hamming distance


def as_u64(desc: np.ndarray) -> np.ndarray:
    """N×32 uint8 ORB descriptors viewed as N×4 uint64 (for `hamming_matrix`)."""
    d = np.ascontiguousarray(desc, dtype=np.uint8)
    if d.ndim != 2 or d.shape[1] != 32:
        raise ValueError(f"descriptors must be N×32 uint8, got {d.shape}")
    return d.view(np.uint64)


def _runs(sorted_keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(starts, ends) of the runs of equal values of a sorted array."""
    cuts = np.flatnonzero(sorted_keys[1:] != sorted_keys[:-1]) + 1
    return np.r_[0, cuts], np.r_[cuts, len(sorted_keys)]


class MissingWordsError(LookupError):
    """`reload_node` was given word ids this vocabulary holds no descriptor for (and no
    descriptors for them): `word_ids` lists them."""

    def __init__(self, node_id: int, word_ids: np.ndarray):
        self.node_id = int(node_id)
        self.word_ids = np.asarray(word_ids, np.int64)
        some = ", ".join(map(str, self.word_ids[:8].tolist())) + (", ..." if len(self.word_ids) > 8 else "")
        super().__init__(
            f"node {self.node_id} references {len(self.word_ids)} word(s) this vocabulary does not hold "
            f"({some}): pass their descriptors, e.g. descriptors=store.load_words(vocabulary.missing_words(ids))")


def hamming_matrix(a64: np.ndarray, b64: np.ndarray) -> np.ndarray:
    """All-pairs Hamming distances (len(a), len(b)) int32 of (n, 4) uint64 arrays."""
    d = np.bitwise_count(np.bitwise_xor.outer(a64[:, 0], b64[:, 0])).astype(np.int32)
    for k in range(1, a64.shape[1]):
        d += np.bitwise_count(np.bitwise_xor.outer(a64[:, k], b64[:, k]))
    return d


class Vocabulary:
    def __init__(self, nndr: float = 0.8, max_distance: int = 70, n_tables: int = 16,
                 key_bits: int = 16, max_chain: int = 40, capacity: int = 1 << 21, seed: int = 7):
        self.nndr = float(nndr)
        self.max_distance = int(max_distance)
        self.n_tables = int(n_tables)
        self.key_bits = int(key_bits)
        self.max_chain = int(max_chain)
        self.seed = int(seed)
        rng = np.random.default_rng(seed)
        # Bits sampled by each table (distinct within a table).
        self._bits = np.stack([rng.choice(256, self.key_bits, replace=False) for _ in range(self.n_tables)])
        if self.key_bits > 24:
            raise ValueError("key_bits must be <= 24")
        self._weights = np.zeros((256, self.n_tables), np.float32)  # bit -> 2^j in table t
        for t in range(self.n_tables):
            self._weights[self._bits[t], t] = 2.0 ** np.arange(self.key_bits)
        byte_bits = np.unpackbits(np.arange(256, dtype=np.uint8)[:, None], axis=1).astype(np.float64)
        self._lut = np.stack([byte_bits @ self._weights[8 * p: 8 * p + 8].astype(np.float64)
                              for p in range(32)]).astype(np.uint32)  # (32, 256, L)
        self._tbl_off = (np.arange(self.n_tables, dtype=np.int64) << self.key_bits)
        self._head = np.zeros(self.n_tables << self.key_bits, np.int32)
        self._alloc(max(int(capacity), 1024))
        self._next_id = 0
        self._n_live = 0  # words linked in the tables (searchable)
        self._n_dormant = 0  # words kept (descriptors) but unlinked: only LTM nodes have them
        # Inverted index: word -> {node: count}; node -> (unique words, counts), #features.
        self._postings: dict[int, dict[int, int]] = {}
        self._nodes: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._nfeat: dict[int, int] = {}
        self.last_candidates = 0  # exact distance computations of the last search
        self.last_queries = 0
        self.last_new_words = np.zeros(0, np.int64)  # ids of the words the last add() created
        self.lock = threading.RLock()  # for callers sharing the vocabulary between threads

    # -- storage arrays -----------------------------------------------------------------
    def _alloc(self, cap: int) -> None:
        self._cap = cap
        self._desc = np.zeros((cap, 4), np.uint64)
        self._nxt = np.zeros((cap, self.n_tables), np.int32)
        self._prv = np.zeros((cap, self.n_tables), np.int32)
        self._live = np.zeros(cap, bool)  # linked in the tables
        self._dormant = np.zeros(cap, bool)  # descriptor kept, not linked (never both)

    def _ensure(self, n_more: int) -> None:
        need = self._next_id + n_more
        if need <= self._cap:
            return
        cap = self._cap
        while cap < need:
            cap *= 2
        old: tuple[np.ndarray, ...] = (self._desc, self._nxt, self._prv, self._live, self._dormant)
        n = self._next_id
        self._alloc(cap)
        grown: tuple[np.ndarray, ...] = (self._desc, self._nxt, self._prv, self._live, self._dormant)
        for new, a in zip(grown, old):
            new[:n] = a[:n]

    # -- properties ---------------------------------------------------------------------
    def __len__(self) -> int:
        """Searchable words (linked in the hash tables); dormant ones are not counted."""
        return self._n_live

    @property
    def dormant(self) -> int:
        """Words kept out of the search because only unloaded (LTM) nodes have them."""
        return self._n_dormant

    def __contains__(self, node_id) -> bool:
        """Whether a node is in the inverted index."""
        return int(node_id) in self._nodes

    def node_ids(self) -> list[int]:
        return list(self._nodes)

    @property
    def n_nodes(self) -> int:
        """Nodes in the inverted index (in RAM: unloaded nodes are not counted)."""
        return len(self._nodes)

    def descriptors(self, word_ids) -> np.ndarray:
        """Descriptors (W×32 uint8) of words, live or dormant."""
        return self._desc[np.asarray(word_ids, np.int64)].view(np.uint8).reshape(-1, 32)

    def _held(self, word_ids: np.ndarray) -> np.ndarray:
        """Whether each word id (≥ 0) is live or dormant."""
        w = np.asarray(word_ids, np.int64)
        ok = w < self._next_id
        held = np.zeros(len(w), bool)
        held[ok] = self._live[w[ok]] | self._dormant[w[ok]]
        return held

    def missing_words(self, word_ids) -> np.ndarray:
        """The distinct ids (≥ 0, ascending) among `word_ids` that this vocabulary holds no
        descriptor for (neither live nor dormant): what `reload_node` needs `descriptors` for."""
        w = np.unique(np.asarray(word_ids, np.int64))
        w = w[w >= 0]
        return w[~self._held(w)]

    # -- hashing ------------------------------------------------------------------------
    def _keys(self, d64: np.ndarray) -> np.ndarray:
        """(n, L) flat head indices (table offset + key): per descriptor byte, one lookup of
        its contribution to every table's key (32 vectorized gathers)."""
        return self._local_keys(d64).astype(np.int64) + self._tbl_off

    def _local_keys(self, d64: np.ndarray) -> np.ndarray:
        """(n, L) uint32 keys within each table (summed in uint32: keys have ≤ 24 bits)."""
        b = d64.view(np.uint8).reshape(-1, 32)
        keys = self._lut[0][b[:, 0]]
        for p in range(1, 32):
            keys += self._lut[p][b[:, p]]
        return keys

    def _link(self, slots: np.ndarray, keys: np.ndarray) -> None:
        """Push words (slots (n,), keys (n, L)) on their buckets, table by table (L is
        small; each table is one vectorized pass, a radix sort for keys of ≤ 16 bits)."""
        slots = slots.astype(np.int64)
        key_dtype = np.uint16 if self.key_bits <= 16 else np.int64
        for t in range(keys.shape[1]):
            local = (keys[:, t] - self._tbl_off[t]).astype(key_dtype)
            order = np.argsort(local, kind="stable")
            K = keys[order, t]
            S = slots[order]
            brk = K[1:] != K[:-1]
            first = np.r_[True, brk]
            last = np.r_[brk, True]
            old_head = self._head[K]
            nxt = self._nxt[:, t]
            prv = self._prv[:, t]
            nxt[S] = np.where(first, old_head, np.r_[0, S[:-1] + 1])
            m = first & (old_head > 0)
            prv[old_head[m] - 1] = S[m] + 1
            nf = ~first[1:]
            prv[S[:-1][nf]] = S[1:][nf] + 1
            prv[S[last]] = 0
            self._head[K[last]] = S[last] + 1

    def _link_all(self, slots: np.ndarray, d64: np.ndarray, group: int = 4) -> None:
        """Link words (ascending slots, descriptors d64) into empty hash tables: exactly what
        `_link` in id order builds, but a few tables at a time in table-major scratch arrays
        (contiguous scatters instead of ones strided by the row length), copied into the
        per-word links once per group. 4-5x faster than `_link` for a whole vocabulary."""
        n, L = len(slots), self.n_tables
        if n == 0:
            return
        local = np.empty((L, n), np.uint16 if self.key_bits <= 16 else np.uint32)
        for a in range(0, n, 1 << 16):  # chunks bound _keys' temporaries
            local[:, a:a + (1 << 16)] = self._local_keys(d64[a:a + (1 << 16)]).T
        s1 = slots.astype(np.int32) + 1  # link values are slot + 1
        rows = slice(int(slots[0]), int(slots[-1]) + 1) if slots[-1] - slots[0] + 1 == n else slots
        for t0 in range(0, L, group):
            g = min(group, L - t0)
            nxt = np.zeros((g, n), np.int32)
            prv = np.zeros((g, n), np.int32)
            for j in range(g):
                t = t0 + j
                order = np.argsort(local[t], kind="stable")
                K = local[t][order]
                brk = K[1:] != K[:-1]
                # a bucket's words come in ascending slots: each points at the previous (older)
                # one, the bucket's head is its last (newest)
                nxt[j, order[1:]] = np.where(brk, 0, s1[order[:-1]])
                prv[j, order[:-1]] = np.where(brk, 0, s1[order[1:]])
                last = np.r_[brk, True]
                self._head[self._tbl_off[t] + K[last].astype(np.int64)] = s1[order[last]]
            self._nxt[rows, t0:t0 + g] = nxt.T
            self._prv[rows, t0:t0 + g] = prv.T

    def _unlink(self, slots: np.ndarray) -> None:
        """Take words (distinct linked slots) out of every table, vectorized over the words
        of a table: a removed word's nearest kept neighbours in its chain are found by
        pointer jumping over the removed words next to it (runs of them in one bucket), then
        each run is spliced out in one write (all the words of a run write the same links).
        The kept words keep their order, so the tables are those of a vocabulary that never
        had the removed words."""
        slots = np.unique(np.asarray(slots, np.int64))
        if not len(slots):
            return
        L = self.n_tables
        keys = self._keys(self._desc[slots]).ravel()  # (word, table) pairs, word-major: the tables at once
        tbl = np.tile(np.arange(L), len(slots))
        last = len(slots) - 1

        def removed(link: np.ndarray) -> np.ndarray:  # link values (slot + 1, 0 = none)
            s = link.astype(np.int64) - 1
            return slots[np.minimum(np.searchsorted(slots, s), last)] == s

        def kept(link: np.ndarray, table: np.ndarray) -> np.ndarray:
            """`link` (the removed words' neighbours along `table`) jumped over removed words."""
            m = np.nonzero(removed(link))[0]
            while len(m):
                link[m] = table[link[m] - 1, tbl[m]]
                m = m[removed(link[m])]
            return link

        nxt, prv = self._nxt, self._prv
        p = kept(prv[slots].ravel(), prv)
        n = kept(nxt[slots].ravel(), nxt)
        hp = p > 0
        nxt[p[hp] - 1, tbl[hp]] = n[hp]
        self._head[keys[~hp]] = n[~hp]
        hn = n > 0
        prv[n[hn] - 1, tbl[hn]] = p[hn]
        self._nxt[slots] = 0
        self._prv[slots] = 0

    def _relink(self, slots: np.ndarray) -> None:
        """Link words (distinct slots, not linked) into every table at their place: each
        bucket's chain is kept in descending id order (what `_link` of ever newer words and
        `_link_all` build), so relinking what `_unlink` took out restores the tables
        exactly. Vectorized over the words of a table: their successors are found by one
        walk of all the chains at once, words falling between the same two chain words are
        chained together (descending ids) and spliced in."""
        slots = np.unique(np.asarray(slots, np.int64))
        if not len(slots):
            return
        L = self.n_tables
        k = self._keys(self._desc[slots]).ravel()  # (word, table) pairs, word-major: the tables at once
        tbl = np.tile(np.arange(L), len(slots))
        s1 = np.repeat((slots + 1).astype(np.int32), L)  # link values
        nxt, prv = self._nxt, self._prv
        pred = np.zeros(len(s1), np.int32)  # chain word before the gap (0: the head)
        succ = self._head[k]  # chain word after the gap (0: the end)
        act = np.nonzero(succ > s1)[0]  # newer words come first: walk past them
        while len(act):
            pred[act] = succ[act]
            succ[act] = nxt[succ[act] - 1, tbl[act]]
            act = act[succ[act] > s1[act]]
        # by bucket (keys are flat over the tables: a bucket is one table's), gap, then id descending
        order = np.lexsort((-s1, succ, k))
        K, P, N, S, T = k[order], pred[order], succ[order], s1[order], tbl[order]
        first = np.ones(len(S), bool)  # first / last word of its gap
        np.not_equal(K[1:], K[:-1], out=first[1:])
        first[1:] |= N[1:] != N[:-1]
        last = np.ones(len(S), bool)
        last[:-1] = first[1:]
        before = np.zeros_like(S)  # the batch word before / after in the same gap
        before[1:] = S[:-1]
        after = np.zeros_like(S)
        after[:-1] = S[1:]
        prv[S - 1, T] = np.where(first, P, before)
        nxt[S - 1, T] = np.where(last, N, after)
        hp = first & (P > 0)
        nxt[P[hp] - 1, T[hp]] = S[hp]
        hh = first & (P == 0)
        self._head[K[hh]] = S[hh]
        tl = last & (N > 0)
        prv[N[tl] - 1, T[tl]] = S[tl]

    def _wake(self, word_ids: np.ndarray) -> None:
        """Relink the dormant words among `word_ids` (distinct, held)."""
        w = word_ids[self._dormant[word_ids]]
        if len(w):
            self._relink(w)
            self._dormant[w] = False
            self._live[w] = True
            self._n_dormant -= len(w)
            self._n_live += len(w)

    # -- search -------------------------------------------------------------------------
    def _search(self, q64: np.ndarray):
        """Nearest and second-nearest words of each query: (w1, d1, d2), w1 = -1 and
        d = 257 when none was found."""
        Q = len(q64)
        w1 = np.full(Q, -1, np.int64)
        d1 = np.full(Q, _NONE_DIST, np.int32)
        d2 = np.full(Q, _NONE_DIST, np.int32)
        self.last_queries = Q
        self.last_candidates = 0
        if Q == 0 or self._n_live == 0:
            return w1, d1, d2
        # Every (query, table) chain walked at once, the ended ones dropped at each step; a word
        # found by several tables is a candidate once per table (a few %: cheaper than
        # deduplicating), which neither the nearest nor the second-nearest (another word) minds.
        L = self.n_tables
        nxt = self._nxt.reshape(-1)  # (flat takes: ~3x faster than 2-D fancy indexing)
        cur = self._head[self._keys(q64)].reshape(-1)  # (Q * L,) chain heads, query-major
        at = np.flatnonzero(cur)  # the chains still walked (query * L + table)
        cur = cur[at]
        words, owner = [], []
        for _ in range(self.max_chain):
            if not len(at):
                break
            words.append(cur)
            owner.append(at)
            cur = nxt.take((cur - 1).astype(np.int64) * L + at % L)
            live = np.flatnonzero(cur)
            at, cur = at[live], cur[live]
        if not words:
            return w1, d1, d2
        qi = np.concatenate(owner) // L
        slots = np.concatenate(words).astype(np.int64) - 1
        self.last_candidates = len(slots)
        x = self._desc.take(slots, axis=0)  # the candidates' descriptors, xor-ed in place
        x ^= q64.take(qi, axis=0)
        bits = np.bitwise_count(x)
        d = bits[:, 0].astype(np.int64)
        d += bits[:, 1]
        d += bits[:, 2]
        d += bits[:, 3]
        # per query the nearest word (the lowest id of the equally near: distance, then id, in one
        # key), then the nearest other word
        none = np.iinfo(np.int64).max
        best = np.full(Q, none, np.int64)
        np.minimum.at(best, qi, d << 32 | slots)
        found = best < none
        d1[found] = best[found] >> 32
        w1[found] = best[found] & 0xFFFFFFFF
        d[slots == w1[qi]] = _NONE_DIST
        second = np.full(Q, _NONE_DIST, np.int64)
        np.minimum.at(second, qi, d)
        return w1, d1, second.astype(np.int32)

    def _accept(self, d1: np.ndarray, d2: np.ndarray) -> np.ndarray:
        return (d1 <= self.max_distance) & (d1 <= self.nndr * d2)

    def query(self, descriptors: np.ndarray) -> np.ndarray:
        """Word of each descriptor without inserting anything: (N,) int64, -1 when the
        descriptor matches no word (it would make a new one)."""
        q64 = as_u64(descriptors)
        w1, d1, d2 = self._search(q64)
        return np.where(self._accept(d1, d2), w1, -1)

    # -- insertion ----------------------------------------------------------------------
    def add(self, node_id: int, descriptors: np.ndarray, store: WordStore | None = None) -> np.ndarray:
        """Quantize a node's descriptors, creating new words as needed, and index the node.
        Returns the word id of each descriptor (N,) int64; `last_new_words` holds the ids of
        the words created. With a `store` (MapStore holding the node's features) the word
        ids and the new words are committed in one transaction before this returns; if that
        fails, the node and its new words are taken back out and the error propagates, so
        the vocabulary never holds words the map does not."""
        with self.lock:
            q64 = as_u64(descriptors)
            first_new = self._next_id
            w1, d1, d2 = self._search(q64)
            words = np.where(self._accept(d1, d2), w1, -1)
            new = np.nonzero(words < 0)[0]
            if len(new):
                words[new] = self._create_words(q64[new], d1[new])
            created = np.arange(first_new, self._next_id, dtype=np.int64)
            self.last_new_words = created
            self.index_node(node_id, words)
            if store is not None:
                try:
                    store.save_node_words(node_id, words, created, self.descriptors(created))
                except BaseException:
                    self.remove_node(node_id, drop_orphans=False)
                    self.remove_words(created)
                    self.last_new_words = np.zeros(0, np.int64)
                    raise
            return words

    def _create_words(self, n64: np.ndarray, d_existing: np.ndarray) -> np.ndarray:
        """New words for descriptors that matched nothing; descriptors of the batch close to
        an earlier one of the batch share its word."""
        # Exact duplicates first (so that they do not spoil each other's ratio test).
        # (rows sorted by value, stably: a run of equal rows starts with its first occurrence;
        # np.unique(axis=0) gives the same and costs ~10x)
        by_value = np.lexsort(n64.T[::-1])
        s = n64[by_value]
        starts = np.ones(len(s), bool)
        starts[1:] = (s[1:] != s[:-1]).any(axis=1)
        if not starts.all():
            first_of = np.empty(len(n64), np.int64)  # each descriptor's first occurrence
            first_of[by_value] = by_value[starts][np.cumsum(starts) - 1]
            order = np.sort(by_value[starts])
            rank = np.empty(len(n64), np.int64)
            rank[order] = np.arange(len(order))
            ids = self._create_words(n64[order], d_existing[order])
            return ids[rank[first_of]]
        m = len(n64)
        parent = np.arange(m)
        if m > 1:
            D = hamming_matrix(n64, n64)  # (m, m), bounded by the batch size
            D[np.arange(m)[:, None] <= np.arange(m)] = _NONE_DIST  # only earlier descriptors
            j = np.argmin(D, axis=1)
            dj = D[np.arange(m), j]
            D[np.arange(m), j] = _NONE_DIST
            dj2 = np.minimum(D.min(axis=1), d_existing)
            ok = (dj <= self.max_distance) & (dj <= self.nndr * dj2)
            parent = np.where(ok, j, parent)
            while True:  # pointer jumping to the root (an earlier descriptor)
                nxt = parent[parent]
                if np.array_equal(nxt, parent):
                    break
                parent = nxt
        roots = np.nonzero(parent == np.arange(m))[0]
        self._ensure(len(roots))
        ids = np.arange(self._next_id, self._next_id + len(roots), dtype=np.int64)
        self._next_id += len(roots)
        self._desc[ids] = n64[roots]
        self._live[ids] = True
        self._n_live += len(roots)
        self._link(ids, self._keys(n64[roots]))
        root_id = np.full(m, -1, np.int64)
        root_id[roots] = ids
        return root_id[parent]

    def index_node(self, node_id: int, word_ids: np.ndarray) -> None:
        """Add a node to the inverted index from word ids it already has (also used when
        loading a map: no search needed). Dormant words it has become searchable again; ids
        the vocabulary does not hold are indexed as they are (`reload_node` checks them)."""
        node_id = int(node_id)
        if node_id in self._nodes:
            self.remove_node(node_id, drop_orphans=False)
        w = np.asarray(word_ids, np.int64)
        w = w[w >= 0]
        uw, cnt = np.unique(w, return_counts=True)
        self._wake(uw[uw < self._next_id])  # a node in RAM has its words searchable
        self._nodes[node_id] = (uw, cnt)
        self._nfeat[node_id] = int(len(w))
        post = self._postings
        for word, c in zip(uw.tolist(), cnt.tolist()):  # bounded by the node's features
            d = post.get(word)
            if d is None:
                post[word] = {node_id: c}
            else:
                d[node_id] = c

    # -- inverted index queries ---------------------------------------------------------
    def node_words(self, node_id: int) -> tuple[np.ndarray, np.ndarray]:
        return self._nodes[int(node_id)]

    def node_size(self, node_id: int) -> int:
        """Number of (quantized) features of a node: n_i of the tf-idf."""
        return self._nfeat.get(int(node_id), 0)

    def postings(self, word_ids) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """For the distinct given words: (words (U,), document frequency n_w (U,),
        flat postings: index into words (P,), node ids (P,), counts (P,))."""
        uw = np.unique(np.asarray(word_ids, np.int64))
        uw = uw[uw >= 0]
        nodes: list[int] = []
        counts: list[int] = []
        lens: list[int] = []
        post = self._postings
        empty: dict[int, int] = {}
        for w in uw.tolist():  # bounded by the node's features
            d = post.get(w, empty)
            nodes.extend(d.keys())
            counts.extend(d.values())
            lens.append(len(d))
        df = np.asarray(lens, np.int64)
        idx = np.repeat(np.arange(len(uw), dtype=np.int64), df)
        return uw, df, idx, np.asarray(nodes, np.int64), np.asarray(counts, np.int64)

    def tfidf(self, word_ids, nodes: np.ndarray) -> np.ndarray:
        """RTAB-Map's tf-idf likelihood of each of `nodes` (sorted ids) given a keyframe's
        word ids: for every distinct word shared with node i, (n_wi / n_i) · log10(N / n_w)
        (`LoopDetector.raw_likelihood`'s, over this vocabulary's indexed nodes)."""
        s = np.zeros(len(nodes), np.float64)
        uw, df, idx, found, counts = self.postings(word_ids)
        if not len(nodes) or not len(found):
            return s
        pos = np.minimum(np.searchsorted(nodes, found), len(nodes) - 1)
        ok = nodes[pos] == found
        pos, idx, counts = pos[ok], idx[ok], counts[ok]
        n_i = np.array([max(self.node_size(n), 1) for n in nodes.tolist()], np.float64)
        idf = np.log10(max(self.n_nodes, 1) / np.maximum(df[idx], 1))
        np.add.at(s, pos, counts / n_i[pos] * idf)
        return s

    def most_alike(self, word_ids, nodes: np.ndarray, k: int) -> list[tuple[int, float]]:
        """The `k` of `nodes` (sorted ids) with the highest `tfidf` given these word ids, best
        first (ties by id), as (node, score > 0): a relocalization's candidates."""
        scores = self.tfidf(word_ids, nodes)
        best = np.argsort(-scores, kind="stable")[:max(0, k)]
        return [(int(nodes[i]), float(scores[i])) for i in best.tolist() if scores[i] > 0]

    def word_nodes(self, word_id: int) -> dict[int, int]:
        return dict(self._postings.get(int(word_id), {}))

    # -- removal ------------------------------------------------------------------------
    def remove_node(self, node_id: int, drop_orphans: bool = True) -> np.ndarray:
        """Take a node out of the inverted index; words no node references any more are
        removed from the vocabulary. Returns the removed word ids."""
        node_id = int(node_id)
        entry = self._nodes.pop(node_id, None)
        self._nfeat.pop(node_id, None)
        if entry is None:
            return np.zeros(0, np.int64)
        orphans = self._drop_postings(node_id, entry[0])
        if drop_orphans and len(orphans):
            self.remove_words(orphans)
        return orphans if drop_orphans else np.zeros(0, np.int64)

    def _drop_postings(self, node_id: int, words: np.ndarray) -> np.ndarray:
        """Take a node's postings out of its words'; returns the words left without any."""
        orphans = []
        post = self._postings
        for w in words.tolist():  # bounded by the node's features
            d = post.get(w)
            if d is None:
                continue
            d.pop(node_id, None)
            if not d:
                del post[w]
                orphans.append(w)
        return np.asarray(orphans, np.int64)

    def remove_words(self, word_ids) -> None:
        """Delete words for good (live or dormant), from every node that has them."""
        w = np.unique(np.asarray(word_ids, np.int64))
        w = w[(w >= 0) & (w < self._next_id)]
        dormant = w[self._dormant[w]]
        self._dormant[dormant] = False
        self._n_dormant -= len(dormant)
        w = w[self._live[w]]
        self._unlink(w)
        self._live[w] = False
        self._n_live -= len(w)
        for x in w.tolist():
            d = self._postings.pop(x, None)
            if d:
                for n in d:
                    uw, cnt = self._nodes[n]
                    keep = uw != x
                    self._nodes[n] = (uw[keep], cnt[keep])

    # -- working memory ---------------------------------------------------------------
    def unload_node(self, node_id: int) -> tuple[np.ndarray, np.ndarray]:
        """Move a node out of RAM (to long-term memory): it leaves the inverted index, and
        its words no node left in RAM references become dormant (unlinked from the hash
        tables, so `query`/`add` no longer find them; descriptors kept). Nothing is deleted.
        Returns the node's (distinct word ids ascending, counts), what `reload_node` takes
        to restore it (its `node_size` is their sum unless words were removed from under
        it: then pass `n_features=node_size(node_id)` taken before unloading). An unknown
        node gives empty arrays."""
        with self.lock:
            node_id = int(node_id)
            entry = self._nodes.pop(node_id, None)
            self._nfeat.pop(node_id, None)
            if entry is None:
                return np.zeros(0, np.int64), np.zeros(0, np.int64)
            orphans = self._drop_postings(node_id, entry[0])
            orphans = orphans[(orphans < self._next_id)]
            orphans = orphans[self._live[orphans]]
            self._unlink(orphans)
            self._live[orphans] = False
            self._dormant[orphans] = True
            self._n_live -= len(orphans)
            self._n_dormant += len(orphans)
            return entry

    def reload_node(self, node_id: int, word_ids, counts=None, n_features: int | None = None,
                    descriptors=None) -> None:
        """Bring a node back into RAM (retrieved from long-term memory): its postings are
        restored and its dormant words linked back into the hash tables at their place, so
        after `unload_node` + `reload_node` the tables, `postings` (a word's nodes in
        ascending id order), `node_words`, `node_size` and hence the likelihoods are what
        they were. Words already live are just referenced.

        `word_ids`: with `counts=None`, the node's word id per feature as stored
        (`features.word_ids`: repeats are counts, -1 = no word, `node_size` = number of ids
        ≥ 0); else distinct ids with their `counts` (what `unload_node` returned,
        `node_size` = sum of counts). `n_features` overrides `node_size`.

        `descriptors`: for word ids this vocabulary does not hold (`missing_words`), e.g.
        after a restart that loaded only working memory: either the `(ids, W×32 uint8)` pair
        `MapStore.load_words` returns (any superset of the missing ids), or W×32 uint8 for
        the node's distinct ids ≥ 0 in ascending order. Missing ids without descriptors
        raise `MissingWordsError` (nothing changed). A node already in RAM is a ValueError."""
        with self.lock:
            node_id = int(node_id)
            if node_id in self._nodes:
                raise ValueError(f"node {node_id} is in RAM already (unload_node it first)")
            w = np.asarray(word_ids, np.int64).ravel()
            if counts is None:
                w = w[w >= 0]
                uw, cnt = np.unique(w, return_counts=True)
                nf = len(w)
            else:
                c = np.asarray(counts, np.int64).ravel()
                if len(c) != len(w):
                    raise ValueError(f"{len(c)} counts for {len(w)} word ids")
                keep = w >= 0
                w, c = w[keep], c[keep]
                if np.any(c <= 0):
                    raise ValueError("counts must be positive")
                if len(w) > 1 and np.any(w[1:] <= w[:-1]):
                    uw, inv = np.unique(w, return_inverse=True)
                    cnt = np.bincount(inv.ravel(), weights=c, minlength=len(uw)).astype(np.int64)
                else:
                    uw, cnt = w, c
                nf = int(cnt.sum())
            if n_features is not None:
                nf = int(n_features)
            missing = uw[~self._held(uw)]
            if len(missing):
                self._add_held(node_id, missing, uw, descriptors)
            self._wake(uw)
            self._nodes[node_id] = (uw, cnt)
            self._nfeat[node_id] = nf
            post = self._postings
            for word, k in zip(uw.tolist(), cnt.tolist()):  # bounded by the node's features
                d = post.get(word)
                if d is None:
                    post[word] = {node_id: k}
                elif next(reversed(d)) < node_id:  # the usual case: newer nodes hold it
                    d[node_id] = k
                else:  # keep the word's nodes in ascending id order
                    items = sorted([*d.items(), (node_id, k)])
                    d.clear()
                    d.update(items)

    def reload_nodes(self, nodes, descriptors=None) -> None:
        """`reload_node` of many nodes ({node id: word id per feature as stored}, none of
        them in RAM), with one link pass for all their words: the same vocabulary as
        reloading them one by one. `descriptors`: the `(ids, W×32)` pair of
        `MapStore.load_words` for the words this vocabulary does not hold (any superset)."""
        with self.lock:
            items = sorted((int(n), np.asarray(w, np.int64).ravel()) for n, w in nodes.items())
            for n, _ in items:
                if n in self._nodes:
                    raise ValueError(f"node {n} is in RAM already (unload_node it first)")
            if not items:
                return
            allw = np.unique(np.concatenate([w[w >= 0] for _, w in items]))
            missing = allw[~self._held(allw)]
            if len(missing):
                self._add_held(items[0][0], missing, allw, descriptors)
            self._wake(allw)
            for n, w in items:  # postings: ascending node ids as reload_node keeps them
                self.reload_node(n, w)

    def _add_held(self, node_id: int, missing: np.ndarray, uw: np.ndarray, descriptors) -> None:
        """Store the descriptors of words this vocabulary did not hold, as dormant words
        (`_wake` then links them); raises MissingWordsError before changing anything."""
        if descriptors is None:
            raise MissingWordsError(node_id, missing)
        if isinstance(descriptors, tuple):
            ids, desc = descriptors
            ids = np.asarray(ids, np.int64).ravel()
            d64 = as_u64(desc)
            if len(ids) != len(d64):
                raise ValueError(f"{len(d64)} descriptors for {len(ids)} word ids")
        else:
            ids, d64 = uw, as_u64(descriptors)
            if len(d64) != len(uw):
                raise ValueError(f"{len(d64)} descriptors for the node's {len(uw)} distinct word ids "
                                 "(pass the (ids, descriptors) pair of MapStore.load_words instead)")
        order = np.argsort(ids, kind="stable")
        ids, d64 = ids[order], d64[order]
        pos = np.minimum(np.searchsorted(ids, missing), max(len(ids) - 1, 0))
        found = (ids[pos] == missing) if len(ids) else np.zeros(len(missing), bool)
        if not found.all():
            raise MissingWordsError(node_id, missing[~found])
        top = int(missing[-1]) + 1
        if top > self._next_id:  # ids are the map's: never hand them out again
            self._ensure(top - self._next_id)
            self._next_id = top
        self._desc[missing] = d64[pos]
        self._dormant[missing] = True
        self._n_dormant += len(missing)

    # -- persistence --------------------------------------------------------------------
    def state(self) -> dict[str, np.ndarray]:
        """Arrays to persist: the word ids held (W,) int64 ascending, live and dormant (the
        map's words: the database has them all) with their descriptors (W×32 uint8) and
        `dormant` (W,) bool; the postings (word, node, count) and sizes of the nodes in RAM;
        `next_id`; the parameters. `from_state` rebuilds the same vocabulary (dormant words
        stay out of the tables), which then reloads nodes like this one."""
        held = self._live[: self._next_id] | self._dormant[: self._next_id]
        ids = np.nonzero(held)[0].astype(np.int64)
        pw, pn, pc = [], [], []
        for n, (uw, cnt) in self._nodes.items():
            pw.append(uw)
            pn.append(np.full(len(uw), n, np.int64))
            pc.append(cnt)
        def cat(a):
            return np.concatenate(a) if a else np.zeros(0, np.int64)
        nodes = np.fromiter(self._nfeat.keys(), np.int64, len(self._nfeat))
        return {
            "word_ids": ids,
            "descriptors": self._desc[ids].view(np.uint8).reshape(-1, 32).copy(),
            "dormant": self._dormant[ids],
            "post_word": cat(pw), "post_node": cat(pn), "post_count": cat(pc),
            "node_ids": nodes,
            "node_nfeat": np.fromiter(self._nfeat.values(), np.int64, len(self._nfeat)),
            "next_id": np.array([self._next_id], np.int64),
            "params": np.array([self.nndr, self.max_distance, self.n_tables, self.key_bits,
                                self.max_chain, self.seed], np.float64),
        }

    @classmethod
    def from_state(cls, st: dict[str, np.ndarray], **overrides) -> "Vocabulary":
        """Rebuild from `state()` arrays; the hash tables are rebuilt in one vectorized
        O(W) pass (no search). Words flagged `dormant` (optional; e.g. a map's store state has
        none) are kept unlinked, unless a node of the postings references them."""
        p = st.get("params")
        kw: dict[str, Any] = {}
        if p is not None:
            kw = dict(nndr=float(p[0]), max_distance=int(p[1]), n_tables=int(p[2]),
                      key_bits=int(p[3]), max_chain=int(p[4]), seed=int(p[5]))
        kw.update(overrides)
        ids = np.asarray(st["word_ids"], np.int64)
        next_id = int(st["next_id"][0]) if "next_id" in st else (int(ids.max()) + 1 if len(ids) else 0)
        kw.setdefault("capacity", max(1 << 21, 2 * next_id))
        v = cls(**kw)
        v._ensure(next_id)
        v._next_id = next_id
        d64 = as_u64(st["descriptors"])
        dormant = np.asarray(st.get("dormant", np.zeros(len(ids), bool)), bool)
        pw = np.asarray(st.get("post_word", np.zeros(0)), np.int64)
        if dormant.any():  # a word a node in RAM has is searchable
            dormant = dormant & ~np.isin(ids, pw)
        v._desc[ids] = d64
        if len(ids) > 1 and np.any(ids[1:] <= ids[:-1]):
            order = np.argsort(ids, kind="stable")
            ids, d64, dormant = ids[order], d64[order], dormant[order]
        v._live[ids[~dormant]] = True
        v._dormant[ids[dormant]] = True
        v._n_dormant = int(dormant.sum())
        v._n_live = len(ids) - v._n_dormant
        if v._n_dormant:
            v._link_all(ids[~dormant], d64[~dormant])
        else:
            v._link_all(ids, d64)
        pn = np.asarray(st.get("post_node", np.zeros(0)), np.int64)
        pc = np.asarray(st.get("post_count", np.zeros(0)), np.int64)
        if len(pn):
            same = pn[1:] == pn[:-1]
            if not (np.all(pn[1:] >= pn[:-1]) and np.all(pw[1:][same] > pw[:-1][same])):
                order = np.lexsort((pw, pn))  # by node, then word (as state() and the store give them)
                pw, pn, pc = pw[order], pn[order], pc[order]
            a, b = _runs(pn)
            for nid, i, j in zip(pn[a].tolist(), a.tolist(), b.tolist()):  # per node
                v._nodes[nid] = (pw[i:j], pc[i:j])
            # word -> {node: count}, nodes ascending (the order they were added in): one dict
            # per word from the word-sorted postings, literals for the (many) words of one or
            # two nodes; no per-posting dict updates.
            order = np.argsort((pw << 32) | pn)  # (word, node) pairs are distinct
            ws, ns, cs = pw[order], pn[order].tolist(), pc[order].tolist()
            a, b = _runs(ws)
            df = b - a
            post = dict(zip(ws[a[df == 1]].tolist(), [{ns[i]: cs[i]} for i in a[df == 1].tolist()]))
            post.update(zip(ws[a[df == 2]].tolist(),
                            [{ns[i]: cs[i], ns[i + 1]: cs[i + 1]} for i in a[df == 2].tolist()]))
            for w, i, j in zip(ws[a[df > 2]].tolist(), a[df > 2].tolist(), b[df > 2].tolist()):
                post[w] = dict(zip(ns[i:j], cs[i:j]))
            v._postings = post
        for n, f in zip(np.asarray(st.get("node_ids", []), np.int64).tolist(),
                        np.asarray(st.get("node_nfeat", []), np.int64).tolist()):
            v._nfeat[n] = f
            v._nodes.setdefault(n, (np.zeros(0, np.int64), np.zeros(0, np.int64)))
        return v

    @classmethod
    def from_store(cls, store: WordStore, **params) -> Vocabulary:
        """The vocabulary of a stored map (`MapStore.load_vocabulary_state`: its words and
        the word ids of its nodes), hash tables and inverted index rebuilt without any
        search; empty for a map without words. `params` are the constructor's (the hashing
        parameters are not stored: the tables are rebuilt with whatever is given)."""
        return cls.from_state(store.load_vocabulary_state(), **params)

    @classmethod
    def for_store(cls, store: WordStore, words: bool = True, **params) -> Vocabulary:
        """The one vocabulary of a map for this process: loaded with `from_store` by the
        first caller (with `words=False`: `empty_for` instead, the caller reloads the nodes
        it wants in RAM), the same object for every later one while that `store` object
        lives (their `words` and `params` are then ignored). Hold its `lock` around
        anything that reads it while another thread may add to it."""
        with _SHARED_LOCK:
            v = _SHARED.get(store)
            if v is None:
                v = cls.from_store(store, **params) if words else cls.empty_for(store, **params)
                _SHARED[store] = v
            return v

    @classmethod
    def of_nodes(cls, store: WordStore, nodes, **params) -> Vocabulary:
        """A vocabulary of some of a stored map's nodes only (e.g. the older maps' a new
        session relocalizes against): their postings and the words they hold, nothing else
        (`load_vocabulary_state` filtered), so that a query finds their words and no other."""
        st = store.load_vocabulary_state()
        keep = np.isin(st["post_node"], np.asarray(list(nodes), np.int64))
        words = np.unique(st["post_word"][keep])
        held = np.isin(st["word_ids"], words)
        mine = np.isin(st["node_ids"], np.asarray(list(nodes), np.int64))
        return cls.from_state({
            "word_ids": st["word_ids"][held], "descriptors": st["descriptors"][held],
            "post_word": st["post_word"][keep], "post_node": st["post_node"][keep],
            "post_count": st["post_count"][keep], "node_ids": st["node_ids"][mine],
            "node_nfeat": st["node_nfeat"][mine], "next_id": st["next_id"]}, **params)

    @classmethod
    def empty_for(cls, store: WordStore, **params) -> Vocabulary:
        """A vocabulary of a stored map that holds none of its words yet (RTAB-Map's start-up
        loads only working memory's): new words get ids after the map's
        (`MapStore.next_word_id`); nodes come in with `reload_node(s)` and the descriptors
        of their words from `MapStore.load_words`."""
        return cls.from_state({"word_ids": np.zeros(0, np.int64), "descriptors": np.zeros((0, 32), np.uint8),
                               "next_id": np.array([store.next_word_id()], np.int64)}, **params)


_SHARED: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # store -> its Vocabulary
_SHARED_LOCK = threading.Lock()
