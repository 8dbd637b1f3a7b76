"""Pose graph over keyframes with GTSAM iSAM2 (RTAB-Map's graph optimisation, incremental).

Nodes are keyframe ids (global ints, used directly as GTSAM keys); poses are camera-to-world 4×4
matrices. Links are ``BetweenFactorPose3`` with the registration's 6×6 information (rotation
first, GTSAM's Pose3 tangent order — see ``service.memory.keyframes.odometry_information``):

* odometry links with a plain Gaussian model;
* loop links with a robust kernel (Huber by default, or Cauchy) around the same Gaussian;
* the first node of the graph gets a tight prior; the first node of every later disconnected
  segment (``odom_from=None``) gets a very loose one, so a loop link can move the whole segment.

Every ``add_node`` is one iSAM2 update (a fraction of a millisecond on a chain). ``add_loop`` adds
the loop link, iterates iSAM2 to convergence, then runs the graph-error check of RTAB-Map's
``RGBD/OptimizeMaxError`` (3.0): the error of every link in the optimised graph, normalised by
its σ (rotation and translation separately, the larger counts), must stay ≤ ``max_error``;
otherwise the loop link is removed again (``removeFactorIndices``) and the estimate goes back to
where it was. The outcome says why.

Thread-safe: one re-entrant lock serialises the updates (add_node waits while a loop closure
optimises — call it from the mapping thread); ``poses()``/``pose()`` read a snapshot under a
separate short lock and never wait for an optimisation (tracking reads poses while loop closure
runs on a background thread).
"""
from __future__ import annotations

import contextlib
import dataclasses
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import cast

import gtsam
import numpy as np

from mnemoslam.client.kernel.geometry import invert

# default σ of an odometry link when none is given: 0.5° / 1 cm (rotation first)
DEFAULT_ODOMETRY_SIGMAS = np.array([np.deg2rad(0.5)] * 3 + [0.01] * 3)
FIRST_PRIOR_SIGMAS = np.array([1e-6] * 3 + [1e-6] * 3)
SEGMENT_PRIOR_SIGMAS = np.array([3.0] * 3 + [100.0] * 3)  # loose: a loop link places the segment
ROBUST_KERNELS = ("huber", "cauchy", "none")


@dataclass
class LoopOutcome:
    """What happened to one loop link. Errors are normalised (σ units, RTAB-Map's ratio)."""

    accepted: bool
    reason: str  # "accepted", "max error exceeded by the loop link", ... , "check disabled"
    error_before: float  # loop link's normalised error on the estimate before the link
    error_after: float  # loop link's normalised error after optimisation (with the link)
    max_normalized_error: float  # largest normalised error of any link after optimisation
    worst_link: tuple[int, int] | None = None  # (from, to) of that link
    iterations: int = 0  # iSAM2 updates spent on the loop
    duration_ms: float = 0.0


@dataclass
class _Link:
    from_id: int
    to_id: int
    transform: np.ndarray  # T_from_to
    information: np.ndarray  # 6×6
    loop: bool
    factor_index: int


def _as_pose(m, what: str) -> np.ndarray:
    a = np.asarray(m, dtype=np.float64)
    if a.shape != (4, 4) or not np.all(np.isfinite(a)):
        raise ValueError(f"{what} must be a finite 4×4 matrix, got shape {a.shape}")
    return a


def _as_information(m, what: str) -> np.ndarray:
    a = np.asarray(m, dtype=np.float64)
    if a.shape != (6, 6) or not np.all(np.isfinite(a)):
        raise ValueError(f"{what} must be a finite 6×6 information matrix, got shape {a.shape}")
    a = 0.5 * (a + a.T)
    try:
        np.linalg.cholesky(a)
    except np.linalg.LinAlgError:
        raise ValueError(f"{what} must be positive definite") from None
    return a


def to_pose3(m: np.ndarray) -> gtsam.Pose3:
    """A 4×4 rigid transform as a GTSAM Pose3 (the graph's and local BA's)."""
    # re-orthonormalise: GTSAM's Rot3 from a slightly non-orthogonal matrix is not a rotation
    u, _, vt = np.linalg.svd(m[:3, :3])
    r = u @ vt
    if np.linalg.det(r) < 0:
        u[:, -1] *= -1
        r = u @ vt
    return gtsam.Pose3(gtsam.Rot3(r), np.asarray(m[:3, 3], dtype=np.float64))


