"""Full synthetic runs through the offline pipeline: exact ground truth, no real data."""
import numpy as np
import pytest

from client.datasets import open_dataset
from service.config import load_config
from service.evaluation import evaluate
from service.runner import run_dataset
from storage import MapStore


# issue #2: the synthetic loop, noise-free, ATE < 1 cm (the whole loop at 30 Hz, as `mnemoslam
# run synthetic:loop` runs it); with realistic depth noise < 3 cm (its first 20 s, to save time)
@pytest.mark.parametrize("noise,frames,bound", [(False, None, 0.01), (True, 600, 0.03)])
def test_synthetic_loop(noise, frames, bound, tmp_path):
    ds = open_dataset("synthetic:loop", max_frames=frames, noise=noise)
    n = len(ds)
    out = run_dataset(ds, load_config(), tmp_path, progress=False)
    assert out.summary.tracked == n and out.summary.lost == 0
    ev = evaluate(ds.ground_truth, out.trajectory)
    # measured: whole loop noise-free 0.21 cm (odometry alone 1.74); first 20 s with noise ~0.2 cm
    assert ev.ate_rmse < bound
    assert (tmp_path / "trajectory.tum").read_text().count("\n") == n
    assert 0 < out.summary.keyframes < n
    with MapStore(tmp_path / "map.db", create=False) as store:  # the same database the service writes
        assert store.count_nodes() == out.summary.keyframes
        assert store.integrity_check() == "ok"
        np.testing.assert_allclose(store.trajectory(store.sessions()[0].id).poses, out.keyframes.poses)
