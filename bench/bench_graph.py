"""iSAM2 pose-graph timings (service/mapping/graph.py PoseGraph).

    .venv/bin/python bench/bench_graph.py [--nodes 10000] [--lap 1000] [--loops-at 1000,5000,10000] [--batch]

Walks laps of a square (--lap keyframes per lap, 0.5 m steps) with noisy odometry (σ 0.5°/1 cm,
noise 0.3 σ) and adds one keyframe at a time (one iSAM2 update each, odometry only). Prints
add_node time p50/p99/max per 1k-node bucket (what tracking pays per keyframe, Python included).
At each --loops-at size it closes two loops before going on: a "lap" loop (newest node to the
same place one lap earlier) and a "full" loop (newest node back to node 0, the whole graph moves),
and prints add_loop time (iSAM2 update + iterations to convergence + the graph-error check over
every link), iterations, acceptance, and the changed_poses() time of the correction.
Loops stay in the graph, as in the service. --batch adds Levenberg–Marquardt over the final graph.

Measured (2 cores shared with other jobs, gtsam 4.3.0, QR, 10k nodes, total 7 s): add_node p50
0.11 ms (0-1k) growing to 0.60 ms (9-10k), p99 ≤ 0.92 ms, single spikes of 20-34 ms on the first
keyframe after a loop; add_loop "lap" 88/175/284 ms at 1k/5k/10k, "full" (all nodes move)
826 ms at 5k and 1,990 ms at 10k (7 iSAM2 steps, each re-eliminating every node); batch LM over
10k nodes 633 ms; iSAM2 vs LM max difference 8.75e-5.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

SIGMAS = np.array([np.deg2rad(0.5)] * 3 + [0.01] * 3)
INFO = np.diag(1.0 / SIGMAS**2)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--nodes", type=int, default=10000)
    ap.add_argument("--lap", type=int, default=1000, help="keyframes per lap of the square (multiple of 4)")
    ap.add_argument("--loops-at", default="1000,5000,10000", help="graph sizes at which loops are closed")
    ap.add_argument("--bucket", type=int, default=1000)
    ap.add_argument("--batch", action="store_true", help="also time batch LM over the final graph")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    import gtsam

    from mnemoslam.service.mapping.graph import PoseGraph

    rng = np.random.default_rng(args.seed)
    side = args.lap // 4
    fwd = gtsam.Pose3.Expmap(np.array([0, 0, 0, 0.5, 0, 0])).matrix()
    turn = gtsam.Pose3.Expmap(np.array([0, 0, np.pi / 2, 0, 0, 0])).matrix()
    loops_at = sorted({int(x) for x in args.loops_at.split(",") if x.strip() and int(x) <= args.nodes})

    def true_step(k: int) -> np.ndarray:  # motion from node k to node k+1
        return fwd @ turn if (k + 1) % side == 0 else fwd

    truth = [np.eye(4)]
    dead = [np.eye(4)]  # odometry alone
    g = PoseGraph()
    g.add_node(0, truth[0])
    times = np.zeros(args.nodes)
    cpu = np.zeros(args.nodes)  # thread CPU time: unaffected by other processes taking the cores
    loop_rows = []
    t_start = time.perf_counter()
    for k in range(1, args.nodes):
        step = true_step(k - 1)
        truth.append(truth[-1] @ step)
        meas = step @ gtsam.Pose3.Expmap(rng.normal(size=6) * SIGMAS * 0.3).matrix()
        dead.append(dead[-1] @ meas)
        c0, t0 = time.thread_time(), time.perf_counter()
        g.add_node(k, np.eye(4), odom_from=k - 1, transform=meas, information=INFO)
        times[k] = time.perf_counter() - t0
        cpu[k] = time.thread_time() - c0
        if k + 1 in loops_at:
            for name, other in (("lap", k - args.lap), ("full", 0)):
                if other < 0 or (name == "full" and other == k - args.lap):
                    continue
                noise = gtsam.Pose3.Expmap(rng.normal(size=6) * SIGMAS * 0.3).matrix()
                rel = np.linalg.inv(truth[k]) @ truth[other] @ noise
                g.changed_poses()  # reference: everything published so far
                c0, t0 = time.thread_time(), time.perf_counter()
                out = g.add_loop(k, other, rel, INFO)
                dt = time.perf_counter() - t0
                dcpu = time.thread_time() - c0
                t1 = time.perf_counter()
                moved = g.changed_poses()
                dtc = time.perf_counter() - t1
                loop_rows.append((k + 1, name, other, dt * 1e3, dcpu * 1e3, out.iterations, out.accepted,
                                  out.error_before, out.max_normalized_error, len(moved), dtc * 1e3))
    total = time.perf_counter() - t_start

    print(f"PoseGraph iSAM2, {args.nodes} nodes, lap {args.lap}, gtsam {_version('gtsam')}, total {total:.1f} s")
    print()
    print(f"load average at the end: {' '.join(f'{x:.2f}' for x in _loadavg())} on {_cores()} cores "
          "(wall times include waiting for a core; CPU = this thread's CPU time)")
    print()
    print("add_node (odometry only), ms per node")
    print(f"{'nodes':>13} {'p50':>7} {'p99':>7} {'max':>7} {'CPU p50':>8} {'CPU p99':>8}")
    for b0 in range(0, args.nodes, args.bucket):
        sl = slice(max(b0, 1), min(b0 + args.bucket, args.nodes))
        t, c = times[sl] * 1e3, cpu[sl] * 1e3
        if len(t):
            print(f"{b0:>6}-{min(b0 + args.bucket, args.nodes):<6} {np.percentile(t, 50):7.3f} "
                  f"{np.percentile(t, 99):7.3f} {t.max():7.3f} {np.percentile(c, 50):8.3f} {np.percentile(c, 99):8.3f}")
    print()
    print("add_loop (iSAM2 update + iterations + error check over all links)")
    print(f"{'nodes':>6} {'loop':>5} {'to':>6} {'ms':>8} {'CPU ms':>8} {'iters':>5} {'accepted':>8} "
          f"{'err before σ':>12} {'max err σ':>9} {'moved':>6} {'changed_poses ms':>16}")
    for r in loop_rows:
        print(f"{r[0]:>6} {r[1]:>5} {r[2]:>6} {r[3]:8.1f} {r[4]:8.1f} {r[5]:>5} {str(r[6]):>8} {r[7]:12.1f} "
              f"{r[8]:9.2f} {r[9]:>6} {r[10]:16.1f}")
    est = g.poses()
    ate = np.sqrt(np.mean([np.sum((est[i][:3, 3] - truth[i][:3, 3]) ** 2) for i in range(len(truth))]))
    ate0 = np.sqrt(np.mean([np.sum((dead[i][:3, 3] - truth[i][:3, 3]) ** 2) for i in range(len(truth))]))
    print(f"\nATE against the truth (no alignment): odometry alone {ate0:.3f} m, with the "
          f"{len(g.loops())} loops {ate:.3f} m (perimeter of a lap {args.lap * 0.5:.0f} m)")
    if args.batch:
        t0 = time.perf_counter()
        batch = g.batch_optimize()
        dt = time.perf_counter() - t0
        diff = max(float(np.abs(batch[k] - est[k]).max()) for k in est)
        print(f"batch LM over {len(est)} nodes / {len(g.loops())} loops: {dt * 1e3:.0f} ms, "
              f"max |iSAM2 - LM| {diff:.2e}")
    return 0


def _loadavg() -> tuple[float, float, float]:
    import os
    try:
        return os.getloadavg()
    except OSError:
        return (float("nan"),) * 3


def _cores() -> int:
    import os
    return os.cpu_count() or 0


def _version(name: str) -> str:
    from importlib.metadata import version
    try:
        return version(name)
    except Exception:
        return "?"


if __name__ == "__main__":
    raise SystemExit(main())
