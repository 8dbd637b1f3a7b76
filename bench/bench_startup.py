"""Start-up on a big map (issue 11): the time and RAM to open a map of N nodes for a new
session the way `serve` / `run --db` does (`MapStore` + `build_pipeline`, map update inline),
with `memory.max_wm_nodes` set (RTAB-Map's loadLastNodes: only WM is loaded) and, for
comparison in the same process, the old start-up that loaded the whole vocabulary with every
node's postings (`Vocabulary.from_store`, what every Mapper did before).

The map is built once with direct batched inserts (no images, no search) and cached in
--out: N nodes along a path of loops, ~500 features each (random keypoints, points and
descriptors; word ids drawn from the words of the nodes around it, so the vocabulary grows
to --words), odometry links and a loop link every 50 nodes, one ended session.

    python bench/bench_startup.py [--nodes 100000] [--words 300000] [--max-wm 100] [--out out/bench_startup]

Prints seconds and RSS (current, this process: the new start-up is measured first) of each.

Measured 2026-11-25 (2 cores shared with other jobs; the 2.8 GB file in the page cache):
100,000 nodes, 300,000 words, max_wm_nodes=100: new 0.57-0.84 s, RSS +33-63 MB (WM 100,
LTM 99,900, 1,383 words, 100 graph nodes; the ids-only queries of the nodes and links take
~0.4 s of it); old 48.6 s, RSS +3.2 GB (every node's postings in RAM): 85x faster.
"""
from __future__ import annotations

import argparse
import gc
import json
import sqlite3
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mnemoslam.client.kernel.frames import Calibration, PinholeCamera  # noqa: E402
from mnemoslam.service.builder import build_pipeline  # noqa: E402
from mnemoslam.service.config import load_config  # noqa: E402
from mnemoslam.service.memory.vocabulary import Vocabulary  # noqa: E402
from mnemoslam.storage import LinkType, MapStore  # noqa: E402

CAL = Calibration(PinholeCamera(525.0, 525.0, 319.5, 239.5, 640, 480), None, 1000.0)
FEATURES = 500
CHUNK = 2000


def rss_mb() -> float:
    for line in open("/proc/self/status"):
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def build(path: Path, n: int, n_words: int, seed: int = 0) -> None:
    """The cached bench map (see the module docstring)."""
    rng = np.random.default_rng(seed)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".building")
    for p in (tmp, Path(f"{tmp}-wal"), Path(f"{tmp}-shm")):
        p.unlink(missing_ok=True)
    with MapStore(tmp) as store:
        sid = store.begin_session("bench", CAL, {})
    c = sqlite3.connect(tmp)
    c.execute("PRAGMA synchronous = OFF")
    info = np.diag([1e4] * 6).astype("<f8").tobytes()
    t0 = time.perf_counter()
    with c:
        for a in range(0, n_words, 1 << 16):
            d = rng.integers(0, 256, (min(1 << 16, n_words - a), 32), np.uint8)
            c.executemany("INSERT INTO words (id, descriptor, time_enter) VALUES (?, ?, 0)",
                          ((a + i, d[i].tobytes()) for i in range(len(d))))
        c.execute("INSERT OR REPLACE INTO admin (key, value) VALUES ('next_word_id', ?)", (str(n_words),))
    per_node = n_words / n
    for a in range(0, n, CHUNK):
        m = min(CHUNK, n - a)
        i = np.arange(a, a + m)
        t = i * 0.05  # a path of 20 m loops, slowly drifting up a floor
        x, y, z = 10 * np.cos(t / 10 * 2 * np.pi / 2), 10 * np.sin(t / 10 * 2 * np.pi / 2), 0.001 * i
        kp = rng.random((m, FEATURES, 2), np.float32) * 600
        desc = rng.integers(0, 256, (m, FEATURES, 32), np.uint8)
        pts = rng.random((m, FEATURES, 3), np.float32) * 4
        hi = np.maximum(((i + 1) * per_node).astype(np.int64), 1)
        lo = np.maximum(hi - int(200 * per_node) - 500, 0)
        words = (lo[:, None] + (rng.random((m, FEATURES)) * (hi - lo)[:, None]).astype(np.int64)).astype("<i4")
        words[rng.random((m, FEATURES)) < 0.1] = -1
        nodes, feats, links = [], [], []
        for k in range(m):
            nid = a + k + 1
            pose = np.eye(4)
            pose[:3, 3] = (x[k], y[k], z[k])
            nodes.append((nid, sid, "bench", float(t[k]), pose.astype("<f8").tobytes(), x[k], y[k], z[k], 0, 0.0))
            feats.append((nid, FEATURES, kp[k].tobytes(), desc[k].tobytes(), pts[k].tobytes(), words[k].tobytes()))
            if nid > 1:
                links.append((nid - 1, nid, int(LinkType.NEIGHBOR), np.eye(4).astype("<f8").tobytes(), info))
            if nid % 50 == 0 and nid > 400:
                links.append((int(rng.integers(1, nid - 200)), nid, int(LinkType.GLOBAL_CLOSURE),
                              np.eye(4).astype("<f8").tobytes(), info))
        with c:
            c.executemany("INSERT INTO nodes (id, session_id, robot, stamp, pose, x, y, z, weight, time_enter) "
                          "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)", nodes)
            c.executemany("INSERT INTO features (node_id, count, keypoints, descriptors, points, word_ids) "
                          "VALUES (?, ?, ?, ?, ?, ?)", feats)
            c.executemany("INSERT INTO links (from_id, to_id, type, transform, information) VALUES (?, ?, ?, ?, ?)",
                          links)
        print(f"\rbuilding {path.name}: {a + m}/{n} nodes, {time.perf_counter() - t0:.0f} s", end="", file=sys.stderr)
    with c:
        c.execute("UPDATE sessions SET ended_at = ?, end_reason = 'stopped' WHERE id = ?", (time.time(), sid))
    c.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    c.close()
    print(file=sys.stderr)
    tmp.rename(path)


