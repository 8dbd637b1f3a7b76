"""Trajectory evaluation: association, Umeyama alignment, ATE, RPE, file helper."""
import json

import numpy as np
import pytest

from mnemoslam.client.kernel.geometry import invert, make_pose, rodrigues
from mnemoslam.client.kernel.trajectory import Trajectory, write_tum
from mnemoslam.service.evaluation import associate_stamps, evaluate, evaluate_files, umeyama


def random_rotation(rng) -> np.ndarray:
    return rodrigues(rng.normal(size=3))


def smooth_trajectory(n=60, seed=0, dt=0.1) -> Trajectory:
    """A wandering camera: small random rotations and ~0.3 m steps between frames."""
    rng = np.random.default_rng(seed)
    poses = [np.eye(4)]
    for _ in range(n - 1):
        R = rodrigues(rng.normal(scale=0.1, size=3))
        step = make_pose(R, rng.normal(scale=0.2, size=3) + [0.3, 0, 0])
        poses.append(poses[-1] @ step)
    return Trajectory(np.arange(n) * dt + 1000.0, np.array(poses))


# --- Umeyama -------------------------------------------------------------------------------------

def test_umeyama_recovers_rigid_and_similarity():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(50, 3))
    R0, t0 = random_rotation(rng), rng.normal(size=3)

    R, t, s = umeyama(src, src @ R0.T + t0, with_scale=False)
    np.testing.assert_allclose(R, R0, atol=1e-10)
    np.testing.assert_allclose(t, t0, atol=1e-10)
    assert s == 1.0

    dst = 2.5 * src @ R0.T + t0
    R, t, s = umeyama(src, dst, with_scale=True)
    np.testing.assert_allclose(R, R0, atol=1e-10)
    np.testing.assert_allclose(t, t0, atol=1e-10)
    assert s == pytest.approx(2.5, abs=1e-12)
    assert umeyama(src, dst, with_scale=False)[2] == 1.0


def test_umeyama_reflection_gives_proper_rotation():
    rng = np.random.default_rng(2)
    src = rng.normal(size=(20, 3))
    R, _, _ = umeyama(src, src * [1, 1, -1], with_scale=False)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)


def test_umeyama_degenerate_inputs():
    with pytest.raises(ValueError, match="at least 3"):
        umeyama(np.zeros((2, 3)), np.zeros((2, 3)), with_scale=True)
    rng = np.random.default_rng(3)
    line = np.outer(np.linspace(0, 4, 10), [1.0, 2.0, -0.5])
    R0, t0 = random_rotation(rng), rng.normal(size=3)
    R, t, s = umeyama(line, line @ R0.T + t0, with_scale=True)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(s * line @ R.T + t, line @ R0.T + t0, atol=1e-9)
    # identical points: no spread, scale falls back to 1, translation maps the point
    same = np.tile([1.0, 2.0, 3.0], (5, 1))
    R, t, s = umeyama(same, same + 1.0, with_scale=True)
    assert s == 1.0 and np.all(np.isfinite(R)) and np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(same @ R.T + t, same + 1.0, atol=1e-12)


# --- association ---------------------------------------------------------------------------------

def test_associate_jitter_missing_and_max_dt():
    rng = np.random.default_rng(4)
    gt = np.arange(100) * 0.1
    est = gt + rng.uniform(-0.01, 0.01, size=100)
    i_gt, i_est = associate_stamps(gt, est, max_dt=0.02)
    np.testing.assert_array_equal(i_gt, np.arange(100))
    np.testing.assert_array_equal(i_est, np.arange(100))

    keep = np.sort(rng.choice(100, size=70, replace=False))
    i_gt, i_est = associate_stamps(gt, est[keep], max_dt=0.02)
    np.testing.assert_array_equal(i_gt, keep)
    np.testing.assert_array_equal(i_est, np.arange(70))

    shifted = gt + 0.03
    assert len(associate_stamps(gt, shifted, max_dt=0.02)[0]) == 0
    assert len(associate_stamps(gt, shifted, max_dt=0.04)[0]) == 100


