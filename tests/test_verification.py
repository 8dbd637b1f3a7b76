"""Geometric verification of loop hypotheses on the synthetic scene's exact poses."""
import numpy as np

from client.datasets import open_dataset
from client.geometry import invert, rotation_angle
from service.config import load_config
from service.features import FeatureExtractor
from service.verification import verify


def _features(ds, i):
    cfg = load_config()
    return FeatureExtractor(ds.calibration, cfg.features, cfg.stereo).extract(ds.frame(i))


def test_revisit_is_verified_with_the_true_transform():
    ds = open_dataset("synthetic:loop", noise=True)
    a, b = 0, len(ds) - 5  # the loop comes back to its start
    fa, fb = _features(ds, a), _features(ds, b)
    v = verify(ds.calibration.camera, fb.keypoints, fb.descriptors, fa.descriptors, fa.points)
    assert v.accepted and v.inliers >= 50
    truth = invert(ds.ground_truth.poses[a]) @ ds.ground_truth.poses[b]
    err = invert(truth) @ v.transform
    assert np.linalg.norm(err[:3, 3]) < 0.02 and np.degrees(rotation_angle(err[:3, :3])) < 1.0
    assert v.information.shape == (6, 6)


def test_different_places_are_rejected():
    ds = open_dataset("synthetic:loop")
    fa, fb = _features(ds, 0), _features(ds, len(ds) // 2)  # the other side of the loop
    v = verify(ds.calibration.camera, fb.keypoints, fb.descriptors, fa.descriptors, fa.points)
    assert not v.accepted and v.reason in ("few_matches", "few_inliers", "pnp_failed")
