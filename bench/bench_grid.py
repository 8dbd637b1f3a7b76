"""Occupancy grids (issue 25): per-keyframe local grid cost, the map grid's assembly after a
loop closure, and REST latency of the grid of a 20k-keyframe map.

    .venv/bin/python bench/bench_grid.py [--nodes 20000] [--frames 60] [--requests 30] [--db FILE]

1. Per keyframe: `LocalGridMaker.make` on `--frames` frames of the synthetic walk_b (640×480,
   every 3rd frame), median / p90 ms, its PNG encoding and `save_local_grids` (the row the
   keyframe writer adds), and, as the baseline in the same process, ORB extraction
   (`FeatureExtractor.extract`, what tracking pays on every frame) on the same frames: the
   ratio is the figure to trust on a shared machine.
2. A `--nodes` map: keyframes on a random walk over a 60 × 60 m floor, each with one of the
   walk's local grids (`save_local_grids`), odometry links. `MapGrids.grid`: the first
   assembly (every local grid read and placed), a request without change, 10 new keyframes,
   and a loop closure that moves every keyframe (a 1° / 0.5 m bend growing along the path:
   all re-placed) against a from-scratch assembly at the corrected poses.
3. REST: the app under uvicorn in a thread (a service stand-in holding the store), GET
   /maps/0/grid?format=png and ?format=json, `--requests` each, p50 / p99 as the client sees
   them (the grid up to date, no change between requests: what a planner polling pays); then
   a loop closure moving every keyframe while a planner polls every 50 ms: the requests'
   latency and how long until the grid served follows it (X-Map-Current).
4. The map cloud (`map_cloud`, GET /maps/{map}/cloud's) of `--cloud-keyframes` keyframes of
   walk_b with images: without the cache, and with it (first, again, after 10 % moved).

Prints the load average: on a shared 2-core machine the figures move with it.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def ms(a, q) -> float:
    return float(np.percentile(np.asarray(a) * 1e3, q))


def per_keyframe(frames: int):
    from mnemoslam.client.synthetic.dataset import SyntheticDataset
    from mnemoslam.service.config import Config
    from mnemoslam.service.grid.local import LocalGridMaker
    from mnemoslam.service.tracking.features import FeatureExtractor
    from mnemoslam.storage import KeyframeRecord, LocalGridRecord, MapStore

    ds = SyntheticDataset("walk_b", rate=30.0)
    idx = np.linspace(0, len(ds) - 1, frames).astype(int)
    fr = [ds.frame(int(i)) for i in idx]
    T0 = np.linalg.inv(ds.ground_truth.poses[0])
    poses = [T0 @ ds.ground_truth.poses[int(i)] for i in idx]
    cfg = Config()
    mk = LocalGridMaker(ds.calibration.camera, cfg.grid)
    ext = FeatureExtractor(ds.calibration, cfg.features, cfg.stereo)
    for f in fr[:3]:  # warm-up
        mk.make(f.depth, np.eye(4), 0)
        ext.extract(f)
    t_grid, t_orb, t_png, sizes, cells = [], [], [], [], []
    grids = []
    for f, p in zip(fr, poses):
        t = time.perf_counter()
        g = mk.make(f.depth, p, 0)
        t_grid.append(time.perf_counter() - t)
        t = time.perf_counter()
        blob = g.encode_cells()
        t_png.append(time.perf_counter() - t)
        sizes.append(len(blob))
        cells.append(g.cells.size)
        grids.append(g)
        t = time.perf_counter()
        ext.extract(f)
        t_orb.append(time.perf_counter() - t)
    with tempfile.TemporaryDirectory() as d, MapStore(Path(d) / "k.db") as s:
        sid = s.begin_session("b", ds.calibration)
        t_db = []
        for g, p in zip(grids, poses):
            nid = s.add_keyframe(KeyframeRecord(sid, 0.0, p, np.zeros((0, 2), np.float32), np.zeros((0, 32), np.uint8),
                                                np.zeros((0, 3), np.float32)))
            t = time.perf_counter()
            s.save_local_grids([LocalGridRecord(nid, g.cell_size, g.T_cam_local, g.origin_x, g.origin_y,
                                                g.encode_cells(), g.up_source, g.floor_points)])
            t_db.append(time.perf_counter() - t)
    print(f"1. per keyframe ({frames} frames of walk_b, 640x480, decimation {cfg.grid.depth_decimation}):")
    print(f"   local grid          p50 {ms(t_grid, 50):.2f} ms  p90 {ms(t_grid, 90):.2f} ms")
    print(f"   + PNG encode        p50 {ms(t_png, 50):.2f} ms;  stored {np.median(sizes) / 1e3:.1f} kB "
          f"(cells {np.median(cells):.0f})")
    print(f"   + save_local_grids  p50 {ms(t_db, 50):.2f} ms  p90 {ms(t_db, 90):.2f} ms")
    ratio = np.median(t_grid) / np.median(t_orb)
    print(f"   baseline: ORB extract p50 {ms(t_orb, 50):.2f} ms  -> grid / ORB = {ratio:.2f}")
    return grids, poses


def build_map(path: Path, n: int, grids, seed: int = 0):
    from mnemoslam.client.kernel.frames import Calibration, PinholeCamera
    from mnemoslam.storage import KeyframeRecord, LinkType, LocalGridRecord, MapStore

    rng = np.random.default_rng(seed)
    s = MapStore(path)
    sid = s.begin_session("b", Calibration(PinholeCamera(525, 525, 319.5, 239.5, 640, 480)))
    # a random walk on a 60 x 60 m floor, 0.15 m per keyframe, heading turning slowly; camera
    # looking along the heading (map frame = a camera frame: y down, z forward at the start)
    pos, yaw = np.zeros(2), 0.0
    prev_id = prev_pose = None
    ids, poses = [], []
    recs = [LocalGridRecord(0, g.cell_size, g.T_cam_local, g.origin_x, g.origin_y, g.encode_cells(), g.up_source,
                            g.floor_points) for g in grids]
    for k in range(n):
        yaw += rng.normal(0, 0.15)
        step = 0.15 * np.array([np.cos(yaw), np.sin(yaw)])
        if np.any(np.abs(pos + step) > 30):
            yaw += np.pi
            step = -step
        pos = pos + step
        c, si = np.cos(yaw), np.sin(yaw)
        # camera: x right, y down, z forward; the floor plane is the map's x-z plane (y down)
        R = np.array([[si, 0, c], [0, 1, 0], [-c, 0, si]])
        P = np.eye(4)
        P[:3, :3] = R
        P[:3, 3] = (pos[0], 0.0, pos[1])
        link = None if prev_id is None else (prev_id, np.linalg.inv(prev_pose) @ P, None)
        nid = s.add_keyframe(KeyframeRecord(sid, float(k), P, np.zeros((0, 2), np.float32),
                                            np.zeros((0, 32), np.uint8), np.zeros((0, 3), np.float32), odom_link=link))
        r = recs[k % len(recs)]
        s.save_local_grids([LocalGridRecord(nid, r.cell_size, r.transform, r.origin_x, r.origin_y, r.cells,
                                            "floor", 1000)])
        ids.append(nid)
        poses.append(P)
        prev_id, prev_pose = nid, P
    s.add_link(ids[0], ids[-1], LinkType.GLOBAL_CLOSURE, np.linalg.inv(poses[0]) @ poses[-1])
    return s, np.array(ids), np.stack(poses)


def bend(poses, degrees: float, keep: int):
    """Poses as a loop closure corrects them: a yaw about the map's y and a shift along x,
    growing along the path; the first `keep` (the grid frame's keyframes) kept: no rebuild."""
    n = len(poses)
    f = np.arange(n) / (n - 1)
    a = np.radians(degrees) * f
    bent = poses.copy()
    for i in range(n):
        R = np.array([[np.cos(a[i]), 0, np.sin(a[i])], [0, 1, 0], [-np.sin(a[i]), 0, np.cos(a[i])]])
        bent[i, :3, :3] = R @ poses[i, :3, :3]
        bent[i, :3, 3] = R @ poses[i, :3, 3] + np.array([0.5 * f[i], 0, 0])
    bent[:keep] = poses[:keep]
    return bent


def assembly(store, ids, poses):
    from mnemoslam.service.config import GridConfig
    from mnemoslam.service.grid.maps import MapGrids

    cfg = GridConfig()
    mg = MapGrids(store, cfg)
    t = time.perf_counter()
    img = mg.grid(0)
    first = time.perf_counter() - t
    t = time.perf_counter()
    mg.grid(0)
    again = time.perf_counter() - t
    print(f"2. map grid of {len(ids)} keyframes ({img.width} x {img.height} cells at {img.resolution} m):")
    print(f"   first assembly (read + place all)   {first * 1e3:8.0f} ms")
    print(f"   a request without change            {again * 1e3:8.1f} ms")
    # a loop closure: every keyframe moved (a bend growing along the path)
    bent = bend(poses, 1.0, cfg.frame_nodes)
    store.update_poses({int(k): p for k, p in zip(ids, bent)})
    t = time.perf_counter()
    img = mg.grid(0)
    loop = time.perf_counter() - t
    st = mg.last_update
    t = time.perf_counter()
    fresh = MapGrids(store, cfg).grid(0)
    scratch = time.perf_counter() - t
    same = img.states.shape == fresh.states.shape and np.mean(img.states == fresh.states)
    print(f"   after a loop closure moving {st['moved']} keyframes: {loop * 1e3:.0f} ms "
          f"(from scratch {scratch * 1e3:.0f} ms); cells equal to the from-scratch grid: {100 * same:.2f} %")
    return mg


def rest(store, requests_n: int):
    import http.client

    from mnemoslam.service.api import ApiThread, create_app
    from mnemoslam.service.config import load_config

    class Stand:
        def __init__(self, store):
            self.store, self.config = store, load_config()

        def robots(self):
            return []

        def status(self):
            return {}

    app = create_app(Stand(store))
    with ApiThread(app) as url:
        host, port = url.removeprefix("http://").split(":")
        conn = http.client.HTTPConnection(host, int(port), timeout=120)
        print(f"3. REST on the {store.count_nodes()}-keyframe map (grid up to date; {requests_n} requests each):")
        for fmt in ("png", "pgm", "json"):
            lat, size = [], 0
            for k in range(requests_n + 1):
                t = time.perf_counter()
                conn.request("GET", f"/maps/0/grid?format={fmt}")
                r = conn.getresponse()
                body = r.read()
                if k:  # the first one assembles
                    lat.append(time.perf_counter() - t)
                size = len(body)
                assert r.status == 200, body[:200]
            print(f"   GET /maps/0/grid?format={fmt:<4}  p50 {ms(lat, 50):7.1f} ms  p99 {ms(lat, 99):7.1f} ms  "
                  f"({size / 1e6:.2f} MB)")
        # a loop closure moving every keyframe while a planner polls (every 50 ms): with the
        # background thread (grid.refresh_interval) the requests get the last grid at once until
        # the re-placed one is ready; without it the first request pays the re-placing
        from mnemoslam.service.config import GridConfig

        g = store.grid_nodes(has_grid=False)
        store.update_poses({int(k): p for k, p in zip(g["id"], bend(g["pose"], -1.0, GridConfig().frame_nodes))})
        t0, lat, stale = time.perf_counter(), [], 0
        while time.perf_counter() - t0 < 120:
            t = time.perf_counter()
            conn.request("GET", "/maps/0/grid?format=png")
            r = conn.getresponse()
            r.read()
            lat.append(time.perf_counter() - t)
            if r.getheader("X-Map-Current", "true") == "true":
                break
            stale += 1
            time.sleep(0.05)
        print(f"   after a loop closure moving every keyframe, GET ?format=png every 50 ms: {len(lat)} requests "
              f"(p50 {ms(lat, 50):.0f} ms, max {max(lat) * 1e3:.0f} ms; {stale} served the last grid), "
              f"up to date after {time.perf_counter() - t0:.1f} s")
        conn.close()


def cloud(keyframes: int):
    """4. The map cloud: `map_cloud` of walk_b's keyframes (every 2nd frame at 5 Hz, images
    stored as the service stores them) without the cache, then with it: the first request,
    a second one (nothing changed), one after 10 % of the keyframes moved."""
    import cv2

    from mnemoslam.client.synthetic.dataset import SyntheticDataset
    from mnemoslam.service.config import GridConfig
    from mnemoslam.service.grid.cloud import CloudCache, map_cloud
    from mnemoslam.storage import KeyframeRecord, MapStore

    ds = SyntheticDataset("walk_b", rate=5.0)
    with tempfile.TemporaryDirectory() as d, MapStore(Path(d) / "c.db") as s:
        sid = s.begin_session("r", ds.calibration)
        T0 = np.linalg.inv(ds.ground_truth.poses[0])
        ids, poses = [], []
        for i in list(range(0, len(ds), 2))[:keyframes]:
            f = ds.frame(i)
            p = T0 @ ds.ground_truth.poses[i]
            depth = cv2.imencode(".png", np.clip(np.rint(f.depth * 1000), 0, 65535).astype(np.uint16))[1].tobytes()
            jpeg = cv2.imencode(".jpg", f.image)[1].tobytes()
            ids.append(s.add_keyframe(KeyframeRecord(sid, f.stamp, p, np.zeros((0, 2), np.float32),
                                                     np.zeros((0, 32), np.uint8), np.zeros((0, 3), np.float32),
                                                     image_jpeg=jpeg, depth_png=depth)))
            poses.append(p)
        poses = np.stack(poses)
        moved = poses.copy()
        moved[::10, 0, 3] += 0.05
        cache = CloudCache(GridConfig().cloud_cache_mb * 2 ** 20)
        t = []
        runs = (("no cache", poses, None), ("cached: first", poses, cache), ("cached: again", poses, cache),
                ("cached: 10 % moved", moved, cache), ("no cache, 10 % moved", moved, None))
        for label, ps, c in runs:
            t0 = time.perf_counter()
            P, _ = map_cloud(s, ids, ps, 0.02, cache=c)
            t.append((label, time.perf_counter() - t0, len(P)))
        print(f"4. map cloud of {len(ids)} keyframes (640x480, voxel 0.02 m; cache {cache.bytes / 2 ** 20:.0f} MiB):")
        for label, dt, n in t:
            print(f"   {label:<22} {dt * 1e3:7.0f} ms  ({n} points)")
        print(f"   again / no cache = {t[2][1] / t[0][1]:.3f}; 10 % moved / no cache = {t[3][1] / t[4][1]:.2f}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--nodes", type=int, default=20000)
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--requests", type=int, default=30)
    ap.add_argument("--db", help="keep the map here (reused when it exists)")
    ap.add_argument("--cloud-keyframes", type=int, default=96, help="keyframes of the cloud figure (0: skip it)")
    ap.add_argument("--only-cloud", action="store_true", help="the cloud figure alone")
    a = ap.parse_args()
    if a.only_cloud:
        cloud(a.cloud_keyframes)
        return 0
    print(f"load average {os.getloadavg()[0]:.1f}")
    grids, _ = per_keyframe(a.frames)
    from mnemoslam.storage import MapStore

    with tempfile.TemporaryDirectory() as d:
        path = Path(a.db) if a.db else Path(d) / "grid.db"
        t = time.perf_counter()
        if a.db and path.exists():
            store = MapStore(path)
            ids = store.grid_nodes()["id"]
            poses = store.grid_nodes()["pose"]
        else:
            store, ids, poses = build_map(path, a.nodes, grids)
        print(f"   (map of {len(ids)} keyframes ready in {time.perf_counter() - t:.0f} s)")
        with store:
            assembly(store, ids, poses)
            rest(store, a.requests)
    if a.cloud_keyframes:
        cloud(a.cloud_keyframes)
    print(f"load average {os.getloadavg()[0]:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