def test_associate_one_to_one_prefers_smallest_dt_and_sorts_by_estimate():
    gt = np.array([0.0, 1.0, 2.0])
    est = np.array([2.004, 1.01, 0.99, 1.002, 5.0])      # three estimates near gt 1.0, one far away
    i_gt, i_est = associate_stamps(gt, est, max_dt=0.02)
    np.testing.assert_array_equal(i_est, [3, 0])          # 1.002 wins gt 1.0; ordered by est stamp
    np.testing.assert_array_equal(i_gt, [1, 2])
    assert associate_stamps([], est)[0].size == 0


# --- ATE -----------------------------------------------------------------------------------------

def test_noise_free_estimate_in_other_frame_has_zero_ate():
    gt = smooth_trajectory()
    rng = np.random.default_rng(5)
    T = make_pose(random_rotation(rng), rng.normal(size=3) * 5)
    est = Trajectory(gt.stamps + rng.uniform(-0.005, 0.005, len(gt)), T @ gt.poses)
    res = evaluate(gt, est, align="se3")
    assert (res.matched, res.gt_count, res.est_count) == (len(gt), len(gt), len(gt))
    assert res.ate_rmse < 1e-9 and res.ate_max < 1e-9
    assert res.scale == 1.0
    assert res.rpe_trans_rmse < 1e-9 and res.rpe_rot_rmse < 1e-9
    assert res.path_length == pytest.approx(gt.path_length())

    # monocular-style: estimate at 0.4 x scale -> sim3 recovers 2.5 and zero error
    scaled = est.poses.copy()
    scaled[:, :3, 3] *= 0.4
    res = evaluate(gt, Trajectory(est.stamps, scaled), align="sim3")
    assert res.scale == pytest.approx(2.5, rel=1e-9)
    assert res.ate_rmse < 1e-9 and res.rpe_trans_rmse < 1e-9
    assert evaluate(gt, Trajectory(est.stamps, scaled), align="se3").ate_rmse > 0.1


def test_constant_offset_on_some_poses_gives_expected_ate():
    gt = smooth_trajectory(n=40)
    est = Trajectory(gt.stamps, gt.poses.copy())
    bad = np.arange(0, 40, 4)                              # 10 of 40 poses
    offset = np.array([0.06, 0.0, -0.08])                  # 0.1 m
    est.poses[bad, :3, 3] += offset
    res = evaluate(gt, est, align="none")
    assert res.ate_rmse == pytest.approx(0.1 * np.sqrt(10 / 40))
    assert res.ate_mean == pytest.approx(0.1 * 10 / 40)
    assert res.ate_max == pytest.approx(0.1)
    assert res.ate_median == pytest.approx(0.0)
    assert res.ate_percent_of_path == pytest.approx(100 * res.ate_rmse / res.path_length)

    est_all = gt.transformed(T_left=make_pose(np.eye(3), offset))
    assert evaluate(gt, est_all, align="none").ate_rmse == pytest.approx(0.1)
    assert evaluate(gt, est_all, align="se3").ate_rmse < 1e-9


# --- RPE -----------------------------------------------------------------------------------------

def test_rpe_of_scaled_and_rotated_relative_motions():
    gt = smooth_trajectory(n=30, seed=7)
    rel = invert(gt.poses[:-1]) @ gt.poses[1:]

    def integrate(steps):
        poses = [gt.poses[0]]
        for s in steps:
            poses.append(poses[-1] @ s)
        return Trajectory(gt.stamps, np.array(poses))

    longer = rel.copy()
    longer[:, :3, 3] *= 1.1                                # every step 10 % too long
    est = integrate(longer)
    res = evaluate(gt, est, align="none")
    expected = 0.1 * np.linalg.norm(rel[:, :3, 3], axis=1)
    assert res.rpe_trans_rmse == pytest.approx(np.sqrt(np.mean(expected ** 2)))
    assert res.rpe_rot_rmse < 1e-9
    # RPE does not depend on the rigid alignment
    assert evaluate(gt, est, align="se3").rpe_trans_rmse == pytest.approx(res.rpe_trans_rmse)

    # delta = 2: the two-step motion is also 10 % too long
    two = invert(gt.poses[:-2]) @ gt.poses[2:]
    res2 = evaluate(gt, est, align="none", rpe_delta=2)
    assert res2.rpe_delta == 2
    two_err = 0.1 * np.linalg.norm(two[:, :3, 3], axis=1)
    assert res2.rpe_trans_rmse == pytest.approx(np.sqrt(np.mean(two_err ** 2)))

    turned = rel.copy()
    turned[:, :3, :3] = turned[:, :3, :3] @ rodrigues(np.radians([0.0, 0.0, 2.0]))  # 2 deg extra yaw
    res = evaluate(gt, integrate(turned), align="none")
    assert res.rpe_rot_rmse == pytest.approx(2.0)
    assert res.rpe_trans_rmse < 1e-9


