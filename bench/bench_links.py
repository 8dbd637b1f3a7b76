"""Loop-link refinement, part by part (issue 29): what `loop.link_refine` does to each loop /
proximity link and to the optimised graph.

    python bench/bench_links.py [--only NAME] [--links] [--set KEY=VALUE ...]

Per sequence with ground truth, one offline run per variant of the mechanism, each printing
the ATE with loops (cm, se3-aligned, every frame) and its links:

- `odometry`: no loop closure at all;
- `off`: loop.link_refine=false (verified links as PnP / dense registration made them);
- `default`: the configuration as it is (with --set applied);
- `transform` / `information` / `drop`: the refinement on with only that part switched on
  (`loop.link_refine_transform` / `_information` / `_drop`), the others off.

With `--links`, a second table gives per link type of the `off` and `default` runs' maps the
median error against the ground truth, the median σ the links' information claims and the
median ratio of the two: the graph weighs link types as their errors deserve only when the
ratio is alike across types. A third table lists every loop / proximity link the default run verified
and refined: the two keyframes, the link type the map stored it as (or "-" if it was not
added), its error against the ground truth before the refinement (the verified transform) and
after (the refined one), the σ the refinement estimated, the σ its information claims (the
floor applied), and what became of it (dropped as inaccurate, refused by the graph, added).
Recorded by wrapping the mapper's `_accurate` and `refine_link` in this process: the run
itself is the product's, unchanged.
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from run_sequences import opened, print_table  # noqa: E402  (bench/, the script's folder)

from mnemoslam.service.config import load_config, merge_overrides, parse_sets  # noqa: E402
from mnemoslam.service.evaluation import LINK_KINDS, evaluate, evaluate_links  # noqa: E402
from mnemoslam.service.mapping import mapper as mapper_module  # noqa: E402
from mnemoslam.service.runner import run_dataset  # noqa: E402
from mnemoslam.storage import MapStore  # noqa: E402

PARTS = ("transform", "information", "drop")
VARIANTS = ("odometry", "off", "default") + PARTS


def sequences(data: Path, synthetic_frames: int):
    yield "7-scenes redkitchen", data / "7scenes_redkitchen", {}
    yield "tum fr1/desk", data / "rgbd_dataset_freiburg1_desk", {}
    yield "tum fr3/cabinet keyframes", data / "rgbd_dataset_freiburg3_cabinet_keyframes", {}
    yield "synthetic loop + noise", "synthetic:loop", {"max_frames": synthetic_frames, "noise": True}


def variant_overrides(variant: str) -> dict:
    if variant == "odometry":
        return {"loop": {"enabled": False}}
    if variant == "off":
        return {"loop": {"link_refine": False}}
    if variant in PARTS:
        return {"loop": {"link_refine": True, **{f"link_refine_{p}": p == variant for p in PARTS}}}
    return {}


class Recorder:
    """Every `_accurate` call of the mapper in this process: the verified link, the
    refinement's estimate and the decision."""

    def __init__(self):
        self.rows: list[dict] = []
        self._estimate = None
        self._accurate = mapper_module.Mapper._accurate
        self._refine_link = mapper_module.refine_link

    def __enter__(self):
        recorder = self

        def refine_link(*args, **kwargs):
            recorder._estimate = recorder._refine_link(*args, **kwargs)
            return recorder._estimate

        def accurate(mapper, u, candidate, v):
            recorder._estimate = None
            decision, out = recorder._accurate(mapper, u, candidate, v)
            e = recorder._estimate
            if e is not None:
                recorder.rows.append({"new": u.node_id, "candidate": candidate, "before": v.transform,
                                      "after": e.transform, "dense": bool(v.refined), "estimate": e,
                                      "decision": decision, "information": out.information})
            return decision, out

        mapper_module.refine_link = refine_link
        mapper_module.Mapper._accurate = accurate
        return self

    def __exit__(self, *exc):
        mapper_module.refine_link = self._refine_link
        mapper_module.Mapper._accurate = self._accurate


def claimed_sigma(information: np.ndarray) -> tuple[float, float]:
    """Largest translation σ (cm) and rotation σ (deg) a 6×6 information (rotation first) claims."""
    C = np.linalg.inv(information)
    return (100 * float(np.sqrt(np.linalg.eigvalsh(C[3:, 3:])[-1])),
            float(np.degrees(np.sqrt(np.linalg.eigvalsh(C[:3, :3])[-1]))))


def link_table(ds, db: Path, rows: list[dict]) -> list[tuple]:
    with MapStore(db, create=False) as store:
        nodes = store.nodes(limit=None)
        stored = {(x.from_id, x.to_id): int(x.type) for x in store.links()}
    ids, stamps = [n.id for n in nodes], [n.stamp for n in nodes]

    def errors(key):
        rep = evaluate_links(ds.ground_truth, ids, stamps,
                             [(r["candidate"], r["new"], 1, r[key]) for r in rows if r[key] is not None])
        return {(a, b): (cm, deg) for a, b, _, cm, deg in rep.rows}

    before, after = errors("before"), errors("after")
    out = []
    for r in rows:
        key = (r["candidate"], r["new"])
        e = r["estimate"]
        kind = LINK_KINDS.get(stored[key], str(stored[key])) if key in stored else "-"
        b = before.get(key, (float("nan"),) * 2)
        a = after.get(key, (float("nan"),) * 2)
        claim = claimed_sigma(r["information"]) if r["information"] is not None else (float("nan"),) * 2
        decision = r["decision"] if r["decision"] != "ok" else ("added" if key in stored else "refused by the graph")
        out.append((f"{r['candidate']}-{r['new']}", kind, "dense" if r["dense"] else "pnp",
                    f"{b[0]:.2f} / {b[1]:.2f}", f"{a[0]:.2f} / {a[1]:.2f}",
                    f"{e.sigma_translation * 100:.2f} / {e.sigma_rotation:.2f}" if e.covariance is not None else "-",
                    f"{claim[0]:.2f} / {claim[1]:.2f}", e.inliers, decision[:40]))
    return out


