"""PoseGraph (service/mapping/graph.py): iSAM2 pose graph with loop links and the graph-error check."""
from __future__ import annotations

import threading

import gtsam
import numpy as np
import pytest

from mnemoslam.service.mapping.graph import PoseGraph, normalized_errors, se3_log

SIGMAS = np.array([np.deg2rad(0.5)] * 3 + [0.01] * 3)  # odometry σ: rotation first
INFO = np.diag(1.0 / SIGMAS**2)
LOOP_SIGMAS = np.array([np.deg2rad(0.5)] * 3 + [0.01] * 3)
LOOP_INFO = np.diag(1.0 / LOOP_SIGMAS**2)


def exp(xi) -> np.ndarray:
    return gtsam.Pose3.Expmap(np.asarray(xi, dtype=np.float64)).matrix()


def inv(t):
    return np.linalg.inv(t)


def square(side: int = 10, step: float = 0.5, origin=np.eye(4)) -> list[np.ndarray]:  # noqa: B008 - only copied
    """Camera-to-world poses around a square (4·side steps; the last pose is back at the start)."""
    poses = [origin.copy()]
    fwd, turn = exp([0, 0, 0, step, 0, 0]), exp([0, 0, np.pi / 2, 0, 0, 0])
    for k in range(4 * side):
        nxt = poses[-1] @ fwd
        if (k + 1) % side == 0:
            nxt = nxt @ turn
        poses.append(nxt)
    return poses


def noisy_odometry(truth, rng, bias_yaw=np.deg2rad(0.4), noise=0.3):  # noqa: B008 - a float
    """Relative motions with a constant yaw bias (a drifting gyro) plus noise of noise·σ."""
    out = []
    for a, b in zip(truth[:-1], truth[1:]):
        xi = rng.normal(size=6) * SIGMAS * noise
        xi[2] += bias_yaw
        out.append(inv(a) @ b @ exp(xi))
    return out


def build(truth, odo, graph=None, first_id=0, start=None):
    g = graph if graph is not None else PoseGraph()
    g.add_node(first_id, truth[0] if start is None else start)
    for i, t in enumerate(odo):
        g.add_node(first_id + i + 1, np.eye(4), odom_from=first_id + i, transform=t, information=INFO)
    return g


def ate(est: dict, truth, first_id=0) -> float:
    return float(np.sqrt(np.mean([np.sum((est[first_id + i][:3, 3] - t[:3, 3]) ** 2) for i, t in enumerate(truth)])))


def loop_measurement(truth, i, j, rng, noise=0.3):
    xi = rng.normal(size=6) * LOOP_SIGMAS * noise
    return inv(truth[i]) @ truth[j] @ exp(xi)


def max_diff(a: dict, b: dict) -> float:
    return max(float(np.abs(a[k] - b[k]).max()) for k in a)


@pytest.fixture
def scene():
    rng = np.random.default_rng(7)
    truth = square()
    odo = noisy_odometry(truth, rng)
    return truth, odo, rng


def test_log_and_normalized_error_match_gtsam():
    rng = np.random.default_rng(1)
    for _ in range(20):
        p = gtsam.Pose3.Expmap(rng.normal(size=6) * rng.uniform(0.01, 2.0))
        assert np.allclose(se3_log(p.matrix()[None])[0], gtsam.Pose3.Logmap(p), atol=1e-9)
    a, b, m = (exp(rng.normal(size=6)) for _ in range(3))
    f = gtsam.BetweenFactorPose3(1, 2, gtsam.Pose3(m), gtsam.noiseModel.Gaussian.Information(INFO))
    v = gtsam.Values()
    v.insert(1, gtsam.Pose3(a))
    v.insert(2, gtsam.Pose3(b))
    e = f.unwhitenedError(v)
    expect = max(np.sqrt(e[:3] @ INFO[:3, :3] @ e[:3]), np.sqrt(e[3:] @ INFO[3:, 3:] @ e[3:]))
    assert normalized_errors(a[None], b[None], m[None], INFO[None])[0] == pytest.approx(expect, rel=1e-9)


def test_odometry_chain_follows_odometry(scene):
    truth, odo, _ = scene
    g = build(truth, odo)
    assert len(g) == len(truth)
    dead = [truth[0]]
    for t in odo:
        dead.append(dead[-1] @ t)
    est = g.poses()
    assert max(float(np.abs(est[i] - d).max()) for i, d in enumerate(dead)) < 1e-6
    assert np.allclose(g.pose(5), est[5])
    assert ate(est, truth) > 0.3  # the drift the loop must remove