# --- errors --------------------------------------------------------------------------------------

def test_too_few_matches_and_bad_arguments_raise():
    gt = smooth_trajectory(n=10)
    with pytest.raises(ValueError, match="only 2 poses matched"):
        evaluate(gt, Trajectory(gt.stamps[:2], gt.poses[:2]))
    with pytest.raises(ValueError, match="only 0 poses matched"):
        evaluate(gt, Trajectory(gt.stamps + 50.0, gt.poses))
    with pytest.raises(ValueError, match="unknown alignment"):
        evaluate(gt, gt, align="affine")
    with pytest.raises(ValueError, match="rpe_delta"):
        evaluate(gt, gt, rpe_delta=10)


# --- files ---------------------------------------------------------------------------------------

def test_evaluate_files_text_and_json(tmp_path):
    gt = smooth_trajectory(n=50)
    est = Trajectory(gt.stamps + 0.003, gt.poses.copy())
    est.poses[::5, :3, 3] += [0.05, 0.0, 0.0]
    write_tum(tmp_path / "gt.txt", gt)
    write_tum(tmp_path / "est.txt", est)

    text = evaluate_files(tmp_path / "gt.txt", tmp_path / "est.txt", align="se3", max_dt=0.02, as_json=False)
    d = json.loads(evaluate_files(tmp_path / "gt.txt", tmp_path / "est.txt", "se3", 0.02, as_json=True))
    assert "ATE" in text and "RPE" in text and "50 poses" in text
    for key in ("ate_rmse", "ate_max", "rpe_trans_rmse", "path_length"):
        assert f"{d[key]:.6f}" in text
    assert d["ate_rmse"] == pytest.approx(evaluate(gt, est, align="se3").ate_rmse, abs=1e-5)

    d = json.loads(evaluate_files(tmp_path / "gt.txt", tmp_path / "est.txt", align="sim3", max_dt=0.02,
                                  as_json=True))
    assert {"ate_rmse", "rpe_trans_rmse", "matched"} <= d.keys()
    assert d["matched"] == 50 and d["align"] == "sim3"
    assert d["ate_rmse"] == pytest.approx(evaluate(gt, est, align="sim3").ate_rmse, abs=1e-5)


def test_evaluate_files_kitti_ground_truth(tmp_path):
    gt = smooth_trajectory(n=20, dt=0.1)
    np.savetxt(tmp_path / "00.txt", gt.poses[:, :3, :4].reshape(-1, 12))
    write_tum(tmp_path / "est.txt", Trajectory(np.arange(20) * 0.1, gt.poses))
    d = json.loads(evaluate_files(tmp_path / "00.txt", tmp_path / "est.txt", "se3", 0.02, True))
    assert d["matched"] == 20 and d["ate_rmse"] < 1e-5


def test_loop_links_are_scored_against_ground_truth():
    from mnemoslam.client.kernel.geometry import look_at
    from mnemoslam.service.evaluation import evaluate_loops
    # A camera that goes round a 2 m circle in 40 s (1 Hz keyframes) and comes back.
    t = np.arange(41.0)
    ang = 2 * np.pi * t / 40
    eye = np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], 1)
    poses = np.stack([look_at(e, e + [-np.sin(a), np.cos(a), 0]) for e, a in zip(eye, ang)])
    gt = Trajectory(t, poses)
    rel = lambda a, b: invert(poses[a]) @ poses[b]  # noqa: E731
    off = make_pose(np.eye(3), [0.3, 0, 0])  # a 30 cm error: a false link
    links = [(0, 40, rel(0, 40)), (1, 39, rel(1, 39) @ make_pose(np.eye(3), [0.01, 0, 0])), (5, 20, rel(5, 20) @ off)]
    r = evaluate_loops(gt, np.arange(41), t, links, min_age=10.0)
    assert (r.links, r.false_links) == (3, 1) and r.precision == pytest.approx(2 / 3)
    # revisits (≥ 10 s after a keyframe within 0.5 m and 30°; 0.16 m and 9° per step): 37-40
    assert r.revisits == 4 and r.recalled == 2 and r.recall == pytest.approx(0.5)
    assert r.link_error_median == pytest.approx(0.01, abs=1e-9) and r.link_error_max == pytest.approx(0.3)
    assert "precision" in r.format()


