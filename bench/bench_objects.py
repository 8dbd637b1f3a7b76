"""Nearest-object queries at map scale: the query layer alone and over HTTP (issue 14: p99 ≤ 5 ms
at 100k objects with 50 concurrent clients).

    .venv/bin/python bench/bench_objects.py [--objects 100000] [--nodes 2000] [--clients 50]
                                            [--requests 200] [--db FILE]

1. Writes a real SQLite map: `--nodes` keyframes on a random walk over ~100 × 100 m (small
   feature sets, odometry links) and `--objects` objects through `MapStore.save_objects`,
   anchored to random keyframes within 3 m of them, labels drawn from the 32 ADE20K classes
   (so ~3k objects per label; `--one-label` puts all of them under "door": the worst case).
2. The query layer (`ObjectIndex`): `object_arrays()` and index build time, then nearest
   queries (random label and point): p50/p99 per call from one thread, and from `--clients`
   threads at once (closed loop: each thread asks again as soon as it has its answer).
3. Over HTTP: the REST app (`service.api.create_app`) under uvicorn in its own process (a
   service stand-in holding the store: no Zenoh, no tracking), `--clients` client threads in
   this process, each on its own keep-alive connection, closed loop, GET
   /objects/nearest?label=&x=&y=&z=: p50/p99 latency as the client sees it, requests/s, and
   the app's own time per request (from the X-App-Ms header a thin ASGI wrapper adds in the
   bench server): what a request costs once it is served, without queueing behind the other
   49. Also one client alone (no queueing), and the clients paced at `--rate` Hz each (a
   planner asking a few times a second: open loop, latency without self-made queues).

Prints the machine's load average before and after: on a shared 2-core machine the figures
move with it.
"""
from __future__ import annotations

import argparse
import http.client
import json
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

ADE20K32 = ["other", "wall", "floor", "ceiling", "bed", "window", "cabinet", "person", "table", "curtain", "chair",
            "painting", "sofa", "shelf", "mirror", "door", "rug", "lamp", "bathtub", "cushion", "counter",
            "sink", "fridge", "stairs", "toilet", "tv", "plant", "desk", "bookcase", "pillow", "stove", "armchair"]


def pct(a, q) -> float:
    return float(np.percentile(np.asarray(a) * 1e3, q))


def build_map(path: Path, n_nodes: int, n_objects: int, one_label: bool, seed: int = 0) -> None:
    from mnemoslam.client.kernel.frames import Calibration, PinholeCamera
    from mnemoslam.storage import KeyframeRecord, LinkType, MapStore
    from mnemoslam.storage.records import ObjectRecord

    rng = np.random.default_rng(seed)
    cal = Calibration(PinholeCamera(525.0, 525.0, 319.5, 239.5, 640, 480))
    t = time.perf_counter()
    with MapStore(path) as store:
        sid = store.begin_session("bench", cal)
        pos = np.zeros(3)
        ids, poses = [], []
        k = 8
        for i in range(n_nodes):
            step = rng.normal(0, 1.0, 3) * (1, 1, 0.05)
            pos = np.clip(pos + step, -50, 50)
            P = np.eye(4)
            P[:3, 3] = pos
            ids.append(store.add_keyframe(KeyframeRecord(
                session_id=sid, stamp=float(i), pose=P, keypoints=(rng.random((k, 2)) * 640).astype(np.float32),
                descriptors=rng.integers(0, 256, (k, 32), dtype=np.uint8),
                points=rng.normal(size=(k, 3)).astype(np.float32))))
            poses.append(P)
            if i:
                store.add_link(ids[-2], ids[-1], LinkType.NEIGHBOR, np.linalg.inv(poses[-2]) @ P)
        t_nodes = time.perf_counter() - t
        t = time.perf_counter()
        hist = np.full(32, 1 / 32, np.float32)
        batch = 10_000
        for start in range(0, n_objects, batch):
            m = min(batch, n_objects - start)
            anchor = rng.integers(0, n_nodes, m)
            cls = np.full(m, 15) if one_label else rng.integers(0, 32, m)
            centroid = rng.uniform(-3, 3, (m, 3))
            extent = rng.uniform(0.2, 2.0, (m, 3))
            store.save_objects(ObjectRecord(None, ids[a], int(c), ADE20K32[c], 0.8, hist, centroid[j], extent[j],
                                            int(rng.integers(1, 30)), np.array([ids[a]], np.int64))
                               for j, (a, c) in enumerate(zip(anchor, cls)))
        t_objects = time.perf_counter() - t
        print(f"map: {n_nodes} keyframes in {t_nodes:.1f} s, {store.count_objects()} objects through save_objects "
              f"in {t_objects:.1f} s; {path.stat().st_size / 2**20:.0f} MB")