def test_correct_loop_removes_drift(scene):
    truth, odo, rng = scene
    g = build(truth, odo)
    n = len(truth) - 1
    before = g.poses()
    ate0 = ate(before, truth)
    end_err0 = np.linalg.norm((inv(before[n]) @ before[0])[:3, 3] - (inv(truth[n]) @ truth[0])[:3, 3])
    out = g.add_loop(n, 0, loop_measurement(truth, n, 0, rng), LOOP_INFO)
    assert out.accepted, out
    assert out.error_before > 20 and out.error_after <= 3.0 and out.max_normalized_error <= 3.0
    est = g.poses()
    ate1 = ate(est, truth)
    assert ate1 < ate0 / 5, (ate0, ate1)
    rel = inv(est[n]) @ est[0]
    end_err = np.linalg.norm(rel[:3, 3] - (inv(truth[n]) @ truth[0])[:3, 3])
    assert end_err < 0.02 < end_err0  # 1 cm σ of the loop link: at the noise level
    assert g.loops() == [(n, 0)]


def test_wrong_loop_is_rejected_and_poses_unchanged(scene):
    truth, odo, rng = scene
    g = build(truth, odo)
    n = len(truth) - 1
    before = g.poses()
    # 2 m sideways. (2 m along z passes the check here: tilting the square by ~20° costs the
    # 40 odometry links only ~1 σ each with σ = 0.5° — the check is only as strict as the σ.)
    wrong = loop_measurement(truth, n, 0, rng) @ exp([0, 0, 0, 0, 2.0, 0])
    out = g.add_loop(n, 0, wrong, LOOP_INFO)
    assert not out.accepted
    assert "σ" in out.reason and out.max_normalized_error > 3.0
    assert max_diff(before, g.poses()) < 1e-6
    assert g.loops() == []
    # the graph keeps working: more odometry and a correct loop afterwards
    assert g.add_loop(n, 0, loop_measurement(truth, n, 0, rng), LOOP_INFO).accepted
    assert ate(g.poses(), truth) < ate(before, truth) / 5


