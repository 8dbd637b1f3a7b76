"""Loop closure against ground truth: precision (true links / links), recall (revisiting
keyframes that got a loop link), loop-link errors and keyframe ATE with loops vs odometry
alone — both runs in this process on the same frames.

    python bench/bench_loop_closure.py                      # synthetic loop + figure8 + straight
    python bench/bench_loop_closure.py synthetic:loop 7scenes_redkitchen   # names or paths

Scoring is service.evaluation.evaluate_loops: a keyframe "revisits" when a keyframe at least
`loop.min_age` seconds older has its ground truth within 0.5 m and 30° of view direction
(places seen ≥ 10 s earlier); a link is true when within 10 cm / 5° of the truth.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mnemoslam.client.datasets import open_dataset  # noqa: E402
from mnemoslam.service.config import load_config  # noqa: E402
from mnemoslam.service.evaluation import evaluate, evaluate_map_loops  # noqa: E402
from mnemoslam.service.runner import run_dataset  # noqa: E402


def loop_report(ds, db: Path, min_age: float) -> dict:
    r = evaluate_map_loops(ds.ground_truth, db, min_age)
    return {"links": r.links, "false": r.false_links, "precision": r.precision, "revisits": r.revisits,
            "recall": r.recall, "link_err_cm_p50": r.link_error_median * 100, "link_err_cm_max": r.link_error_max * 100}


def run(spec: str) -> dict:
    data = Path(os.environ.get("MNEMOSLAM_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
    path = spec if spec.startswith("synthetic:") or Path(spec).exists() else str(data / spec)
    opts = {"rate": 15, "noise": True} if path.startswith("synthetic:") else {}
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        for enabled in (False, True):
            ds = open_dataset(path, **opts)
            cfg = load_config(overrides={"loop": {"enabled": enabled}})
            r = run_dataset(ds, cfg, Path(tmp) / str(enabled), progress=True)
            out["ate_slam" if enabled else "ate_odom"] = evaluate(ds.ground_truth, r.keyframes).ate_rmse * 100
            out["fps_slam" if enabled else "fps_odom"] = r.summary.fps
            if enabled:
                out.update(loop_report(ds, Path(tmp) / "True" / "map.db", cfg.loop.min_age))
    out["ratio"] = out["ate_slam"] / out["ate_odom"]
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("sequences", nargs="*", default=["synthetic:loop", "synthetic:figure8", "synthetic:straight"])
    args = p.parse_args()
    rows = []
    for spec in args.sequences:
        rows.append((spec, run(spec)))
    print(f"\n{'sequence':28s} {'ATE odom':>9s} {'ATE slam':>9s} {'ratio':>6s} {'links':>6s} {'false':>6s} "
          f"{'revisits':>8s} {'recall':>7s} {'err p50':>8s} {'err max':>8s} {'fps':>6s}")
    for spec, r in rows:
        print(f"{spec:28s} {r['ate_odom']:8.2f}c {r['ate_slam']:8.2f}c {r['ratio']:6.2f} {r['links']:6d} "
              f"{r['false']:6d} {r['revisits']:8d} {r['recall']:7.2f} {r['link_err_cm_p50']:7.2f}c "
              f"{r['link_err_cm_max']:7.2f}c {r['fps_slam']:6.1f}")


if __name__ == "__main__":
    main()
