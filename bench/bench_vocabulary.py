"""Vocabulary growth bench: per-node add+query time as the vocabulary grows from 10k to 1M
words (500 descriptors per node, half uniformly random, half clustered around a fixed set of
centres with bit noise, so that both new words and votes happen). It must grow
sub-linearly and show no rebuild spikes (introlab/rtabmap#982).

    python bench/bench_vocabulary.py            # up to 300k words
    python bench/bench_vocabulary.py --max 1000000
    python bench/bench_vocabulary.py --wm       # unload/reload of nodes at 100k and 1M words

--wm (working memory): a vocabulary of W words is built with `from_state` (half random, half
around centres, as above; nodes of 1000 distinct words: 500 they created, 500 older ones they
voted for), then random nodes are moved to LTM (`unload_node`: their words no other node has
go dormant, unlinked) and back (`reload_node`: relinked at their place in the chains).
Measured (2 shared cores, load ~3): 100k words: unload 2.3 ms, reload 3.4 ms median
(~300 words made dormant per node); 1M words / 2000 nodes: unload 2.3 ms, reload 6.1 ms
(max 5 / 11 ms), the same with a quarter of the nodes in LTM (142k dormant words).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from mnemoslam.service.memory.vocabulary import Vocabulary  # noqa: E402


def _noisy(rng, desc, p):
    bits = np.unpackbits(desc, axis=1)
    bits ^= (rng.random(bits.shape) < p).astype(np.uint8)
    return np.packbits(bits, axis=1)


def wm_bench(sizes, rng, reps: int = 30) -> None:
    own, votes = 500, 500  # distinct words per node: created by it, older ones it voted for
    print(f"unload/reload of a {own + votes}-word node ({reps} random nodes per size; median, max):")
    for n_words in sizes:
        centres = rng.integers(0, 256, (20_000, 32), dtype=np.uint8)
        desc = rng.integers(0, 256, (n_words, 32), dtype=np.uint8)
        half = rng.random(n_words) < 0.5
        desc[half] = _noisy(rng, centres[rng.integers(0, len(centres), int(half.sum()))], 0.06)
        n_nodes = n_words // own
        pw, pn = [], []
        for i in range(n_nodes):
            older = rng.choice(i * own, min(votes, i * own), replace=False) if i else np.zeros(0, np.int64)
            w = np.unique(np.r_[np.arange(i * own, (i + 1) * own), older])
            pw.append(w)
            pn.append(np.full(len(w), i, np.int64))
        pw, pn = np.concatenate(pw), np.concatenate(pn)
        st = {"word_ids": np.arange(n_words, dtype=np.int64), "descriptors": desc, "post_word": pw,
              "post_node": pn, "post_count": np.ones(len(pw), np.int64),
              "node_ids": np.arange(n_nodes, dtype=np.int64), "node_nfeat": np.bincount(pn, minlength=n_nodes)}
        t0 = time.perf_counter()
        v = Vocabulary.from_state(st)
        build = time.perf_counter() - t0
        probe = _noisy(rng, desc[rng.choice(n_words, 1000, replace=False)], 0.03)
        before = v.query(probe)
        tu, tr, dormant = [], [], []
        for node in rng.choice(n_nodes, reps, replace=False).tolist():
            t0 = time.perf_counter()
            w, c = v.unload_node(node)
            t1 = time.perf_counter()
            dormant.append(v.dormant)
            v.reload_node(node, w, c)
            t2 = time.perf_counter()
            tu.append(t1 - t0)
            tr.append(t2 - t1)
        assert v.dormant == 0 and np.array_equal(v.query(probe), before)
        # The same with a quarter of the map in LTM (its words dormant) around the timed ones.
        ltm = rng.choice(n_nodes, n_nodes // 4, replace=False)
        t0 = time.perf_counter()
        out = {n: v.unload_node(n) for n in ltm.tolist()}
        bulk = time.perf_counter() - t0
        searchable, n_dormant = len(v), v.dormant
        tu2, tr2 = [], []
        for node in rng.choice(sorted(set(range(n_nodes)) - set(out)), reps, replace=False).tolist():
            t0 = time.perf_counter()
            w, c = v.unload_node(node)
            t1 = time.perf_counter()
            v.reload_node(node, w, c)
            t2 = time.perf_counter()
            tu2.append(t1 - t0)
            tr2.append(t2 - t1)
        t0 = time.perf_counter()
        for n, (w, c) in out.items():
            v.reload_node(n, w, c)
        bulk_back = time.perf_counter() - t0
        assert v.dormant == 0 and np.array_equal(v.query(probe), before)
        def ms(a):
            return f"{1e3 * np.median(a):5.1f} ms (max {1e3 * max(a):5.1f})"
        print(f"  {n_words:>8} words, {n_nodes} nodes (from_state {build:.1f} s): unload {ms(tu)}, "
              f"reload {ms(tr)}; words made dormant per node: median {int(np.median(dormant))}")
        print(f"  {'':>8} with {len(out)} nodes in LTM ({searchable} searchable, {n_dormant} dormant): "
              f"unload {ms(tu2)}, reload {ms(tr2)}; all {len(out)} out {bulk:.1f} s, back {bulk_back:.1f} s")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--max", type=int, default=300_000, help="vocabulary size to grow to (words)")
    ap.add_argument("--per-node", type=int, default=500)
    ap.add_argument("--window", type=int, default=40, help="nodes timed around each checkpoint")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--wm", action="store_true", help="only the working-memory section (unload/reload)")
    ap.add_argument("--wm-sizes", default="100000,1000000", help="vocabulary sizes of --wm (words)")
    a = ap.parse_args(argv)
    rng = np.random.default_rng(a.seed)
    if a.wm:
        wm_bench([int(x) for x in a.wm_sizes.split(",")], rng)
        return 0
    checkpoints = [c for c in (10_000, 100_000, 300_000, 1_000_000) if c <= a.max]
    v = Vocabulary(capacity=max(1 << 21, 2 * a.max))
    centres = rng.integers(0, 256, (20_000, 32), dtype=np.uint8)
    half = a.per_node // 2
    times: list[tuple[int, float, float, float]] = []  # (words before, add s, query s, candidates/query)
    node = 0
    t_start = time.perf_counter()
    while len(v) < a.max:
        d = rng.integers(0, 256, (a.per_node, 32), dtype=np.uint8)
        d[:half] = _noisy(rng, centres[rng.integers(0, len(centres), half)], 0.06)
        w_before = len(v)
        t0 = time.perf_counter()
        v.add(node, d)
        t1 = time.perf_counter()
        v.query(_noisy(rng, d, 0.04))  # the likelihood-side lookup of a revisit
        t2 = time.perf_counter()
        times.append((w_before, t1 - t0, t2 - t1, v.last_candidates / max(v.last_queries, 1)))
        node += 1
    total = time.perf_counter() - t_start
    arr = np.array(times)
    print(f"grew to {len(v)} words over {node} nodes in {total:.1f} s")
    print(f"{'words':>9} {'nodes':>6} {'add+query p50':>14} {'p99':>9} {'max':>9} {'add p50':>9} {'query p50':>10} "
          f"{'cand/query':>11}")
    for c in checkpoints:
        # the nodes added while the vocabulary was in [c/2, c]: (lower edge at 10k: [0, 10k])
        lo = c // 2 if c > 10_000 else 0
        sel = (arr[:, 0] >= lo) & (arr[:, 0] < c)
        if not sel.any():
            continue
        tot = (arr[sel, 1] + arr[sel, 2]) * 1e3
        print(f"{c:>9} {int(sel.sum()):>6} {np.percentile(tot, 50):>11.1f} ms {np.percentile(tot, 99):>6.1f} ms "
              f"{tot.max():>6.1f} ms {np.median(arr[sel, 1]) * 1e3:>6.1f} ms {np.median(arr[sel, 2]) * 1e3:>7.1f} ms "
              f"{np.median(arr[sel, 3]):>11.0f}")
    tot = (arr[:, 1] + arr[:, 2]) * 1e3
    worst = np.argsort(-tot)[:5]
    print("slowest nodes: " + ", ".join(f"{tot[i]:.0f} ms at {int(arr[i, 0])} words" for i in worst))
    print(f"all nodes: p50 {np.percentile(tot, 50):.1f} ms, p99 {np.percentile(tot, 99):.1f} ms, "
          f"max {tot.max():.1f} ms (max/p50 {tot.max() / np.percentile(tot, 50):.1f})")
    t0 = time.perf_counter()
    st = v.state()
    t1 = time.perf_counter()
    v2 = Vocabulary.from_state(st)
    t2 = time.perf_counter()
    probe = v.descriptors(st["word_ids"][:500])
    assert np.array_equal(v2.query(probe), v.query(probe))
    print(f"persistence at {len(v)} words / {v.n_nodes} nodes: state() {1e3 * (t1 - t0):.0f} ms, "
          f"from_state() {1e3 * (t2 - t1):.0f} ms (hash tables rebuilt vectorized; postings dicts in Python)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