def query_layer(path: Path, clients: int, per_client: int, labels: list[str]) -> None:
    from mnemoslam.service.semantics.queries import ObjectIndex
    from mnemoslam.storage import MapStore

    with MapStore(path, create=False) as store:
        t = time.perf_counter()
        arrays = store.object_arrays()
        t_arrays = time.perf_counter() - t
        index = ObjectIndex(store)
        t = time.perf_counter()
        index.refresh()
        t_build = time.perf_counter() - t
        print(f"query layer: object_arrays {t_arrays * 1e3:.0f} ms ({len(arrays['id'])} objects), "
              f"index rebuild (object_arrays + grouping) {t_build * 1e3:.0f} ms")
        rng = np.random.default_rng(1)
        qs = rng.uniform(-55, 55, (20_000, 3))
        lab = [labels[i] for i in rng.integers(0, len(labels), len(qs))]
        lat = np.empty(len(qs))
        for i, (q, label) in enumerate(zip(qs, lab)):
            t = time.perf_counter()
            index.nearest(label, q)
            lat[i] = time.perf_counter() - t
        print(f"  1 thread:  nearest p50 {pct(lat, 50):.3f} ms, p99 {pct(lat, 99):.3f} ms ({len(lat)} queries)")
        nodes = store.node_ids()
        at = nodes[rng.integers(0, len(nodes), len(qs))]
        for i, (q, label) in enumerate(zip(qs, lab)):  # a robot's query: only objects links join to its keyframe
            t = time.perf_counter()
            index.nearest(label, q, joined_to=int(at[i]))
            lat[i] = time.perf_counter() - t
        print(f"  1 thread:  nearest to a robot's keyframe (joined_to) p50 {pct(lat, 50):.3f} ms, "
              f"p99 {pct(lat, 99):.3f} ms")
        lats: list[np.ndarray] = []
        barrier = threading.Barrier(clients + 1)

        def worker(seed):
            r = np.random.default_rng(seed)
            q = r.uniform(-55, 55, (per_client, 3))
            ls = [labels[i] for i in r.integers(0, len(labels), per_client)]
            out = np.empty(per_client)
            barrier.wait()
            for i in range(per_client):
                t0 = time.perf_counter()
                index.nearest(ls[i], q[i])
                out[i] = time.perf_counter() - t0
            lats.append(out)

        threads = [threading.Thread(target=worker, args=(s,)) for s in range(clients)]
        for th in threads:
            th.start()
        barrier.wait()
        t = time.perf_counter()
        for th in threads:
            th.join()
        wall = time.perf_counter() - t
        lat = np.concatenate(lats)
        print(f"  {clients} threads: nearest p50 {pct(lat, 50):.3f} ms, p99 {pct(lat, 99):.3f} ms, "
              f"{len(lat) / wall:.0f} queries/s ({len(lat)} queries)")
        index.close()


def serve(db: str, port: int) -> None:
    """The bench server (child process): the REST app over the map under uvicorn."""
    import uvicorn

    from mnemoslam.service.api import create_app
    from mnemoslam.service.config import load_config, to_dict
    from mnemoslam.storage import MapStore

    store = MapStore(db, create=False)
    config = load_config(None, {"storage": {"path": db}})

    class Service:  # what the API reads of SlamService
        def __init__(self):
            self.store, self.config = store, config

        def robots(self):
            return []

        def status(self):
            return {"uptime_s": 0.0, "robots": 0, "rejected_total": 0, "config": to_dict(config)}

        def semantics_status(self):
            return {"enabled": True, "source": "camera", "model": None, "reason": None, "classes": ADE20K32}

    app = create_app(Service())

    async def timed(scope, receive, send):  # X-App-Ms: the app's time per request
        t = time.perf_counter()

        async def send_timed(message):
            if message["type"] == "http.response.start":
                message = dict(message, headers=list(message.get("headers", [])) + [
                    (b"x-app-ms", f"{(time.perf_counter() - t) * 1e3:.3f}".encode())])
            await send(message)
        await app(scope, receive, send_timed)

    uvicorn.run(timed, host="127.0.0.1", port=port, log_level="warning", access_log=False)