def test_robust_kernel_limits_damage_of_wrong_link(scene):
    truth, odo, rng = scene
    n = len(truth) - 1
    good = loop_measurement(truth, n, 0, rng)
    bad = loop_measurement(truth, n // 2, 0, rng) @ exp([0, 0, 0, 0.8, 0.6, 0])  # 1 m off
    results = {}
    for robust in (False, "huber", "cauchy"):
        g = build(truth, odo, PoseGraph(max_error=0))
        assert g.add_loop(n, 0, good, LOOP_INFO).accepted
        out = g.add_loop(n // 2, 0, bad, LOOP_INFO, robust=robust)
        assert out.accepted and out.reason.startswith("accepted (check disabled)")
        results[robust] = ate(g.poses(), truth)
    assert results["huber"] < results[False] * 0.85, results  # Huber bounds the pull
    assert results["cauchy"] < results[False] * 0.25, results  # Cauchy nearly ignores it


def test_second_segment_pulled_into_place_by_loop(scene):
    truth, odo, rng = scene
    g = build(truth, odo[:20])
    # second session: same square walked again, odometry restarted in its own frame, ids go on
    rng2 = np.random.default_rng(3)
    truth2 = truth
    odo2 = noisy_odometry(truth2, rng2, bias_yaw=0.0)
    start = exp([0.3, -0.2, 1.0, 5.0, -3.0, 0.5])  # arbitrary odometry frame
    build(truth2, odo2[:10], graph=g, first_id=100, start=start)
    assert np.abs(g.pose(100) - start).max() < 1e-6  # loose prior: stays where odometry put it
    out = g.add_loop(105, 5, loop_measurement(truth, 5, 5, rng), LOOP_INFO)
    assert out.accepted, out
    est = g.poses()
    assert np.linalg.norm(est[100][:3, 3] - start[:3, 3]) > 5  # moved from where odometry put it
    for k in range(11):  # now where the first segment says (relative to the loop's anchor)
        rel, true_rel = inv(est[5]) @ est[100 + k], inv(truth[5]) @ truth[k]
        assert np.linalg.norm(rel[:3, 3] - true_rel[:3, 3]) < 0.03
        assert np.allclose(rel[:3, :3], true_rel[:3, :3], atol=0.02)
    # the first segment hardly moved (tight prior, loose second segment)
    assert np.linalg.norm(est[0][:3, 3] - truth[0][:3, 3]) < 1e-4


def test_incremental_equals_batch(scene):
    truth, odo, rng = scene
    g = build(truth, odo)
    n = len(truth) - 1
    assert g.add_loop(n, 0, loop_measurement(truth, n, 0, rng), LOOP_INFO, robust=False).accepted
    assert g.add_loop(n - 10, 10, loop_measurement(truth, n - 10, 10, rng), LOOP_INFO, robust=False).accepted
    for i in range(5):  # keep going after the loops
        g.add_node(n + 1 + i, np.eye(4), odom_from=n + i, transform=odo[i], information=INFO)
    inc = g.poses()
    batch = g.batch_optimize()
    assert max_diff(inc, batch) < 1e-4


def test_remove_loop_and_changed_poses(scene):
    truth, odo, rng = scene
    g = build(truth, odo)
    n = len(truth) - 1
    first = g.changed_poses()
    assert set(first) == set(range(n + 1))
    assert g.changed_poses() == {}
    before = g.poses()
    assert g.add_loop(n, 0, loop_measurement(truth, n, 0, rng), LOOP_INFO).accepted
    moved = g.changed_poses()
    assert 0 not in moved and n in moved and len(moved) > n // 2  # the tight-prior node stays
    for k, p in moved.items():
        assert p.shape == (4, 4) and not np.allclose(p, before[k], atol=1e-4)
    assert g.remove_loop(0, n) == 1 and g.loops() == []
    assert max_diff(before, g.poses()) < 1e-5


def test_replace_loop_in_one_update(scene):
    """add_loop(..., replace=T_old): the new measurement takes the old link's place (one link,
    the optimum of a graph that only ever had the new one); a refused replacement leaves the
    old link and the estimate as they were."""
    truth, odo, rng = scene
    n = len(truth) - 1
    first, second = loop_measurement(truth, n, 0, rng), loop_measurement(truth, n, 0, rng)
    g = build(truth, odo)
    assert g.add_loop(n, 0, first, LOOP_INFO).accepted
    out = g.add_loop(n, 0, second, LOOP_INFO, replace=first)
    assert out.accepted
    assert g.loops() == [(n, 0)]
    only = build(truth, odo)
    assert only.add_loop(n, 0, second, LOOP_INFO).accepted
    assert max_diff(g.poses(), only.poses()) < 1e-4
    # a replacement the graph refuses (2 m off): the accepted one stays, and the estimate
    before = g.poses()
    wrong = second @ exp([0, 0, 0, 2.0, 0, 0])
    out = g.add_loop(n, 0, wrong, LOOP_INFO, replace=second)
    assert not out.accepted
    assert g.loops() == [(n, 0)]
    assert max_diff(before, g.poses()) < 1e-6
    assert g.remove_loop(n, 0, second) == 1  # the link back is the old measurement
    # nothing to replace: a plain add
    assert g.add_loop(n, 0, first, LOOP_INFO, replace=wrong).accepted and g.loops() == [(n, 0)]


def test_bad_input():
    g = PoseGraph()
    g.add_node(1, np.eye(4))
    with pytest.raises(ValueError):
        g.add_node(1, np.eye(4))
    with pytest.raises(ValueError):
        g.add_node(2, np.eye(4), odom_from=9)
    with pytest.raises(ValueError):
        g.add_node(3, np.eye(3))
    g.add_node(2, exp([0, 0, 0, 1, 0, 0]), odom_from=1)  # transform from the odometry poses
    assert np.allclose(g.pose(2)[:3, 3], [1, 0, 0])
    with pytest.raises(ValueError):
        g.add_loop(1, 7, np.eye(4), LOOP_INFO)
    with pytest.raises(ValueError):
        g.add_loop(1, 2, np.eye(4), -LOOP_INFO)
    with pytest.raises(KeyError):
        g.pose(42)


def test_reads_while_loop_closes(scene):
    truth, odo, rng = scene
    g = build(truth, odo)
    n = len(truth) - 1
    errors, stop = [], threading.Event()

    def reader():
        while not stop.is_set():
            try:
                p = g.poses()
                assert len(p) >= n + 1 and all(np.isfinite(v).all() for v in p.values())
                g.pose(n)
            except Exception as e:  # pragma: no cover
                errors.append(e)

    th = threading.Thread(target=reader)
    th.start()
    try:
        for k in range(3):
            g.add_loop(n, 0, loop_measurement(truth, n, 0, rng), LOOP_INFO)
            g.add_node(n + 1 + k, np.eye(4), odom_from=n + k, transform=odo[k], information=INFO)
    finally:
        stop.set()
        th.join()
    assert not errors


def test_batch_apply_and_rejected_factor_not_in_batch(scene):
    truth, odo, rng = scene
    g = build(truth, odo)
    n = len(truth) - 1
    assert not g.add_loop(n, 0, loop_measurement(truth, n, 0, rng) @ exp([0, 0, 0, 0, 2.0, 0]), LOOP_INFO).accepted
    before = g.poses()
    assert max_diff(before, g.batch_optimize()) < 1e-5  # the removed link is not in the batch graph
    assert g.add_loop(n, 0, loop_measurement(truth, n, 0, rng), LOOP_INFO).accepted
    batch = g.batch_optimize(apply=True)  # iSAM2 restarted from the LM solution
    assert max_diff(batch, g.poses()) < 1e-6
    g.add_node(n + 1, np.eye(4), odom_from=n, transform=odo[0], information=INFO)
    assert g.remove_loop(n, 0) == 1  # factor indices were renumbered correctly
    assert max_diff(before, {k: v for k, v in g.poses().items() if k in before}) < 1e-5


def test_readers_do_not_wait_for_an_optimisation(scene):
    truth, odo, _ = scene
    g = build(truth, odo)
    got = {}
    with g._lock:  # as if a loop closure were optimising on another thread
        th = threading.Thread(target=lambda: got.update(poses=g.poses(), pose=g.pose(3)))
        th.start()
        th.join(timeout=5)
        assert not th.is_alive()
    assert len(got["poses"]) == len(truth) and np.allclose(got["pose"], got["poses"][3])
    with pytest.raises(ValueError):
        got["poses"][3][0, 0] = 5.0  # snapshot arrays are read-only


def test_restore_continues_a_stored_graph(scene):
    """A graph rebuilt from stored poses and links (a map update resumed after a crash) holds
    the same estimate, reports nothing moved, and goes on like the original."""
    truth, odo, rng = scene
    n = len(truth) - 1
    g = build(truth, odo[:30])  # the second half comes after the "crash"
    loop = (25, 3, loop_measurement(truth, 25, 3, rng))
    assert g.add_loop(*loop, LOOP_INFO).accepted
    stored = g.poses()
    g2 = PoseGraph()
    g2.restore(stored, [(i, i + 1, odo[i], INFO) for i in range(30)], [(*loop, LOOP_INFO)])
    assert len(g2) == len(g) and g2.loops() == g.loops() == [(25, 3)]
    assert max_diff(stored, g2.poses()) < 1e-6
    assert g2.changed_poses() == {}  # (within the graph's move tolerance)
    for gg in (g, g2):  # both go on with the same keyframes and close the big loop the same way
        for i in range(30, n):
            gg.add_node(i + 1, np.eye(4), odom_from=i, transform=odo[i], information=INFO)
        assert gg.add_loop(n, 0, loop_measurement(truth, n, 0, np.random.default_rng(5)), LOOP_INFO).accepted
    assert max_diff(g.poses(), g2.poses()) < 1e-4
    assert ate(g2.poses(), truth) < 0.05
    moved = g2.changed_poses()
    assert set(range(31, n + 1)) <= set(moved) and 0 not in moved  # new nodes + what the loop moved
    # a node without an odometry link to it starts a (loosely anchored) segment; bad input refused
    g3 = PoseGraph()
    three = {0: truth[0], 1: truth[0] @ odo[0], 7: truth[7]}
    g3.restore(three, [(0, 1, odo[0], INFO)])
    assert max_diff(three, g3.poses()) < 1e-6
    with pytest.raises(ValueError, match="empty graph"):
        g3.restore({9: truth[0]})
    with pytest.raises(ValueError, match="earlier node"):
        PoseGraph().restore({0: truth[0], 1: truth[1]}, [(1, 0, odo[0], INFO)])
    with pytest.raises(ValueError, match="loop link"):
        PoseGraph().restore({0: truth[0]}, [], [(0, 5, odo[0], LOOP_INFO)])


def test_replace_odometry_takes_the_new_measurements(scene):
    """Local BA hands refined relative poses for odometry links: the chain follows them, a
    loop link and pairs without an odometry link are left alone."""
    truth, odo, rng = scene
    g = build(truth, odo[:10])
    g.add_loop(0, 5, loop_measurement(truth, 0, 5, rng), LOOP_INFO)
    exact = {(i, i + 1): inv(truth[i]) @ truth[i + 1] for i in range(5, 10)}
    replaced = g.replace_odometry({**exact, (0, 5): np.eye(4), (2, 9): np.eye(4)})
    assert sorted((lk.from_id, lk.to_id) for lk in replaced) == sorted(exact)
    est = g.poses()
    for (a, b), t in exact.items():  # the links after the loop's end are now exact
        assert np.abs(inv(est[a]) @ est[b] - t).max() < 1e-4
    assert g.loops() == [(0, 5)]
    links = {(a, b): e for a, b, loop, e in g.link_errors() if not loop}
    assert len(links) == 10 and max(links[k] for k in exact) < 0.01  # σ units
    assert g.replace_odometry({}) == []
