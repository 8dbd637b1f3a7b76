"""Stereo visual odometry on the KITTI snippets: every frame tracked, drift bounds, and the
depth uncertainty that weighs far stereo points in pose refinement.

Sequence b's stereo pair disagrees with its ground truth by a disparity offset of about
1 px (far hills measure a negative disparity; fitting an offset to frame pairs under the
ground-truth motion gives 1.3 px, 0.3 px for a), which stretches the odometry's scale by
~5 %: the issue #2 target of < 1 % of path on b is not met yet (measured 1.6 %)."""
import numpy as np
import pytest
from conftest import require

from client.datasets import open_dataset
from service.config import load_config
from service.evaluation import evaluate
from service.features import FeatureExtractor
from service.runner import run_dataset

pytestmark = pytest.mark.data


@pytest.mark.parametrize("name,max_percent", [("a", 0.45), ("b", 2.0)])
def test_kitti_every_frame_tracked(data_dir, name, max_percent):
    ds = open_dataset(require(data_dir / "kitti_odometry_snippets" / "sequences" / name))
    out = run_dataset(ds, load_config(), progress=False)
    assert out.summary.tracked == 51 and out.summary.lost == 0 and out.summary.segments == 1
    # measured a: 0.30 %, b: 1.58 % of path (before: 0.30 % and 2.0 % with 4 frames lost)
    assert evaluate(ds.ground_truth, out.trajectory).ate_percent_of_path < max_percent


def test_stereo_depth_uncertainty_grows_with_the_square_of_depth(data_dir):
    ds = open_dataset(require(data_dir / "kitti_odometry_snippets" / "sequences" / "a"), max_frames=1)
    cfg = load_config()
    ex = FeatureExtractor(ds.calibration, cfg.features, cfg.stereo)
    assert ex.max_features > cfg.features.max_features  # a 1226×370 image gets more keypoints than 640×480
    f = ex.extract(ds.frame(0))
    ok = f.has_depth
    assert ok.sum() > 200
    z = f.points[ok, 2].astype(np.float64)
    cam = ds.calibration.camera
    expected = z ** 2 * cfg.stereo.disparity_sigma / (cam.fx * ds.calibration.baseline)
    np.testing.assert_allclose(f.depth_sigma[ok], expected, rtol=1e-5)
    assert np.isnan(f.depth_sigma[~ok]).all()