def http_bench(db: Path, clients: int, per_client: int, labels: list[str], rates=()) -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    proc = subprocess.Popen([sys.executable, __file__, "--serve", str(db), "--port", str(port)], cwd=ROOT)
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                c = http.client.HTTPConnection("127.0.0.1", port, timeout=5)
                c.request("GET", "/health")
                if c.getresponse().status == 200:
                    c.close()
                    break
            except OSError:
                pass
            if time.monotonic() > deadline or proc.poll() is not None:
                raise RuntimeError("bench server did not start")
            time.sleep(0.2)

        def run(seed, n, out, app_ms, rate=0.0):
            r = np.random.default_rng(seed)
            start = time.perf_counter() + r.uniform(0, 1 / rate) if rate else 0.0
            q = r.uniform(-55, 55, (n, 3))
            ls = [labels[i] for i in r.integers(0, len(labels), n)]
            conn = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
            for i in range(n):
                if rate:  # paced: request i at start + i / rate (a planner asking at `rate` Hz)
                    time.sleep(max(0.0, start + i / rate - time.perf_counter()))
                path = f"/objects/nearest?label={ls[i]}&x={q[i, 0]:.3f}&y={q[i, 1]:.3f}&z={q[i, 2]:.3f}"
                t0 = time.perf_counter()
                conn.request("GET", path)
                resp = conn.getresponse()
                body = resp.read()
                out.append(time.perf_counter() - t0)
                app_ms.append(float(resp.getheader("x-app-ms", "nan")))
                if resp.status != 200:
                    raise RuntimeError(f"{path}: {resp.status} {body[:200]!r}")
                json.loads(body)
            conn.close()

        warm, warm_app = [], []
        run(99, 300, warm, warm_app)  # first query builds the index in the server
        solo, solo_app = [], []
        run(98, 1000, solo, solo_app)
        print(f"HTTP (uvicorn, 1 worker): 1 client:  p50 {pct(solo, 50):.2f} ms, p99 {pct(solo, 99):.2f} ms; "
              f"app time p50 {np.percentile(solo_app, 50):.2f} ms, p99 {np.percentile(solo_app, 99):.2f} ms")
        lat, app_ms = [], []
        threads = [threading.Thread(target=run, args=(s, per_client, lat, app_ms)) for s in range(clients)]
        t = time.perf_counter()
        for th in threads:
            th.start()
        for th in threads:
            th.join()
        wall = time.perf_counter() - t
        print(f"HTTP (uvicorn, 1 worker): {clients} clients: p50 {pct(lat, 50):.2f} ms, p99 {pct(lat, 99):.2f} ms, "
              f"{len(lat) / wall:.0f} requests/s ({len(lat)} requests); app time p50 "
              f"{np.percentile(app_ms, 50):.2f} ms, p99 {np.percentile(app_ms, 99):.2f} ms")
        for hz in rates:
            lat, app_ms = [], []
            n = max(20, int(hz * 10))  # ~10 s
            threads = [threading.Thread(target=run, args=(s, n, lat, app_ms, hz)) for s in range(clients)]
            for th in threads:
                th.start()
            for th in threads:
                th.join()
            print(f"HTTP (uvicorn, 1 worker): {clients} clients at {hz:g} Hz each ({clients * hz:g} requests/s): "
                  f"p50 {pct(lat, 50):.2f} ms, p99 {pct(lat, 99):.2f} ms ({len(lat)} requests); app time p50 "
                  f"{np.percentile(app_ms, 50):.2f} ms, p99 {np.percentile(app_ms, 99):.2f} ms")
    finally:
        proc.terminate()
        proc.wait(10)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--objects", type=int, default=100_000)
    ap.add_argument("--nodes", type=int, default=2000)
    ap.add_argument("--clients", type=int, default=50)
    ap.add_argument("--requests", type=int, default=200, help="per client")
    ap.add_argument("--one-label", action="store_true", help="every object a door (the nearest query scans all)")
    ap.add_argument("--db", help="map file to write (default: a temporary one); reused if it exists")
    ap.add_argument("--no-http", action="store_true")
    ap.add_argument("--rate", type=float, nargs="*", default=[2.0, 5.0],
                    help="then the clients paced at each of these rates (Hz per client, ~10 s each)")
    ap.add_argument("--serve", help=argparse.SUPPRESS)
    ap.add_argument("--port", type=int, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.serve:
        serve(args.serve, args.port)
        return 0
    print(f"load average {os.getloadavg()[0]:.1f} {os.getloadavg()[1]:.1f} {os.getloadavg()[2]:.1f} "
          f"({os.cpu_count()} cores)")
    tmp = None
    if args.db:
        db = Path(args.db)
    else:
        tmp = tempfile.TemporaryDirectory(prefix="bench_objects_")
        db = Path(tmp.name) / "objects.db"
    if not db.exists():
        build_map(db, args.nodes, args.objects, args.one_label)
    labels = ["door"] if args.one_label else ADE20K32
    query_layer(db, args.clients, args.requests * 4, labels)
    if not args.no_http:
        http_bench(db, args.clients, args.requests, labels, args.rate)
    print(f"load average {os.getloadavg()[0]:.1f} {os.getloadavg()[1]:.1f} {os.getloadavg()[2]:.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
