"""The grid's up direction against the accelerometer's gravity on a TUM sequence with an
`accelerometer.txt` (issue 25: "on TUM fr1/desk the up direction found from the floor agrees
with the accelerometer's gravity within 3°").

    .venv/bin/python bench/grid_up.py [DATASET] [--poses trajectory.tum] [--every 5] [--frames START:END]

Replays the local grids of every `--every`-th frame (as the keyframe writer makes them, with the
player's `extras["accel"]`) at the poses of `--poses` (a run's `trajectory.tum`: the camera's
own frame; default the dataset's ground truth, whose camera orientation is ~3° off the depth
camera's on fr1/desk, docs/data.md) and prints, over the frames where a floor was found in depth,
the angle between that floor's normal and

- the frame's own accelerometer reading (a handheld camera's accelerations tilt it),
- the grid's up (the session's accelerometer gravity so far, `up_source` "accelerometer"),
- the session's final accelerometer gravity,

as median / p90 / worst, then the session's mean floor against its mean gravity (the map's
figure), and the same replay without the accelerometer (the floor-only up of before).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def replay(ds, poses, frames, use_accel: bool):
    from mnemoslam.service.config import GridConfig
    from mnemoslam.service.grid.local import LocalGridMaker, angle_deg

    mk = LocalGridMaker(ds.calibration.camera, GridConfig())
    rows = []
    for i in frames:
        f = ds.frame(i)
        accel = f.extras.get("accel")
        g = mk.make(f.depth, poses[i], 0, accel=accel if use_accel else None)
        rows.append((g, accel, poses[i][:3, :3]))
    fl = [(g, a, R) for g, a, R in rows if g.floor_up is not None]
    out = {"keyframes": len(rows), "floors": len(fl),
           "sources": {s: sum(g.up_source == s for g, _, _ in rows) for s in sorted({g.up_source for g, _, _ in rows})}}
    if fl and all(a is not None for _, a, _ in fl):
        out["reading"] = [angle_deg(g.floor_up, a) for g, a, _ in fl]
    out["grid_up"] = [angle_deg(g.floor_up, g.up) for g, _, _ in fl]
    if mk.gravity_up is not None:
        out["final"] = [angle_deg(g.floor_up, R.T @ mk.gravity_up) for g, _, R in fl]
        if mk.floor_up is not None:
            out["map"] = angle_deg(mk.floor_up, mk.gravity_up)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset", nargs="?", default=str(ROOT.parent / "shared/data/rgbd_dataset_freiburg1_desk"))
    ap.add_argument("--poses", help="a TUM trajectory of the frames (a run's trajectory.tum); default the ground truth")
    ap.add_argument("--every", type=int, default=5)
    ap.add_argument("--frames", default=":", help="START:END of the frames replayed")
    a = ap.parse_args(argv)
    from mnemoslam.client.datasets import open_dataset
    from mnemoslam.client.kernel.trajectory import read_tum
    from mnemoslam.service.evaluation import associate_stamps

    ds = open_dataset(a.dataset)
    if a.poses:
        tr = read_tum(a.poses)
        it, idx = associate_stamps(tr.stamps, ds.stamps, max_dt=0.005)
        poses = {int(j): tr.poses[k] for k, j in zip(it, idx)}
        src = a.poses
    else:
        poses = dict(enumerate(ds.ground_truth.poses))
        src = "ground truth"
    lo, _, hi = a.frames.partition(":")
    frames = [i for i in range(int(lo or 0), int(hi or len(ds)), a.every) if i in poses]
    print(f"{ds.name}: {len(frames)} frames (every {a.every}th), poses: {src}")
    for use in (True, False):
        r = replay(ds, poses, frames, use)
        print(f"\n{'with' if use else 'without'} the accelerometer: {r['keyframes']} grids, up_source {r['sources']}, "
              f"a floor found in {r['floors']}")
        for key, what in (("reading", "its own accelerometer reading"), ("grid_up", "the grid's up"),
                          ("final", "the session's final gravity")):
            if key in r and r[key]:
                v = np.asarray(r[key])
                print(f"  floor normal vs {what:30s} median {np.median(v):5.2f}°  p90 {np.percentile(v, 90):5.2f}°  "
                      f"worst {v.max():5.2f}°")
        if "map" in r:
            print(f"  session's mean floor vs its mean gravity: {r['map']:.2f}°")
    return 0


if __name__ == "__main__":
    sys.exit(main())
