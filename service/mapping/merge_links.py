"""The graph links rehearsal's merges make (RTAB-Map merges a keyframe into the node the map
has where it was taken; the path from the keyframe before then links to that node): one link
per pair of nodes, however many merges measured it (`MergeLinks.add`)."""
from __future__ import annotations

import dataclasses
import time

import gtsam
import numpy as np

from mnemoslam.client.kernel.geometry import invert, rotation_angle

from .graph import LoopOutcome, PoseGraph


@dataclasses.dataclass
class _MergeLink:
    """The graph link merges made between two nodes: T_from_to (mean of `count` measurements)
    and the information of the link in the graph."""

    from_id: int
    to_id: int
    transform: np.ndarray
    information: np.ndarray
    count: int
    in_graph: np.ndarray  # T_from_to of the link in the graph (the mean when it was last put there)


class MergeLinks:
    """The links merges made in `graph`, by node pair."""

    def __init__(self, graph: PoseGraph):
        self.graph = graph
        self._links: dict[frozenset, _MergeLink] = {}  # node pair -> the one graph link merges between them made

    def add(self, a: int, b: int, transform: np.ndarray, information: np.ndarray,
            check: str | bool = "link") -> LoopOutcome:
        """The graph link a merge makes between two nodes (T_a_b): the first merge between
        them adds it; a later one replaces it by the running mean of their measurements, its
        information that of one measurement times their count (up to 3), so repeated passes
        refine one link per pair instead of adding one per keyframe (iSAM2 grows ~7 kB per
        link). A mean that moved less than the graph's `move_tolerance` from the link in the
        graph, at the same information, is kept in the mean only when the measurement itself
        fits the current estimate (`graph.max_error`): no optimisation for what would move no
        pose the map reports. Returns the graph's outcome."""
        t0 = time.perf_counter()
        key = frozenset((a, b))
        old = self._links.get(key)
        n = 0
        if old is not None:
            t = transform if old.from_id == a else invert(transform)
            a, b, n = old.from_id, old.to_id, old.count
            one = information
            step = gtsam.Pose3.Logmap(gtsam.Pose3(invert(old.transform) @ t)) / (n + 1)
            transform = old.transform @ gtsam.Pose3.Expmap(step).matrix()
            information = information * min(n + 1, 3)
            if n >= 3 and self._within_tolerance(old.in_graph, transform):
                err = self.graph.link_error(a, b, t, one)
                if not check or self.graph.max_error <= 0 or err <= self.graph.max_error:
                    self._links[key] = _MergeLink(a, b, transform, old.information, n + 1, old.in_graph)
                    return LoopOutcome(True, "accepted (the link moved within tolerance: kept)", err, err, err,
                                       duration_ms=(time.perf_counter() - t0) * 1e3)
        # (one optimisation replaces the previous link; a refused one leaves it in place)
        outcome = self.graph.add_loop(a, b, transform, information, check=check,
                                      replace=None if old is None else old.in_graph)
        if outcome.accepted:
            self._links[key] = _MergeLink(a, b, transform, information, n + 1, transform)
        return outcome

    def _within_tolerance(self, a: np.ndarray, b: np.ndarray) -> bool:
        tol_t, tol_r = self.graph.move_tolerance
        d = invert(a) @ b
        return bool(float(np.linalg.norm(d[:3, 3])) < tol_t and rotation_angle(d[:3, :3]) < tol_r)
