"""The one graph link rehearsal keeps between two nodes (MergeLinks.add): the running
mean of the merges' measurements, put in the graph only when it moved more than what the map
reports (`PoseGraph.move_tolerance`)."""
import gtsam
import numpy as np

from mnemoslam.service.mapping.graph import PoseGraph
from mnemoslam.service.mapping.merge_links import MergeLinks

INFO = np.diag(1.0 / np.array([np.radians(0.5)] * 3 + [0.01] * 3) ** 2)


def exp(xi) -> np.ndarray:
    return gtsam.Pose3.Expmap(np.asarray(xi, np.float64)).matrix()


def chain(graph: PoseGraph, n: int = 6) -> list[np.ndarray]:
    poses = [exp([0, 0, 0.1 * i, 0.5 * i, 0, 0]) for i in range(n)]
    graph.add_node(0, poses[0])
    for i in range(1, n):
        graph.add_node(i, np.eye(4), odom_from=i - 1, transform=np.linalg.inv(poses[i - 1]) @ poses[i],
                       information=INFO)
    return poses


def test_repeated_merges_refine_one_link_and_skip_what_moves_nothing():
    g = PoseGraph()
    poses = chain(g)
    m = MergeLinks(g)
    rng = np.random.default_rng(3)
    true = np.linalg.inv(poses[5]) @ poses[1]
    reasons = []
    for _ in range(12):  # the same place merged again and again: measurements 20 µm apart
        t = true @ exp(np.r_[rng.normal(0, 2e-6, 3), rng.normal(0, 2e-5, 3)])
        out = m.add(5, 1, t, INFO)
        assert out.accepted, out.reason
        reasons.append(out.reason)
    assert g.loops() == [(5, 1)]  # one link per pair, whatever the number of merges
    assert reasons[:3] == ["accepted"] * 3  # added, then replaced while its information grows (x2, x3)
    assert all("within tolerance" in r for r in reasons[3:]), reasons  # then the mean moves < 0.1 mm
    # the map is where the link in the graph puts it, which is within tolerance of the mean
    mean = m._links[frozenset((5, 1))].transform
    est = g.poses()
    d = np.linalg.inv(np.linalg.inv(est[5]) @ est[1]) @ mean
    assert np.linalg.norm(d[:3, 3]) < 1e-4
    # a measurement that moves the mean by more than the tolerance is put in the graph
    before = g.poses()
    out = m.add(1, 5, np.linalg.inv(true @ exp([0, 0, 0, 0.01, 0, 0])), INFO)  # either direction
    assert out.accepted and out.reason == "accepted"
    assert g.loops() == [(5, 1)]
    assert max(np.abs(g.poses()[k] - before[k]).max() for k in before) > 1e-4
