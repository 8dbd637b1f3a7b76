"""Full synthetic runs through the offline pipeline: exact ground truth, no real data."""
import numpy as np

from mnemoslam.client.datasets import open_dataset
from mnemoslam.service.evaluation import evaluate
from mnemoslam.service.runner import run_dataset
from mnemoslam.storage import MapStore

from conftest import LEAN, slam_config


def _check(ds, out, out_dir, bound):
    n = len(ds)
    assert out.summary.tracked == n and out.summary.lost == 0
    ev = evaluate(ds.ground_truth, out.trajectory)
    # measured: whole loop noise-free 0.21 cm at 30 Hz and 15 Hz, 0.22 cm at 10 Hz, 0.197 cm at 5 Hz
    # (odometry alone 1.74 at 30 Hz, 1.28 at 5 Hz); with noise: first 20 s at 30 Hz ~0.2 cm, whole loop at 10 Hz 0.23 cm
    assert ev.ate_rmse < bound
    assert (out_dir / "trajectory.tum").read_text().count("\n") == n
    assert 0 < out.summary.keyframes < n
    with MapStore(out_dir / "map.db", create=False) as store:  # the same database the service writes
        assert store.count_nodes() == out.summary.keyframes
        assert store.integrity_check() == "ok"
        np.testing.assert_allclose(store.trajectory(store.sessions()[0].id).poses, out.keyframes.poses)


# issue #2: the synthetic loop, noise-free, ATE < 1 cm (the whole loop, at 5 Hz to save time:
# 301 frames, measured 0.197 cm, and 1.28 cm with loop closure off; `mnemoslam run
# synthetic:loop` plays it at 30 Hz, measured 0.21 cm, as at 10 Hz). Semantics and the occupancy
# grid off (tests/conftest.py `slam_config`): neither changes a pose (the same trajectory.tum, byte
# for byte, with the default configuration) and they were ~18 % of the run (fusing the scene's
# labels into objects, the keyframes' local grids and the run's map files)
def test_synthetic_loop_noise_free(tmp_path):
    ds = open_dataset("synthetic:loop", rate=5, noise=False)
    out = run_dataset(ds, slam_config(LEAN), tmp_path, progress=False)
    _check(ds, out, tmp_path, 0.01)


# ... with realistic depth noise < 3 cm: the whole loop at 10 Hz, the session's run that
# tests/test_loop_closure.py checks too (tests/conftest.py `loop_run`)
def test_synthetic_loop_with_depth_noise(loop_run):
    ds, out, cfg, out_dir = loop_run
    assert ds.noise and cfg == slam_config(LEAN)  # the default configuration, semantics and grid off
    _check(ds, out, out_dir, 0.03)
