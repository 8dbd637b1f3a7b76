"""Two sessions into one map, offline (issue 22): when the second joins the first's map, its
links to it and their errors, and where it lies in the first one's frame.

    python bench/bench_multisession.py [--only NAME] [--rate HZ] [--set KEY=VALUE ...]

Each case runs session A, then session B into the same map database, as `mnemoslam run
DATASET --db MAP.db` does (`service.runner.run_dataset(..., db=)`), and prints per case:

- `joined`: whether B joined A's map, at which of its frames and stamp;
- `after overlap`: B's path length (ground truth) from the first frame where it is within
  0.5 m of A's path (the overlap) to that frame: how soon it joins once it could;
- `cross`: the links between A's and B's keyframes (by type) and the worst and median error
  of their relative pose against the ground truth (cm, degrees);
- `B in A`: B's trajectory (trajectory.tum, every frame) in A's frame, A's first pose placing
  that frame in the scene (the ground truth's frame), RMSE (cm), and the same with A's se3
  alignment to its ground truth applied to B: the two sessions' ground truths share one frame
  (the synthetic scene's; one sequence cut in two);
- `A`, `B`: each session's own ATE (se3-aligned, cm).

Cases: walk_a → walk_b and the reverse (synthetic, `--rate` Hz, default 5), a third session
(walk_a → walk_b → loop: a row for each later session, B against A = the first), and the negative
controls loop → straight (synthetic, no place in common: zero cross links expected) and KITTI
snippet a → b (when the data is there); with `--real` also TUM fr1/desk frames 0:300 then 300:
and 7-Scenes redkitchen 0:500 then 500:1000 (one sequence in two sessions, the second
restarted from the identity: `run --frames`), whose ground truth is one frame. Figures
measured on the shared 2 cores under load; they are accuracy figures, not timings.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mnemoslam.client.datasets import open_dataset  # noqa: E402
from mnemoslam.client.kernel.geometry import invert, rotation_angle  # noqa: E402
from mnemoslam.service.config import load_config, merge_overrides, parse_sets  # noqa: E402
from mnemoslam.service.evaluation import associate_stamps, evaluate, umeyama  # noqa: E402
from mnemoslam.service.runner import run_dataset  # noqa: E402
from mnemoslam.storage import MapStore, link_name  # noqa: E402


def _data() -> Path:
    import os

    return Path(os.environ.get("MNEMOSLAM_DATA", ROOT.parent / "shared" / "data"))


def cases(rate: float, real: bool = False) -> dict[str, tuple[str, str]]:
    """{name: (A, B)}, each a dataset spec with an optional `#START:END` (--frames)."""
    s = f"?rate={rate:g}"
    out = {"walk_a->walk_b": (f"synthetic:walk_a{s}", f"synthetic:walk_b{s}"),
           "walk_b->walk_a": (f"synthetic:walk_b{s}", f"synthetic:walk_a{s}"),
           "loop->straight": (f"synthetic:loop{s}", f"synthetic:straight{s}"),
           # a third session into the map of two (the loop crosses the walks' rooms)
           "walk_a->walk_b->loop": (f"synthetic:walk_a{s}", f"synthetic:walk_b{s}", f"synthetic:loop{s}")}
    kitti = _data() / "kitti_odometry_snippets" / "sequences"
    if (kitti / "a").is_dir() and (kitti / "b").is_dir():
        out["kitti a->b"] = (str(kitti / "a"), str(kitti / "b"))
    if real:  # one sequence cut in two, the second part restarted from the identity
        desk, kitchen = _data() / "rgbd_dataset_freiburg1_desk", _data() / "7scenes_redkitchen"
        if desk.is_dir():
            out["fr1/desk 0:300->300:"] = (f"{desk}#0:300", f"{desk}#300:")
        if kitchen.is_dir():
            out["redkitchen 0:500->500:1000"] = (f"{kitchen}#0:500", f"{kitchen}#500:1000")
    return out


def _open(spec: str):
    from mnemoslam.client.datasets.subrange import frame_range

    path, _, frames = spec.partition("#")
    return frame_range(open_dataset(path), frames or None)


def _poses_at(gt, stamps):
    ig, ie = associate_stamps(gt.stamps, stamps)
    return ig, ie


def run_case(specs: tuple[str, ...], config, folder: Path) -> list[dict]:
    """Each session of `specs` in turn into one map; a row per session after the first (see
    `_row`), that session as B and the first as A."""
    db = folder / "map.db"
    runs = []
    for i, spec in enumerate(specs):
        ds = _open(spec)
        runs.append((ds, run_dataset(ds, config, folder / f"s{i}", progress=False, db=db)))
    return [_row(runs[0], runs[i], db, i) for i in range(1, len(runs))]


def _row(first, later, db: Path, index: int) -> dict:
    (da, ra), (db_, rb) = first, later
    s = rb.summary
    row = {"joined": s.joined, "frame": s.joined_index, "stamp": s.joined_stamp, "cross": s.cross_links,
           "by_type": s.cross_links_by_type or {}}
    ga, gb = da.ground_truth, db_.ground_truth
    # own ATEs
    row["ate_a"] = evaluate(ga, ra.trajectory, align="se3").ate_rmse
    row["ate_b"] = evaluate(gb, rb.trajectory, align="se3").ate_rmse
    # B in A's frame: A's first pose places A's map frame in the ground truth's (`b_in_a`), or
    # A's se3 alignment to its ground truth (`b_in_a_aligned`, the measure)
    ig, ie = _poses_at(ga, ra.trajectory.stamps)
    to_truth = ga.poses[ig[0]] @ invert(ra.trajectory.poses[ie[0]])
    R, t, _ = umeyama(ra.trajectory.poses[ie, :3, 3], ga.poses[ig, :3, 3], with_scale=False)
    ig, ie = _poses_at(gb, rb.trajectory.stamps)
    est = np.einsum("ij,njk->nik", to_truth, rb.trajectory.poses[ie])
    err = np.linalg.norm(est[:, :3, 3] - gb.poses[ig, :3, 3], axis=1)
    row["b_in_a"] = float(np.sqrt(np.mean(err ** 2)))
    aligned = rb.trajectory.poses[ie, :3, 3] @ R.T + t
    row["b_in_a_aligned"] = float(np.sqrt(np.mean(np.sum((aligned - gb.poses[ig, :3, 3]) ** 2, axis=1))))
    # the overlap: B's first frame within 0.5 m of A's path; path length from there to the join
    pa, pb = ga.poses[:, :3, 3], gb.poses[:, :3, 3]
    near = np.array([np.min(np.linalg.norm(pa - p, axis=1)) < 0.5 for p in pb])
    row["overlap_stamp"] = float(gb.stamps[np.argmax(near)]) if near.any() else None
    if s.joined and near.any():
        i0, i1 = int(np.argmax(near)), int(np.searchsorted(gb.stamps, s.joined_stamp))
        steps = np.linalg.norm(np.diff(pb[i0:i1 + 1], axis=0), axis=1)
        row["after_overlap_m"] = float(steps.sum()) if i1 >= i0 else -float(
            np.linalg.norm(np.diff(pb[i1:i0 + 1], axis=0), axis=1).sum())
    # the cross links against the truth
    errors = []
    with MapStore(db, create=False) as store:
        ids = [x.id for x in store.sessions()]
        sa, sb = ids[0], ids[index]
        stamp = {}
        for sid, gt in ((sa, ga), (sb, gb)):
            nodes = store.nodes(session_id=sid, limit=None, merged=None)
            ig, ie = _poses_at(gt, np.array([n.stamp for n in nodes]))
            stamp.update({nodes[j].id: gt.poses[i] for i, j in zip(ig, ie)})
        mine = {n.id for n in store.nodes(session_id=sb, limit=None, merged=None)}
        for lk in store.links(session_id=sb):  # its links to the first session's nodes
            if (lk.from_id in mine) == (lk.to_id in mine) or lk.from_id not in stamp or lk.to_id not in stamp:
                continue
            d = invert(invert(stamp[lk.from_id]) @ stamp[lk.to_id]) @ lk.transform
            errors.append((link_name(lk.type), np.linalg.norm(d[:3, 3]), np.degrees(rotation_angle(d[:3, :3]))))
    row["errors"] = errors
    return row


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--only", action="append", help="run only this case (repeatable), e.g. walk_a->walk_b")
    p.add_argument("--rate", type=float, default=5.0, help="synthetic frame rate (Hz)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="config override (repeatable)")
    p.add_argument("--real", action="store_true", help="also TUM fr1/desk 0:300 then 300:, and 7-Scenes "
                                                       "redkitchen 0:500 then 500:1000 (run --frames)")
    args = p.parse_args(argv)
    config = load_config(overrides=merge_overrides({"semantics": {"enabled": False}, "grid": {"enabled": False}},
                                                   parse_sets(args.set)))
    for name, specs in cases(args.rate, args.real).items():
        if args.only and name not in args.only:
            continue
        with tempfile.TemporaryDirectory(prefix="bench-multisession-") as tmp:
            rows = run_case(specs, config, Path(tmp))
        for i, r in enumerate(rows, 1):
            _print(name if len(rows) == 1 else f"{name} [{i}]", r)
    return 0


def _print(name: str, r: dict) -> None:
    when = (f"joined at frame {r['frame']} ({r['stamp']:.2f} s), "
            + (f"{r['after_overlap_m']:.2f} m of path after entering the overlap (at {r['overlap_stamp']:.2f} s)"
               if r.get("after_overlap_m") is not None else "no overlap by the ground truth")
            if r["joined"] else "did not join")
    print(f"{name:16s} {when}")
    by_type = ", ".join(f"{n} {k}" for k, n in sorted(r["by_type"].items()))
    if r["errors"]:
        cm = np.array([e[1] for e in r["errors"]]) * 100
        deg = np.array([e[2] for e in r["errors"]])
        print(f"{'':16s} cross links {r['cross']} ({by_type}; {len(cm)} with ground truth at both ends): "
              f"median {np.median(cm):.2f} cm / "
              f"{np.median(deg):.2f} deg, worst {cm.max():.2f} cm / {deg.max():.2f} deg")
    else:
        print(f"{'':16s} cross links {r['cross']}" + (f" ({by_type})" if by_type else ""))
    in_a = (f"B in A's frame {r['b_in_a'] * 100:.2f} cm RMSE (A's se3 alignment: "
            f"{r['b_in_a_aligned'] * 100:.2f} cm); " if r["joined"] else "")
    print(f"{'':16s} {in_a}own ATE A {r['ate_a'] * 100:.2f} cm, B {r['ate_b'] * 100:.2f} cm", flush=True)


if __name__ == "__main__":
    sys.exit(main())
