"""Vocabulary persistence bench: the cost of saving each keyframe's word ids and new words
to the map (`MapStore.save_node_words`, one transaction) as the vocabulary grows, and the
time to load it back from a reopened map (`MapStore.load_vocabulary_state` + `from_state`)
at 100k, 300k and 1M words.

Nodes as in bench_vocabulary.py: 500 descriptors each, half uniformly random (new words),
half clustered around fixed centres with bit noise (votes). Every node is first stored
with `add_keyframe` (not timed here: bench_storage.py), then quantized and saved. Loads
open a second `MapStore` on the file while it grows (a reopened map; the file is in the OS
page cache) and check that the loaded vocabulary answers queries like the live one.

    python bench/bench_vocabulary_load.py              # up to 300k words
    python bench/bench_vocabulary_load.py --max 1000000

Measured (2 cores shared with other jobs, load average ~10, so absolute times are
pessimistic): save_node_words p50 1.0 ms per keyframe at every size (~330-410 new words
per node; p99 9-12 ms, max 20 ms, scheduling noise: add_keyframe's own p99 is 5 ms against
a 0.27 ms median); load 0.43 s at 100k words (read 0.09 + build 0.34), 1.45 s at 300k,
5.8 s at 1M words / 2604 nodes (read 1.1 + build 4.7; 136 MB file).
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from mnemoslam.client.kernel.frames import Calibration, PinholeCamera  # noqa: E402
from mnemoslam.service.memory.vocabulary import Vocabulary  # noqa: E402
from mnemoslam.storage import KeyframeRecord, MapStore  # noqa: E402

CAL = Calibration(PinholeCamera(525.0, 525.0, 319.5, 239.5, 640, 480), None, 1000.0)


def _noisy(rng, desc, p):
    bits = np.unpackbits(desc, axis=1)
    bits ^= (rng.random(bits.shape) < p).astype(np.uint8)
    return np.packbits(bits, axis=1)


def _load(path: Path, live: Vocabulary, rng) -> tuple[float, float, int]:
    """(load_vocabulary_state s, from_state s, words) from a fresh connection."""
    with MapStore(path, create=False) as store:
        t0 = time.perf_counter()
        st = store.load_vocabulary_state()
        t1 = time.perf_counter()
        v = Vocabulary.from_state(st)
        t2 = time.perf_counter()
    probe = _noisy(rng, live.descriptors(rng.choice(st["word_ids"], 1000, replace=False)), 0.03)
    assert len(v) == len(live) and v.n_nodes == live.n_nodes
    assert np.array_equal(v.query(probe), live.query(probe))
    return t1 - t0, t2 - t1, len(v)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--max", type=int, default=300_000, help="vocabulary size to grow to (words)")
    ap.add_argument("--per-node", type=int, default=500)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--dir", type=Path, default=None, help="where the map file goes (default: a temporary folder)")
    a = ap.parse_args(argv)
    rng = np.random.default_rng(a.seed)
    checkpoints = [c for c in (100_000, 300_000, 1_000_000) if c <= a.max] or [a.max]
    tmp = tempfile.TemporaryDirectory(prefix="mnemoslam-bench-voc-") if a.dir is None else None
    path = Path(tmp.name if tmp else a.dir) / "map.db"
    for p in (path, path.with_name("map.db-wal"), path.with_name("map.db-shm")):
        p.unlink(missing_ok=True)
    n = a.per_node
    zeros2, zeros3 = np.zeros((n, 2), np.float32), np.zeros((n, 3), np.float32)
    centres = rng.integers(0, 256, (20_000, 32), dtype=np.uint8)
    v = Vocabulary(capacity=max(1 << 21, 2 * a.max))
    saves: list[tuple[int, int, float, float, float]] = []  # (words before, new, add s, save s, add_keyframe s)
    loads: list[tuple[int, int, float, float, int]] = []  # (words, nodes, read s, build s, db bytes)
    with MapStore(path) as store:
        sid = store.begin_session("bench", CAL)
        k = 0
        t_start = time.perf_counter()
        for c in checkpoints:
            while len(v) < c:
                d = rng.integers(0, 256, (n, 32), dtype=np.uint8)
                d[: n // 2] = _noisy(rng, centres[rng.integers(0, len(centres), n // 2)], 0.06)
                tk = time.perf_counter()
                nid = store.add_keyframe(KeyframeRecord(sid, float(k), np.eye(4), zeros2, d, zeros3))
                before = len(v)
                t0 = time.perf_counter()
                words = v.add(nid, d)
                t1 = time.perf_counter()
                new = v.last_new_words
                store.save_node_words(nid, words, new, v.descriptors(new))
                t2 = time.perf_counter()
                saves.append((before, len(new), t1 - t0, t2 - t1, t0 - tk))
                k += 1
            read_s, build_s, words = _load(path, v, rng)
            loads.append((words, v.n_nodes, read_s, build_s, sum(store.file_bytes())))
        grow_s = time.perf_counter() - t_start
    if tmp:
        tmp.cleanup()

    arr = np.array(saves)
    print(f"grew to {len(v)} words over {len(saves)} nodes ({n} features each) in {grow_s:.1f} s")
    s = arr[:, 3] * 1e3
    print(f"save_node_words over all nodes: p50 {np.median(s):.2f} ms, p99 {np.percentile(s, 99):.2f} ms, "
          f"max {s.max():.1f} ms; add_keyframe p99 {np.percentile(arr[:, 4], 99) * 1e3:.2f} ms")
    print("save cost per keyframe (save_node_words: word ids + new words, one transaction):")
    print(f"{'words':>9} {'nodes':>6} {'new/node':>9} {'save p50':>9} {'p99':>8} {'max':>8} {'add() p50':>10} "
          f"{'add_keyframe p50':>17}")
    lo = 0
    for c in checkpoints:
        sel = (arr[:, 0] >= lo) & (arr[:, 0] < c)
        lo = c
        if not sel.any():
            continue
        s = arr[sel, 3] * 1e3
        print(f"{c:>9} {int(sel.sum()):>6} {np.median(arr[sel, 1]):>9.0f} {np.median(s):>6.2f} ms "
              f"{np.percentile(s, 99):>5.2f} ms {s.max():>5.2f} ms {np.median(arr[sel, 2]) * 1e3:>7.1f} ms "
              f"{np.median(arr[sel, 4]) * 1e3:>14.2f} ms")
    print("load from a reopened map (load_vocabulary_state: SQL + numpy; from_state: hash tables + postings):")
    print(f"{'words':>9} {'nodes':>6} {'read':>9} {'build':>9} {'total':>9} {'file':>8}")
    for words, nodes, r, b, size in loads:
        print(f"{words:>9} {nodes:>6} {r * 1e3:>6.0f} ms {b * 1e3:>6.0f} ms {(r + b) * 1e3:>6.0f} ms "
              f"{size / 1e6:>5.0f} MB")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
