"""Do the ground-truth poses agree with the images? For every graph link of a `mnemoslam run`
output, the share of the two keyframes' feature matches that the link's relative pose explains,
beside the share the ground truth's relative pose explains.

    python bench/gt_consistency.py RUN_DIR DATASET [--types loop,proximity] [--px 3] [--worst 10] [--dense]

RUN_DIR is a `mnemoslam run --out` folder (its map.db), DATASET the sequence it ran on. For
each link, ORB features of both keyframes' colour images are matched (cross-checked Hamming);
the matches of the first keyframe with depth are projected into the second by a relative pose,
and a match is explained when it lands within `--px` pixels. A link's error against ground
truth (the link-accuracy report of `run`) means a bad link only where the ground truth explains
the images at least as well as the link does; where it explains far fewer matches, the
reference, not the link, disagrees with the images. With `--dense` the two keyframes are also
registered densely (the tracker's photometric + point-to-plane ICP, `service.tracking.icp`)
starting from the ground truth's relative pose, and the table gives how far from the ground
truth and from the link it converges (for texture-poor frames where few features match).
Nothing here is a test: it reads no thresholds of the service.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mnemoslam.client.datasets import open_dataset  # noqa: E402
from mnemoslam.client.kernel.geometry import rotation_angle  # noqa: E402
from mnemoslam.service.evaluation import associate_stamps, invert  # noqa: E402
from mnemoslam.service.memory.views import DenseView  # noqa: E402
from mnemoslam.service.tracking import icp  # noqa: E402
from mnemoslam.storage import MapStore, link_name  # noqa: E402


def explained(frame_a, frame_b, K: np.ndarray, T_ab_list, orb, px: float) -> tuple[int, list[int]]:
    """Matches with depth in `frame_a`, and how many of them each T_a_b (pose of b in a) in
    `T_ab_list` projects within `px` of their match in `frame_b`."""
    ka, da = orb.detectAndCompute(frame_a.grey, None)
    kb, db = orb.detectAndCompute(frame_b.grey, None)
    if da is None or db is None:
        return 0, [0] * len(T_ab_list)
    m = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(da, db)
    pa = np.array([ka[x.queryIdx].pt for x in m]).reshape(-1, 2)
    pb = np.array([kb[x.trainIdx].pt for x in m]).reshape(-1, 2)
    z = frame_a.depth[np.rint(pa[:, 1]).astype(int), np.rint(pa[:, 0]).astype(int)]
    ok = np.isfinite(z) & (z > 0)
    pa, pb, z = pa[ok], pb[ok], z[ok]
    X = np.stack(((pa[:, 0] - K[0, 2]) * z / K[0, 0], (pa[:, 1] - K[1, 2]) * z / K[1, 1], z, np.ones_like(z)))
    counts = []
    for T_ab in T_ab_list:
        Xb = (invert(T_ab) @ X)[:3]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = (K @ Xb)[:2] / Xb[2]
        counts.append(int(((Xb[2] > 0) & (np.linalg.norm(uv.T - pb, axis=1) < px)).sum()))
    return len(z), counts


def dense_from_truth(frame_a, frame_b, camera, T_true: np.ndarray,
                     T_link: np.ndarray) -> tuple[float, float, float, float]:
    """Dense registration of b onto a started at the true T_a_b: (cm, deg) of the result from
    the ground truth, then from the link (NaN when it does not converge)."""
    a, b = (DenseView(f.depth, f.grey, camera) for f in (frame_a, frame_b))
    res = icp.register(b.levels(), a.levels(), T_true, hypotheses=False)
    if not res.ok:
        return (float("nan"),) * 4
    out = []
    for T in (T_true, T_link):
        d = invert(T) @ res.pose
        out += [float(np.linalg.norm(d[:3, 3]) * 100), float(np.degrees(rotation_angle(d[:3, :3])))]
    return tuple(out)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_dir", type=Path)
    ap.add_argument("dataset")
    ap.add_argument("--types", default="loop,proximity",
                    help="link kinds to check (odometry, loop, proximity, path, merged)")
    ap.add_argument("--px", type=float, default=3.0, help="a match is explained within this many pixels")
    ap.add_argument("--worst", type=int, default=10, help="list this many links where ground truth explains least")
    ap.add_argument("--dense", action="store_true", help="also register each pair densely from the ground truth's pose")
    args = ap.parse_args()

    ds = open_dataset(args.dataset)
    if ds.ground_truth is None or ds.calibration.kind != "rgbd":
        print("needs an RGB-D dataset with ground truth", file=sys.stderr)
        return 2
    with MapStore(args.run_dir / "map.db", create=False) as store:
        nodes = store.nodes(limit=None)
        links = store.links()
    kinds = set(args.types.split(","))
    stamp = {n.id: n.stamp for n in nodes}
    gi, fi = associate_stamps(ds.ground_truth.stamps, ds.stamps, 0.02)
    truth = dict(zip(fi.tolist(), ds.ground_truth.poses[gi]))
    K = ds.calibration.camera.K
    orb = cv2.ORB_create(2000)
    rows = []
    for link in links:
        kind = link_name(link.type)
        if kind not in kinds:
            continue
        ia, ib = (int(np.argmin(np.abs(ds.stamps - stamp[i]))) for i in (link.from_id, link.to_id))
        if ia not in truth or ib not in truth:
            continue
        T_true = invert(truth[ia]) @ truth[ib]
        fa, fb = ds.frame(ia), ds.frame(ib)
        n, (by_link, by_truth) = explained(fa, fb, K, [np.asarray(link.transform), T_true], orb, args.px)
        dense = (dense_from_truth(fa, fb, ds.calibration.camera, T_true, np.asarray(link.transform))
                 if args.dense else ())
        rows.append((link.from_id, link.to_id, kind, ia, ib, n, by_link, by_truth, dense))
    if not rows:
        print("no links of those kinds with ground truth")
        return 1
    print(f"{len(rows)} links ({args.types}); matches with depth explained within {args.px:g} px")
    print(f"{'link':>9} {'kind':<10} {'frames':>11} {'matches':>7} {'by link':>7} {'by truth':>8}"
          + ("   dense from truth: off truth cm/deg, off link cm/deg" if args.dense else ""))
    order = sorted(rows, key=lambda r: r[7] / max(r[6], 1))
    for a, b, kind, ia, ib, n, by_link, by_truth, dense in order[:args.worst]:
        extra = ("   {:6.2f} / {:5.2f}    {:6.2f} / {:5.2f}".format(*dense)) if dense else ""
        print(f"{a:>4}-{b:<4} {kind:<10} {ia:>5}-{ib:<5} {n:7d} {by_link:7d} {by_truth:8d}{extra}")
    link_share = np.array([r[6] / max(r[5], 1) for r in rows])
    truth_share = np.array([r[7] / max(r[5], 1) for r in rows])
    worse = sum(r[7] < 0.5 * r[6] for r in rows)
    better = sum(r[7] > r[6] for r in rows)
    print(f"median share explained: by the links {np.median(link_share):.2f}, "
          f"by ground truth {np.median(truth_share):.2f}")
    print(f"ground truth explains fewer than half the link's matches on {worse} of {len(rows)} links; "
          f"more than the link on {better}")
    if args.dense:
        d = np.array([r[8] for r in rows])
        ok = np.isfinite(d[:, 0])
        if ok.any():
            nearer = int((d[ok, 2] < d[ok, 0]).sum())
            print(f"dense registration from the ground truth's pose converged on {int(ok.sum())} of {len(rows)}: "
                  f"median {np.median(d[ok, 0]):.2f} cm / {np.median(d[ok, 1]):.2f} deg from the ground truth, "
                  f"{np.median(d[ok, 2]):.2f} cm / {np.median(d[ok, 3]):.2f} deg from the link; "
                  f"nearer the link on {nearer}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
