"""Geometric verification of loop hypotheses on the synthetic scene's exact poses."""
import numpy as np

from mnemoslam.client.datasets import open_dataset
from mnemoslam.client.kernel.geometry import invert, rotation_angle
from mnemoslam.service.config import load_config
from mnemoslam.service.mapping.verification import verify
from mnemoslam.service.tracking.features import FeatureExtractor


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


def test_dense_view_gives_the_full_pyramids_coarse_levels():
    from mnemoslam.service.memory.views import DenseView
    from mnemoslam.service.tracking import icp
    ds = open_dataset("synthetic:loop", noise=True)
    f = ds.frame(3)
    cam = ds.calibration.camera
    full = icp.depth_pyramid(f.depth, cam, icp.STEPS, grey=f.grey)
    small = DenseView(f.depth, f.grey, cam).levels()
    assert small[-1].vertices.shape == (cam.height // 4, cam.width // 4, 3)
    for a, b in zip(full, small):
        np.testing.assert_allclose(a.vertices, b.vertices, rtol=1e-5, equal_nan=True)
        np.testing.assert_allclose(a.intensity[..., 0], b.intensity[..., 0], atol=1e-5)


def test_dense_refinement_makes_a_loop_link_an_order_of_magnitude_more_accurate():
    from mnemoslam.service.mapping.verification import refine
    from mnemoslam.service.memory.views import DenseView
    ds = open_dataset("synthetic:loop", noise=True)
    cam = ds.calibration.camera
    a = 0
    errors = []
    for b in (len(ds) - 25, len(ds) - 15, len(ds) - 5):  # 0.3-0.9 m from the loop's start
        fa, fb = _features(ds, a), _features(ds, b)
        v = verify(cam, fb.keypoints, fb.descriptors, fa.descriptors, fa.points)
        r = refine(v, DenseView(fb.depth, fb.grey, cam), DenseView(fa.depth, fa.grey, cam))
        truth = invert(ds.ground_truth.poses[a]) @ ds.ground_truth.poses[b]
        assert r.refined and r.accepted
        errors.append([np.linalg.norm((invert(truth) @ t)[:3, 3]) for t in (v.transform, r.transform)])
    pnp, dense = np.array(errors).T
    # measured: PnP 19, 2.3, 5.0 mm -> dense 0.05, 0.4, 0.6 mm
    assert dense.max() < 0.003, errors
    assert dense.mean() < 0.3 * pnp.mean(), errors


def test_refinement_keeps_the_pnp_link_when_the_images_do_not_overlap():
    from mnemoslam.service.mapping.verification import Verification, refine
    from mnemoslam.service.memory.views import DenseView
    ds = open_dataset("synthetic:loop", noise=True)
    cam = ds.calibration.camera
    fa, fb = ds.frame(0), ds.frame(len(ds) // 2)  # opposite sides of the loop
    T = invert(ds.ground_truth.poses[0]) @ ds.ground_truth.poses[len(ds) // 2]
    v = Verification(True, "ok", 50, 40, T, np.eye(6))
    r = refine(v, DenseView(fb.depth, fb.grey, cam), DenseView(fa.depth, fa.grey, cam))
    assert not r.refined and r.transform is T