def test_loop_report_without_loops_says_so():
    from mnemoslam.service.evaluation import evaluate_loops
    # a straight path: no keyframe comes back, and no loop link
    t = np.arange(30.0)
    poses = np.stack([make_pose(np.eye(3), [0.5 * k, 0, 0]) for k in range(30)])
    r = evaluate_loops(Trajectory(t, poses), np.arange(30), t, [], min_age=10.0)
    assert (r.links, r.revisits) == (0, 0)
    text = r.format()
    assert "no loop links" in text and "no true revisits" in text
    assert "nan" not in text and "0/0" not in text and "precision" not in text and "recall" not in text
    # revisits but no link: recall is a real 0, link errors are not shown
    t = np.arange(41.0)
    back = np.stack([make_pose(np.eye(3), [0.1 * min(k, 40 - k), 0, 0]) for k in range(41)])
    r = evaluate_loops(Trajectory(t, back), np.arange(41), t, [], min_age=10.0)
    assert r.revisits > 0 and r.recalled == 0
    text = r.format()
    assert "no loop links" in text and f"recall 0.000 (0/{r.revisits}" in text and "nan" not in text


def test_link_report_per_type_with_a_perturbed_link(tmp_path):
    from mnemoslam.service.evaluation import LINK_CSV_COLUMNS, evaluate_links
    gt = smooth_trajectory(20, seed=3)
    P = gt.poses
    rel = lambda a, b: invert(P[a]) @ P[b]  # noqa: E731
    ids = np.arange(20) + 100  # node ids are not row numbers
    links = [(100 + k, 101 + k, 0, rel(k, k + 1)) for k in range(19)]  # exact odometry
    links[4] = (104, 105, 0, rel(4, 5) @ make_pose(np.eye(3), [0.0, 0.02, 0.0]))  # one 2 cm off
    turn = make_pose(rodrigues([0.0, np.radians(4.0), 0.0]), [0.0, 0.0, 0.0])
    links += [(100, 110, 1, rel(0, 10) @ make_pose(np.eye(3), [0.06, 0.0, 0.0])),  # loop 6 cm off
              (102, 112, 2, rel(2, 12) @ turn),  # proximity 4 deg off
              (103, 113, 2, rel(3, 13)),
              (105, 999, 2, np.eye(4))]  # a node without ground truth: left out, counted
    stamps = gt.stamps.copy()
    stamps[19] += 5.0  # node 119 has no ground truth pose within max_dt: the odometry link 118 -> 119 is left out
    r = evaluate_links(gt, ids, stamps, links)
    kinds = r.by_kind()
    assert list(kinds) == ["odometry", "loop", "proximity"]
    odo, loop, prox = kinds["odometry"], kinds["loop"], kinds["proximity"]
    assert (odo.count, odo.unmatched, odo.beyond) == (18, 1, 0)  # 104 -> 105 is 2 cm off: within 5 cm
    assert odo.max_cm == pytest.approx(2.0, abs=1e-6) and odo.median_cm < 1e-6
    assert (loop.count, loop.beyond) == (1, 1) and loop.median_cm == pytest.approx(6.0, abs=1e-6)
    assert loop.max_deg < 1e-4
    assert (prox.count, prox.unmatched, prox.beyond) == (2, 1, 1)
    assert prox.max_deg == pytest.approx(4.0, abs=1e-6) and prox.max_cm < 1e-6
    text = r.format()
    assert "loop" in text and "6.00 cm" in text and "1 beyond 5 cm or 3 deg" in text and "nan" not in text
    r.write(tmp_path)
    lines = (tmp_path / "links.csv").read_text().splitlines()
    assert lines[0] == ",".join(LINK_CSV_COLUMNS) and len(lines) == 1 + 18 + 1 + 2
    assert "100,110,loop,6.0000,0.0000" in lines
    summary = json.loads((tmp_path / "links.json").read_text())
    assert [t["kind"] for t in summary["types"]] == ["odometry", "loop", "proximity"]
    assert summary["types"][2]["unmatched"] == 1