def open_new(path: Path, max_wm: int) -> tuple[float, float, dict]:
    """A new session as `serve` opens it: (seconds, RSS MB after, what is in RAM)."""
    cfg = load_config(None, {"memory": {"max_wm_nodes": max_wm}})
    t0 = time.perf_counter()
    store = MapStore(path)
    pipeline = build_pipeline(store, "bench-2", CAL, cfg)
    seconds = time.perf_counter() - t0
    rss = rss_mb()
    m = pipeline.mapper
    sizes = m.memory.tiers.sizes()
    out = {"wm": sizes.wm, "ltm": sizes.ltm, "words": len(m.vocabulary), "graph": len(m.graph)}
    pipeline.close()
    store.close()
    return seconds, rss, out


def open_old(path: Path) -> tuple[float, float, dict]:
    """What every Mapper did before on a reopened map: the whole vocabulary with every node's
    postings (the rest of its construction was negligible)."""
    t0 = time.perf_counter()
    store = MapStore(path)
    v = Vocabulary.from_store(store)
    seconds = time.perf_counter() - t0
    rss = rss_mb()
    out = {"words": len(v), "indexed_nodes": v.n_nodes}
    store.close()
    return seconds, rss, out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--nodes", type=int, default=100_000)
    ap.add_argument("--words", type=int, default=300_000)
    ap.add_argument("--max-wm", type=int, default=100)
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "bench_startup")
    ap.add_argument("--skip-old", action="store_true", help="only the new start-up")
    a = ap.parse_args(argv)
    path = a.out / f"map_{a.nodes}_{a.words}.db"
    if not path.exists():
        build(path, a.nodes, a.words)
    size = path.stat().st_size / 2**20
    print(f"map {path} ({size:.0f} MB): {a.nodes} nodes x {FEATURES} features, {a.words} words")
    base = rss_mb()
    print(f"RSS before: {base:.0f} MB")
    s_new, r_new, what = open_new(path, a.max_wm)
    print(f"new start-up (memory.max_wm_nodes={a.max_wm}): {s_new:.2f} s, RSS {r_new:.0f} MB "
          f"(+{r_new - base:.0f}); {json.dumps(what)}")
    if not a.skip_old:
        gc.collect()
        base2 = rss_mb()
        s_old, r_old, what = open_old(path)
        print(f"old start-up (whole vocabulary): {s_old:.2f} s, RSS {r_old:.0f} MB (+{r_old - base2:.0f}); "
              f"{json.dumps(what)}")
        print(f"ratio old/new: {s_old / s_new:.1f}x time, {(r_old - base2) / max(r_new - base, 1):.1f}x RSS growth")
    return 0 if s_new < 2.0 else 1


if __name__ == "__main__":
    sys.exit(main())