def _ro(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


def _skew(w: np.ndarray) -> np.ndarray:
    s = np.zeros(w.shape[:-1] + (3, 3))
    s[..., 0, 1], s[..., 0, 2] = -w[..., 2], w[..., 1]
    s[..., 1, 0], s[..., 1, 2] = w[..., 2], -w[..., 0]
    s[..., 2, 0], s[..., 2, 1] = -w[..., 1], w[..., 0]
    return s


def se3_log(t: np.ndarray) -> np.ndarray:
    """Pose3::Logmap of rigid transforms (..., 4, 4) -> (..., 6) = [ω, u], vectorised."""
    r = t[..., :3, :3]
    cos = np.clip((np.trace(r, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    theta = np.arccos(cos)
    vee = np.stack([r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]], -1)
    sin = np.sin(theta)
    small = theta < 1e-5
    near_pi = theta > np.pi - 1e-4
    with np.errstate(divide="ignore", invalid="ignore"):
        k = np.where(small, 0.5 + theta**2 / 12.0, theta / (2.0 * np.where(small, 1.0, sin)))
    w = vee * k[..., None]
    if np.any(near_pi):  # axis from the symmetric part; sign irrelevant for the error norm
        sym = (r[near_pi] + np.eye(3)) / 2.0
        axis = np.sqrt(np.clip(np.diagonal(sym, axis1=-2, axis2=-1), 0.0, None))
        w[near_pi] = axis * np.pi
    ws = _skew(w)
    with np.errstate(divide="ignore", invalid="ignore"):
        c = np.where(small | near_pi, 1.0 / 12.0,
                     (1.0 - theta * sin / (2.0 * (1.0 - cos))) / np.where(small, 1.0, theta**2))
    vinv = np.eye(3) - 0.5 * ws + c[..., None, None] * (ws @ ws)
    u = np.einsum("...ij,...j->...i", vinv, t[..., :3, 3])
    return np.concatenate([w, u], axis=-1)


def normalized_errors(poses_from: np.ndarray, poses_to: np.ndarray, transforms: np.ndarray,
                      informations: np.ndarray) -> np.ndarray:
    """Normalised error of links (n,) given the poses at both ends (n, 4, 4), the measured
    T_from_to (n, 4, 4) and information (n, 6, 6): the BetweenFactorPose3 error
    e = Logmap(measured⁻¹ · from⁻¹ · to), and max(√(e_rᵀ Λ_rr e_r), √(e_tᵀ Λ_tt e_t)) — rotation
    and translation in σ, like RTAB-Map's angular/linear error ratios."""
    e = se3_log(invert(transforms) @ invert(poses_from) @ poses_to)
    er, et = e[:, :3], e[:, 3:]
    cr = np.einsum("ni,nij,nj->n", er, informations[:, :3, :3], er)
    ct = np.einsum("ni,nij,nj->n", et, informations[:, 3:, 3:], et)
    return np.sqrt(np.maximum(np.maximum(cr, ct), 0.0))


def _link_error(est: dict[int, np.ndarray], a: int, b: int, t: np.ndarray, info: np.ndarray) -> float:
    """`normalized_errors` of one measurement T_a_b on the estimate `est`."""
    return float(normalized_errors(est[a][None], est[b][None], t[None], info[None])[0])


class PoseGraph:
    """Incremental pose graph (iSAM2) with RTAB-Map's loop-link error check.

    Parameters: ``max_error`` — RGBD/OptimizeMaxError, σ ratio (≤ 0 disables the check);
    ``robust`` — default kernel of loop links, "huber", "cauchy" or "none"; ``robust_width`` —
    kernel width in σ (whitened units); ``relinearize_threshold``/``wildfire_threshold`` —
    iSAM2 accuracy knobs; ``max_iterations`` — iSAM2 updates per loop closure at most;
    ``move_tolerance`` — (metres, radians) a pose must move to be reported by ``changed_poses``.
    """

    def __init__(self, max_error: float = 3.0, robust: str = "huber", robust_width: float = 3.0,
                 relinearize_threshold: float = 1e-3, wildfire_threshold: float = 1e-6,
                 max_iterations: int = 30, move_tolerance: tuple[float, float] = (1e-4, 1e-4)):
        if robust not in ROBUST_KERNELS:
            raise ValueError(f"robust must be one of {ROBUST_KERNELS}, got {robust!r}")
        self.max_error = float(max_error)
        self.robust = robust
        self.robust_width = float(robust_width)
        self.max_iterations = int(max_iterations)
        self.move_tolerance = (float(move_tolerance[0]), float(move_tolerance[1]))
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(relinearize_threshold)
        params.relinearizeSkip = 1
        # check relinearisation only from the top of the Bayes tree down: checking every variable
        # costs a full wildfire back-substitution per update, ~4-5 ms per keyframe at 8-10k nodes
        # once loops are in (0.4-0.5 ms with this; bench_graph.py). Loop closures switch to the
        # full check while they iterate (_full_check), else deep variables keep stale
        # linearisation points (1 cm from batch LM at 10k nodes).
        params.enablePartialRelinearizationCheck = True
        # QR, not the default Cholesky: Cholesky squares the condition number and reports an
        # "indeterminate system" on plain odometry chains after ~600 keyframes (σ 0.5°/1 cm, 0.5 m
        # steps: the far end's position is poorly determined); QR keeps going (bench_graph.py).
        params.setFactorization("QR")
        gn = gtsam.ISAM2GaussNewtonParams()
        gn.setWildfireThreshold(wildfire_threshold)
        params.setOptimizationParams(gn)
        params.findUnusedFactorSlots = False  # factor indices stay unique (we remove by index)
        self._params = params
        self._isam = gtsam.ISAM2(params)
        self._lock = threading.RLock()
        self._nodes: list[int] = []  # insertion order
        self._raw: dict[int, np.ndarray] = {}  # pose given to add_node (odometry frame)
        self._links: list[_Link] = []  # active links (odometry + accepted loops)
        self._priors: dict[int, tuple[np.ndarray, np.ndarray, int]] = {}  # node -> (pose, sigmas, idx)
        self._first: int | None = None  # the first node `add_node` gave the tight prior (the graph's frame)
        self._n_factors = 0  # factor slots used in iSAM2 (removed slots are not reused)
        self._cache: dict[int, np.ndarray] | None = None  # full estimate, None = stale
        # what readers see: replaced (never mutated in place, arrays read-only) after every
        # update, under its own short lock, so poses()/pose() never wait for an optimisation
        self._snap: dict[int, np.ndarray] = {}
        self._snap_lock = threading.Lock()
        self._published: dict[int, np.ndarray] = {}

    # -- building -------------------------------------------------------------------------

    def add_node(self, node_id: int, pose, odom_from: int | None = None, transform=None,
                 information=None) -> np.ndarray:
        """Add keyframe ``node_id`` and return its pose in the graph (the estimate).

        ``pose``: camera-to-world 4×4 from odometry. With ``odom_from`` (a node already in the
        graph) an odometry link from it is added with ``transform`` = T_from_to (default:
        derived from the two odometry poses) and ``information`` (6×6, rotation first; default
        0.5°/1 cm); the new node starts at estimate(odom_from)·T, so it follows corrections. With
        ``odom_from=None`` the node starts a segment: a tight prior at ``pose`` for the first node
        of the graph, a very loose one for a later segment (a loop link places it).
        """
        nid = int(node_id)
        pose = _as_pose(pose, "pose")
        with self._lock:
            if nid in self._raw:
                raise ValueError(f"node {nid} is already in the graph")
            graph = gtsam.NonlinearFactorGraph()
            values = gtsam.Values()
            if odom_from is None:
                if transform is not None or information is not None:
                    raise ValueError("transform/information need odom_from")
                sigmas = FIRST_PRIOR_SIGMAS if not self._nodes else SEGMENT_PRIOR_SIGMAS
                if not self._nodes:
                    self._first = nid
                graph.add(gtsam.PriorFactorPose3(nid, to_pose3(pose), gtsam.noiseModel.Diagonal.Sigmas(sigmas)))
                new_prior = (pose.copy(), sigmas, self._n_factors)
                new_link = None
                initial = pose
            else:
                src = int(odom_from)
                if src not in self._raw:
                    raise ValueError(f"odom_from node {src} is not in the graph")
                t = invert(self._raw[src]) @ pose if transform is None else _as_pose(transform, "transform")
                info = (np.diag(1.0 / DEFAULT_ODOMETRY_SIGMAS**2) if information is None
                        else _as_information(information, "information"))
                graph.add(gtsam.BetweenFactorPose3(src, nid, to_pose3(t), gtsam.noiseModel.Gaussian.Information(info)))
                new_link, new_prior = _Link(src, nid, t.copy(), info, False, self._n_factors), None
                initial = self._pose_locked(src) @ t
            values.insert(nid, to_pose3(initial))
            self._isam.update(graph, values)
            self._n_factors += 1
            if new_link is not None:
                self._links.append(new_link)
            else:
                assert new_prior is not None  # a node without an odometry link has a prior
                self._priors[nid] = new_prior
            self._nodes.append(nid)
            self._raw[nid] = pose.copy()
            est = self._isam.calculateEstimatePose3(nid).matrix()
            if self._cache is not None:
                # a new leaf (one odometry link or a prior) does not move the optimum of the others
                self._cache[nid] = _ro(est.copy())
            with self._snap_lock:
                self._snap[nid] = _ro(est.copy())
            return est

    def restore(self, poses, odometry=(), loops=()) -> None:
        """Load a stored graph into this empty one, at its stored poses: the nodes in the
        order of ``poses`` ({id: 4×4 pose}); the first gets the tight prior, every other node
        without an odometry link to it the loose segment prior; ``odometry`` (from, to,
        T_from_to, information) links as ``add_node`` makes them (from an earlier node) and
        ``loops`` (from, to, T_from_to, information) as ``add_loop`` does (default robust
        kernel, no error check: they were checked when added). One iSAM2 update from the
        stored poses, iterated to convergence. The stored poses count as published:
        ``changed_poses`` reports only what moves away from them."""
        poses = {int(k): _as_pose(v, f"pose of node {k}") for k, v in poses.items()}
        odometry = [(int(a), int(b), _as_pose(t, "transform"), _as_information(i, "information"))
                    for a, b, t, i in odometry]
        loops = [(int(a), int(b), _as_pose(t, "transform"), _as_information(i, "information"))
                 for a, b, t, i in loops]
        order = {n: k for k, n in enumerate(poses)}
        incoming: dict[int, tuple] = {}
        for link in odometry:
            a, b = link[0], link[1]
            if a not in order or b not in order or order[a] >= order[b]:
                raise ValueError(f"odometry link {a}->{b} must go from an earlier node to a later one of the graph")
            if b in incoming:
                raise ValueError(f"node {b} has two odometry links to it")
            incoming[b] = link
        for a, b, _, _ in loops:
            if a not in order or b not in order or a == b:
                raise ValueError(f"loop link {a}->{b} needs two different nodes of the graph")
        with self._lock:
            if self._nodes:
                raise ValueError("restore needs an empty graph")
            graph = gtsam.NonlinearFactorGraph()
            values = gtsam.Values()
            for k, (nid, pose) in enumerate(poses.items()):
                values.insert(nid, to_pose3(pose))
                link = incoming.get(nid)
                if link is None:
                    sigmas = FIRST_PRIOR_SIGMAS if k == 0 else SEGMENT_PRIOR_SIGMAS
                    graph.add(gtsam.PriorFactorPose3(nid, to_pose3(pose), gtsam.noiseModel.Diagonal.Sigmas(sigmas)))
                    self._priors[nid] = (pose.copy(), sigmas, self._n_factors)
                else:
                    a, b, t, info = link
                    graph.add(gtsam.BetweenFactorPose3(a, b, to_pose3(t), gtsam.noiseModel.Gaussian.Information(info)))
                    self._links.append(_Link(a, b, t.copy(), info, False, self._n_factors))
                self._n_factors += 1
                self._nodes.append(nid)
                self._raw[nid] = pose.copy()
            for a, b, t, info in loops:
                graph.add(gtsam.BetweenFactorPose3(a, b, to_pose3(t), self._loop_noise(info, self.robust)))
                self._links.append(_Link(a, b, t.copy(), info, True, self._n_factors))
                self._n_factors += 1
            if not poses:
                return
            self._isam.update(graph, values)
            self._converge_locked()
            self._cache = None
            self._publish_locked()
            self._published = {k: v.copy() for k, v in poses.items()}

    def add_anchored(self, poses, sigmas=FIRST_PRIOR_SIGMAS) -> None:
        """Add nodes that are already placed, e.g. a previous session's optimised map: each at
        its given pose ({id: 4×4}) with a prior of ``sigmas`` (default the tight first-node
        prior, so they anchor whatever links to them), no link between them; one iSAM2
        update. The given poses count as published (``changed_poses`` reports only moves
        away from them). Later segments (``add_node`` without ``odom_from``) get the loose
        segment prior, so a loop link to these nodes places them."""
        poses = {int(k): _as_pose(v, f"pose of node {k}") for k, v in poses.items()}
        sig = np.asarray(sigmas, np.float64)
        if not poses:
            return
        with self._lock:
            for nid in poses:
                if nid in self._raw:
                    raise ValueError(f"node {nid} is already in the graph")
            graph = gtsam.NonlinearFactorGraph()
            values = gtsam.Values()
            noise = gtsam.noiseModel.Diagonal.Sigmas(sig)
            for nid, pose in poses.items():
                values.insert(nid, to_pose3(pose))
                graph.add(gtsam.PriorFactorPose3(nid, to_pose3(pose), noise))
                self._priors[nid] = (pose.copy(), sig, self._n_factors)
                self._n_factors += 1
                self._nodes.append(nid)
                self._raw[nid] = pose.copy()
            self._isam.update(graph, values)
            if self._cache is not None:  # priors alone: the others' optimum does not move
                self._cache.update({nid: _ro(p.copy()) for nid, p in poses.items()})
            with self._snap_lock:
                snap = dict(self._snap)
                snap.update({nid: _ro(p.copy()) for nid, p in poses.items()})
                self._snap = snap
            self._published.update({nid: p.copy() for nid, p in poses.items()})

    def loosen_first(self) -> bool:
        """The graph's first node (`add_node`'s, with the tight first prior that fixes the
        graph's frame) gets the loose segment prior instead, at the same pose: the graph may
        now be placed by links to anchored nodes (another map joined: `mapping.live`). With
        that one prior the optimum does not move. Returns whether a prior was loosened."""
        with self._lock:
            nid = self._first
            if nid is None or nid not in self._priors:
                return False
            pose, _, idx = self._priors[nid]
            graph = gtsam.NonlinearFactorGraph()
            loose = gtsam.noiseModel.Diagonal.Sigmas(SEGMENT_PRIOR_SIGMAS)
            graph.add(gtsam.PriorFactorPose3(nid, to_pose3(pose), loose))
            self._isam.update(graph, gtsam.Values(), [idx])
            self._priors[nid] = (pose.copy(), SEGMENT_PRIOR_SIGMAS, self._n_factors)
            self._n_factors += 1
            self._first = None
            self._cache = None
            return True

    def _loop_noise(self, info: np.ndarray, kernel: str) -> gtsam.noiseModel.Base:
        noise: gtsam.noiseModel.Base = gtsam.noiseModel.Gaussian.Information(info)
        if kernel == "huber":
            noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(self.robust_width), noise)
        elif kernel == "cauchy":
            noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(self.robust_width), noise)
        return noise

    def add_loop(self, from_id: int, to_id: int, transform, information, robust: bool | str = True,
                 check: bool | str = True, replace=None) -> LoopOutcome:
        """Add a loop link T_from_to between two graph nodes, optimise, and check the graph error.

        ``robust``: True = the graph's default kernel, False/"none" = plain Gaussian, or "huber" /
        "cauchy". ``check=False`` (or ``max_error`` ≤ 0) keeps the link whatever the error;
        ``check="link"`` checks the new link's own error only (not the other links': one
        already at the limit would refuse every link that moves it). A rejected link is removed
        again and the estimate restored.

        ``replace``: T_from_to of a loop link from_id -> to_id that the new one replaces, in the
        same iSAM2 update (one optimisation instead of a ``remove_loop``'s and an ``add_loop``'s);
        if the new link is rejected, that link is back and the estimate restored. No such link:
        a plain add."""
        t0 = time.perf_counter()
        a, b = int(from_id), int(to_id)
        t = _as_pose(transform, "transform")
        info = _as_information(information, "information")
        kernel = self.robust if robust is True else ("none" if robust is False else str(robust))
        if kernel not in ROBUST_KERNELS:
            raise ValueError(f"robust must be bool or one of {ROBUST_KERNELS}, got {robust!r}")
        with self._lock:
            for n in (a, b):
                if n not in self._raw:
                    raise ValueError(f"loop node {n} is not in the graph")
            if a == b:
                raise ValueError("a loop link needs two different nodes")
            before = self._estimate_locked()
            err_before = _link_error(before, a, b, t, info)
            old = [] if replace is None else [lk for lk in self._links if lk.loop and lk.from_id == a and lk.to_id == b
                                              and np.array_equal(lk.transform, replace)][:1]
            link, = self._swap_links_locked(old, [(_Link(a, b, t.copy(), info, True, -1),
                                                   self._loop_noise(info, kernel))])
            iterations = 1 + self._converge_locked()
            self._cache = None
            after = self._estimate_locked()
            errs = self._link_errors_locked(after)
            k = int(np.argmax(errs)) if len(errs) else -1
            max_err = float(errs[k]) if k >= 0 else 0.0
            worst = (self._links[k].from_id, self._links[k].to_id) if k >= 0 else None
            err_after = float(errs[-1])
            if not check or self.max_error <= 0:
                accepted, reason = True, "accepted (check disabled)"
            elif err_after > self.max_error:
                accepted, reason = False, (f"loop link error {err_after:.2f} σ > max {self.max_error:g} σ "
                                           "after optimisation")
            elif max_err > self.max_error and check != "link":
                assert worst is not None  # max_err > max_error > 0: some link's error
                accepted, reason = False, (f"link {worst[0]}->{worst[1]} error {max_err:.2f} σ > max "
                                           f"{self.max_error:g} σ after optimisation")
            else:
                accepted, reason = True, "accepted"
            if not accepted:
                self._remove_links_locked([link], restore=before, back=old)
            self._publish_locked()
            return LoopOutcome(accepted, reason, err_before, err_after, max_err, worst, iterations,
                               (time.perf_counter() - t0) * 1e3)

    def replace_odometry(self, transforms: dict[tuple[int, int], np.ndarray]) -> list:
        """Give odometry links new measurements, {(from, to): T_from_to} (e.g. a local bundle
        adjustment's), each keeping its information; pairs without an odometry link are
        skipped. One iSAM2 update (the old factors removed, the new added), then iterated with
        the partial relinearisation check (the changes are small and at the chain's end).
        Returns the replaced links with their new measurements (for the caller to store)."""
        with self._lock:
            old = [lk for lk in self._links if not lk.loop and (lk.from_id, lk.to_id) in transforms]
            if not old:
                return []
            new = [(dataclasses.replace(lk, transform=_as_pose(transforms[(lk.from_id, lk.to_id)], "transform").copy()),
                    gtsam.noiseModel.Gaussian.Information(lk.information)) for lk in old]
            self._swap_links_locked(old, new)
            self._cache = None
            self._iterate_locked(1e-6)
            self._publish_locked()
            return [link for link, _ in new]

    def link_error(self, from_id: int, to_id: int, transform, information) -> float:
        """Normalised error (σ, as the loop check) of a measurement T_from_to on the current
        estimate, without adding it."""
        t = _as_pose(transform, "transform")
        info = _as_information(information, "information")
        with self._lock:
            return _link_error(self._estimate_locked(), int(from_id), int(to_id), t, info)

    def remove_loop(self, from_id: int, to_id: int, transform=None) -> int:
        """Remove the loop link(s) between two nodes (either direction; with ``transform``,
        only the link from_id -> to_id with that T_from_to) and re-optimise. Returns how many
        links were removed."""
        a, b = int(from_id), int(to_id)
        with self._lock:
            gone = [lk for lk in self._links if lk.loop and {lk.from_id, lk.to_id} == {a, b}
                    and (transform is None or (lk.from_id == a and np.array_equal(lk.transform, transform)))]
            if gone:
                self._remove_links_locked(gone, restore=None)
                self._publish_locked()
            return len(gone)

    def _remove_links_locked(self, links: list[_Link], restore: dict[int, np.ndarray] | None,
                             back: Sequence[_Link] = ()) -> None:
        """Remove `links` (and put the loop links `back` again, with the default kernel, in the
        same update)."""
        self._swap_links_locked(links, [(lk, self._loop_noise(lk.information, self.robust)) for lk in back])
        self._converge_locked()
        self._cache = None
        if restore is not None:
            # the optimum without the link is the estimate before it: iterate until iSAM2 is there
            with self._full_check():
                for _ in range(self.max_iterations):
                    est = self._estimate_locked()
                    if self._max_move(restore, est) < 1e-9:
                        break
                    self._isam.update(gtsam.NonlinearFactorGraph(), gtsam.Values(), [], None, None, None, True)
                    self._cache = None
            self._cache = {k: _ro(v.copy()) for k, v in restore.items()}  # exactly as before

    def _swap_links_locked(self, gone: list[_Link], new: Sequence[tuple[_Link, gtsam.noiseModel.Base]]) -> list[_Link]:
        """One iSAM2 update that removes the factors of links `gone` and adds links `new`
        ((link, noise model), their factor indices given here); the active links follow, the
        new ones last. Returns the new links. The estimate cache is left to the caller."""
        graph = gtsam.NonlinearFactorGraph()
        for lk, noise in new:
            graph.add(gtsam.BetweenFactorPose3(lk.from_id, lk.to_id, to_pose3(lk.transform), noise))
        self._isam.update(graph, gtsam.Values(), [lk.factor_index for lk in gone])
        added = [dataclasses.replace(lk, factor_index=self._n_factors + k) for k, (lk, _) in enumerate(new)]
        self._n_factors += len(added)
        ids = {id(lk) for lk in gone}
        self._links = [lk for lk in self._links if id(lk) not in ids] + added
        return added

    @contextlib.contextmanager
    def _full_check(self):
        prm = self._isam.params()  # a reference: ISAM2 reads it at every update
        prm.enablePartialRelinearizationCheck = False
        try:
            yield
        finally:
            self._isam.params().enablePartialRelinearizationCheck = True

    def _converge_locked(self, tolerance: float = 1e-5) -> int:
        """Extra iSAM2 updates (each one Gauss-Newton step on the relinearised part) until
        nothing is relinearised any more or no pose entry moves more than ``tolerance`` (m, and
        rotation-matrix entries) in a step. After a loop over the whole graph every step
        re-eliminates every node (~0.3 s at 10k nodes) and the steps shrink only linearly along
        the long, weakly determined chains (67 m, 0.6, 0.03, 7e-3, 5e-4, 2e-6 at 10k). Returns the
        number of updates."""
        with self._full_check():
            return self._iterate_locked(tolerance)

    def _iterate_locked(self, tolerance: float) -> int:
        n = 0
        prev = self._stacked_estimate_locked()
        while n < self.max_iterations - 1:
            r = self._isam.update()
            n += 1
            self._cache = None
            if r.getVariablesRelinearized() == 0:
                break
            cur = self._stacked_estimate_locked()
            if cur.shape == prev.shape and float(np.abs(cur - prev).max(initial=0.0)) < tolerance:
                break
            prev = cur
        return n

    def _stacked_estimate_locked(self) -> np.ndarray:
        est = self._estimate_locked()
        return np.stack(list(est.values())) if est else np.zeros((0, 4, 4))

    # -- reading --------------------------------------------------------------------------

    def _estimate_locked(self) -> dict[int, np.ndarray]:
        if self._cache is None:
            values = self._isam.calculateEstimate()
            keys = list(values.keys())
            if keys:
                flat = np.asarray(gtsam.utilities.extractPose3(values))  # rows: R row-major, t
                mats = np.zeros((len(keys), 4, 4))
                mats[:, :3, :3] = flat[:, :9].reshape(-1, 3, 3)
                mats[:, :3, 3] = flat[:, 9:12]
                mats[:, 3, 3] = 1.0
                mats.setflags(write=False)
                self._cache = {int(k): mats[i] for i, k in enumerate(keys)}
            else:
                self._cache = {}
        return self._cache

    def _pose_locked(self, node_id: int) -> np.ndarray:
        if self._cache is not None and node_id in self._cache:
            return self._cache[node_id]
        return self._isam.calculateEstimatePose3(node_id).matrix()

    def _link_errors_locked(self, est: dict[int, np.ndarray]) -> np.ndarray:
        if not self._links:
            return np.zeros(0)
        pf = np.stack([est[lk.from_id] for lk in self._links])
        pt = np.stack([est[lk.to_id] for lk in self._links])
        tr = np.stack([lk.transform for lk in self._links])
        inf = np.stack([lk.information for lk in self._links])
        return normalized_errors(pf, pt, tr, inf)

    def _publish_locked(self) -> None:
        est = self._estimate_locked()
        with self._snap_lock:
            self._snap = dict(est)

    def poses(self) -> dict[int, np.ndarray]:
        """Current estimate of every node: a new dict of read-only 4×4 arrays. Never waits for
        an optimisation in progress (it sees the estimate from before it)."""
        with self._snap_lock:
            return dict(self._snap)

    def pose(self, node_id: int) -> np.ndarray:
        """Current estimate of one node (a copy); never waits for an optimisation."""
        nid = int(node_id)
        with self._snap_lock:
            p = self._snap.get(nid)
        if p is None:
            raise KeyError(f"node {nid} is not in the graph")
        return p.copy()

    def link_errors(self) -> list[tuple[int, int, bool, float]]:
        """(from, to, is_loop, normalised error) of every active link on the current estimate."""
        with self._lock:
            errs = self._link_errors_locked(self._estimate_locked())
            return [(lk.from_id, lk.to_id, lk.loop, float(e)) for lk, e in zip(self._links, errs)]

    def loops(self) -> list[tuple[int, int]]:
        with self._lock:
            return [(lk.from_id, lk.to_id) for lk in self._links if lk.loop]

    def changed_poses(self, tolerance: tuple[float, float] | None = None) -> dict[int, np.ndarray]:
        """Poses that moved more than (metres, radians) since the previous call, plus nodes not
        reported yet — what the caller writes with ``MapStore.update_poses`` before emitting
        'map corrected'."""
        tol_t, tol_r = self.move_tolerance if tolerance is None else tolerance
        with self._lock:
            est = self._estimate_locked()
            out: dict[int, np.ndarray] = {}
            old_ids = [k for k in est if k in self._published]
            out.update({k: est[k].copy() for k in est if k not in self._published})
            if old_ids:
                cur = np.stack([est[k] for k in old_ids])
                prev = np.stack([self._published[k] for k in old_ids])
                dt = np.linalg.norm(cur[:, :3, 3] - prev[:, :3, 3], axis=1)
                rel = np.einsum("nji,njk->nik", prev[:, :3, :3], cur[:, :3, :3])
                dr = np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1))
                for i in np.nonzero((dt > tol_t) | (dr > tol_r))[0]:
                    out[old_ids[i]] = cur[i].copy()
            for k, v in out.items():
                self._published[k] = v.copy()
            return out

    @staticmethod
    def _max_move(a: dict[int, np.ndarray], b: dict[int, np.ndarray]) -> float:
        keys = [k for k in a if k in b]
        if not keys:
            return 0.0
        return float(np.max(np.abs(np.stack([a[k] for k in keys]) - np.stack([b[k] for k in keys]))))

    def __len__(self) -> int:
        with self._lock:
            return len(self._nodes)

    def __contains__(self, node_id) -> bool:
        with self._lock:
            return int(node_id) in self._raw

    # -- batch ----------------------------------------------------------------------------

    def factor_graph(self) -> gtsam.NonlinearFactorGraph:
        """The active factors (priors, odometry, loops) as one graph, for batch solvers."""
        with self._lock:
            return self._isam.getFactorsUnsafe().clone()

    def batch_optimize(self, max_iterations: int = 100, apply: bool = False) -> dict[int, np.ndarray]:
        """Levenberg–Marquardt over the whole graph from the current estimate; returns the poses.
        ``apply=True`` restarts iSAM2 from the batch solution (same factors). Meant for tests and
        comparison: a restarted iSAM2 gets a batch (COLAMD) ordering, and keyframes added after it
        cost several times more (2-3 ms instead of 0.6 ms at 8-10k nodes); solving large loops
        this way was also slower than iSAM2's steps (1.45 s vs 0.83 s CPU at 5k nodes)."""
        with self._lock:
            graph = gtsam.NonlinearFactorGraph()
            factors = self._isam.getFactorsUnsafe()
            for i in range(factors.size()):
                f = factors.at(i)
                if f is not None:
                    graph.add(f)
            initial = self._isam.calculateEstimate()
            params = gtsam.LevenbergMarquardtParams()
            params.setMaxIterations(max_iterations)
            params.setRelativeErrorTol(1e-12)
            params.setAbsoluteErrorTol(1e-14)
            result = gtsam.LevenbergMarquardtOptimizer(graph, initial, params).optimize()
            if apply:
                self._isam = gtsam.ISAM2(self._params)
                self._isam.update(graph, result)
                # indices are renumbered: rebuild them in factor order (priors/links kept in order)
                self._renumber_locked()
                self._cache = None
                self._publish_locked()
            keys = list(result.keys())
            return {int(k): result.atPose3(k).matrix() for k in keys}

    def _renumber_locked(self) -> None:
        old = sorted([(lk.factor_index, "l", lk) for lk in self._links] +
                     [(p[2], "p", n) for n, p in self._priors.items()], key=lambda x: x[0])
        for new, (_, kind, obj) in enumerate(old):
            if kind == "l":
                cast(_Link, obj).factor_index = new
            else:
                pose, sig, _ = self._priors[cast(int, obj)]
                self._priors[cast(int, obj)] = (pose, sig, new)
        self._n_factors = len(old)