def consistency_table(ds, db: Path, variant: str) -> list[tuple]:
    """Per link type of a run's map: the links' errors against the ground truth beside the σ
    their information claims, and the median ratio of the two (a consistent information gives
    every link type the same ratio: the graph then weighs them as their errors deserve)."""
    with MapStore(db, create=False) as store:
        nodes = store.nodes(limit=None)
        links = store.links()
    report = evaluate_links(ds.ground_truth, [n.id for n in nodes], [n.stamp for n in nodes],
                            [(x.from_id, x.to_id, int(x.type), x.transform) for x in links])
    claims = {(x.from_id, x.to_id): claimed_sigma(x.information) for x in links if x.information is not None}
    out = []
    for kind in dict.fromkeys(k for _, _, k, _, _ in report.rows):
        r = np.array([(cm, deg, *claims[(a, b)]) for a, b, k, cm, deg in report.rows
                      if k == kind and (a, b) in claims])
        if not len(r):
            continue
        med = np.median(r, axis=0)
        out.append((variant, kind, len(r), f"{med[0]:.2f} / {med[1]:.2f}", f"{med[2]:.2f} / {med[3]:.2f}",
                    f"{np.median(r[:, 0] / r[:, 2]):.1f} / {np.median(r[:, 1] / r[:, 3]):.1f}"))
    return out


def reduction(table: list[tuple]) -> str:
    """How much closer to the ground truth the refined transform is than the verified one,
    over the links that take it (PnP-verified; dense ones keep their own): median and RMS
    ratio of the errors before / after, translation and rotation."""
    pairs = [(float(x) for x in (*t[3].split(" / "), *t[4].split(" / "))) for t in table if t[2] == "pnp"]
    e = np.array([p for p in (tuple(q) for q in pairs) if all(np.isfinite(p))])
    if not len(e):
        return "no link took the refined transform"
    med = np.median(e[:, :2] / e[:, 2:], axis=0)
    rms = np.sqrt((e[:, :2] ** 2).mean(axis=0) / (e[:, 2:] ** 2).mean(axis=0))
    return (f"{len(e)} links took the refined transform: error before / after, median ratio "
            f"{med[0]:.2f} / {med[1]:.2f}, RMS ratio {rms[0]:.2f} / {rms[1]:.2f} (translation / rotation)")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", help="run sequences whose name contains this")
    ap.add_argument("--variants", default=",".join(VARIANTS), help=f"comma-separated, of {', '.join(VARIANTS)}")
    ap.add_argument("--links", action="store_true", help="also list every refined link of the default run")
    ap.add_argument("--synthetic-frames", type=int, default=900)
    ap.add_argument("--set", action="append", metavar="KEY=VALUE", help="config override (repeatable)")
    args = ap.parse_args()
    data = Path(os.environ.get("MNEMOSLAM_DATA", ROOT.parent / "shared" / "data"))
    overrides = merge_overrides({"semantics": {"enabled": False}}, parse_sets(args.set))  # SLAM alone
    variants = [v for v in args.variants.split(",") if v]
    rows, tables, consistency = [], [], []
    for name, ds in opened(sequences(data, args.synthetic_frames), args.only):
        for variant in variants:
            config = load_config(overrides=merge_overrides(overrides, variant_overrides(variant)))
            out_dir = Path(os.environ.get("TMPDIR", "/tmp")) / "mnemoslam-bench-links"
            with Recorder() as rec:
                out = run_dataset(ds, config, out_dir=out_dir, progress=False)
            ev = evaluate(ds.ground_truth, out.trajectory)
            kinds = {t.kind: t for t in (out.links.types if out.links else [])}
            loops = [kinds[k] for k in ("loop", "proximity") if k in kinds]
            rows.append((name, variant, f"{ev.ate_rmse * 100:.2f}", out.summary.keyframes,
                         sum(t.count for t in loops), sum(t.beyond for t in loops), out.summary.links_dropped,
                         kinds["path"].count if "path" in kinds else 0))
            print("  ".join(map(str, rows[-1])), file=sys.stderr, flush=True)
            if args.links and variant == "default":
                tables.append((name, link_table(ds, out_dir / "map.db", rec.rows)))
            if args.links and variant in ("off", "default"):
                consistency.extend((name, *row) for row in consistency_table(ds, out_dir / "map.db", variant))
    print_table(("sequence", "variant", "ATE cm", "kf", "loop+prox links", "beyond 5 cm/3 deg", "dropped",
                 "path links"), rows)
    if consistency:
        print("\nlinks of the map against the ground truth and the σ their information claims (medians, cm / deg)")
        print_table(("sequence", "variant", "link type", "links", "error", "σ claimed", "error / σ"), consistency)
    for name, t in tables:
        print(f"\n{name}: loop / proximity links of the default run (cm / deg)")
        if t:
            print(reduction(t))
            print_table(("link", "stored as", "verified", "error before", "error after", "σ estimated", "σ claimed",
                    "inliers", "decision"), t)
    return 0


if __name__ == "__main__":
    sys.exit(main())
