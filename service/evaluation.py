"""Trajectory accuracy: absolute trajectory error (ATE) and relative pose error (RPE).

Follows TUM RGB-D's ``evaluate_ate.py`` / ``evaluate_rpe.py`` and evo:

* estimate and ground truth are associated one-to-one by nearest timestamp (``associate_stamps``);
* ATE: the estimate's positions are aligned onto the ground truth (Umeyama, SE(3) or Sim(3)),
  then the per-pose position errors (metres) are summarised;
* RPE: for matched pose pairs (i, i + delta), delta counted in matched poses (frames), the error
  of the estimated relative motion against the true one. It does not depend on the rigid
  alignment; under Sim(3) the estimate's translations are scaled by the recovered scale first.

Everything is vectorized over the poses.
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from mnemoslam.client.kernel.geometry import invert
from mnemoslam.client.kernel.trajectory import Trajectory, read_kitti_poses, read_tum
from mnemoslam.storage import LINK_NAMES, link_name

ALIGN_MODES = ("se3", "sim3", "none")


def associate_stamps(gt_stamps: np.ndarray, est_stamps: np.ndarray,
                     max_dt: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one nearest-timestamp matching.

    Every estimate stamp is paired with the nearest ground-truth stamp when they differ by at most
    ``max_dt`` seconds. When several estimates claim the same ground-truth stamp, only the one with
    the smallest |dt| keeps it (ties: the earlier estimate), so each index is used at most once.
    Inputs need not be sorted. Returns ``(i_gt, i_est)`` integer index arrays, ordered by
    estimate stamp.
    """
    gt = np.asarray(gt_stamps, dtype=np.float64).reshape(-1)
    est = np.asarray(est_stamps, dtype=np.float64).reshape(-1)
    empty = np.zeros(0, dtype=np.intp)
    if len(gt) == 0 or len(est) == 0:
        return empty, empty.copy()
    order = np.argsort(gt, kind="stable")
    g = gt[order]
    k = np.searchsorted(g, est)                        # g[k-1] < est <= g[k]
    lo, hi = np.clip(k - 1, 0, len(g) - 1), np.clip(k, 0, len(g) - 1)
    nearest = np.where(np.abs(g[lo] - est) <= np.abs(g[hi] - est), lo, hi)
    dt = np.abs(g[nearest] - est)
    i_est = np.flatnonzero(dt <= max_dt)
    # Best candidates first (stable: ties keep estimate order), then first claim of each gt wins.
    i_est = i_est[np.lexsort((est[i_est], dt[i_est]))]
    _, first = np.unique(nearest[i_est], return_index=True)
    i_est = i_est[first]
    i_est = i_est[np.argsort(est[i_est], kind="stable")]
    return order[nearest[i_est]].astype(np.intp), i_est.astype(np.intp)


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares (s, R, t) minimising sum ||dst - (s R src + t)||^2 (Umeyama 1991).

    ``src`` and ``dst`` are (N, 3) corresponding points. R is always a proper rotation
    (det +1; a reflection is replaced by the best rotation). Collinear input leaves the rotation
    about the line undetermined: a valid rotation is still returned. With ``with_scale=False``,
    or when ``src`` has no spread (all points identical), s = 1. Raises ValueError for N < 3.
    """
    src = np.asarray(src, dtype=np.float64).reshape(-1, 3)
    dst = np.asarray(dst, dtype=np.float64).reshape(-1, 3)
    if len(src) != len(dst):
        raise ValueError(f"umeyama: {len(src)} source points for {len(dst)} destination points")
    if len(src) < 3:
        raise ValueError(f"umeyama: need at least 3 point pairs to align, got {len(src)}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    U, D, Vt = np.linalg.svd(cov)
    S = np.ones(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2] = -1.0
    R = U @ np.diag(S) @ Vt
    var_s = float((xs ** 2).sum() / len(src))
    s = float(D @ S / var_s) if with_scale and var_s > 1e-12 else 1.0
    t = mu_d - s * R @ mu_s
    return R, t, s


@dataclass
class EvalResult:
    """Accuracy of an estimated trajectory against ground truth (metres, degrees)."""

    align: str
    matched: int
    gt_count: int
    est_count: int
    max_dt: float
    ate_rmse: float
    ate_mean: float
    ate_median: float
    ate_max: float
    scale: float
    rpe_delta: int
    rpe_trans_rmse: float
    rpe_rot_rmse: float
    path_length: float
    ate_percent_of_path: float

    def to_dict(self) -> dict:
        """Plain JSON-serialisable dict; non-finite numbers become None."""
        return {k: (None if isinstance(v, float) and not np.isfinite(v) else v)
                for k, v in asdict(self).items()}

    def format(self) -> str:
        """Human-readable multi-line summary."""
        pct = f"{self.ate_percent_of_path:.3f} %" if np.isfinite(self.ate_percent_of_path) else "n/a"
        return "\n".join([
            f"matched      {self.matched} poses (estimate {self.est_count}, ground truth {self.gt_count},"
            f" max_dt {self.max_dt:g} s)",
            f"alignment    {self.align}  scale {self.scale:.6f}",
            f"ATE rmse     {self.ate_rmse:.6f} m",
            f"ATE mean     {self.ate_mean:.6f} m   median {self.ate_median:.6f} m   max {self.ate_max:.6f} m",
            f"ATE / path   {pct} of {self.path_length:.6f} m",
            f"RPE trans    {self.rpe_trans_rmse:.6f} m rmse   (delta {self.rpe_delta} frames)",
            f"RPE rot      {self.rpe_rot_rmse:.6f} deg rmse",
        ])


def _angle(R: np.ndarray) -> np.ndarray:
    """Rotation angles (radians) of (..., 3, 3) matrices via atan2: precise near 0 and pi,
    unlike arccos of the trace."""
    vee = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0],
                    R[..., 1, 0] - R[..., 0, 1]], -1)
    return np.arctan2(0.5 * np.linalg.norm(vee, axis=-1), 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1))


def _rmse(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(x ** 2)))


def evaluate(gt: Trajectory, est: Trajectory, align: str = "se3", max_dt: float = 0.02,
             rpe_delta: int = 1) -> EvalResult:
    """Associate ``est`` with ``gt`` by stamp, align (``"se3"``, ``"sim3"`` or ``"none"``) and
    compute ATE and RPE.

    ``rpe_delta`` is the RPE step in matched poses (frames), not seconds: pairs (i, i + delta)
    over the matched sequence. Raises ValueError when fewer than 3 poses match, when
    ``rpe_delta`` is not in [1, matched), or for an unknown alignment mode.
    """
    if align not in ALIGN_MODES:
        raise ValueError(f"unknown alignment {align!r}; expected one of {', '.join(ALIGN_MODES)}")
    i_gt, i_est = associate_stamps(gt.stamps, est.stamps, max_dt)
    n = len(i_gt)
    if n < 3:
        raise ValueError(f"only {n} poses matched between ground truth ({len(gt)}) and estimate "
                         f"({len(est)}) within max_dt={max_dt} s; need at least 3 "
                         "(check that both files use the same time base)")
    if not 1 <= rpe_delta < n:
        raise ValueError(f"rpe_delta must be in [1, {n - 1}] for {n} matched poses, got {rpe_delta}")
    G, E = gt.poses[i_gt], est.poses[i_est].copy()

    if align == "none":
        R, t, s = np.eye(3), np.zeros(3), 1.0
    else:
        R, t, s = umeyama(E[:, :3, 3], G[:, :3, 3], with_scale=align == "sim3")
    aligned = s * E[:, :3, 3] @ R.T + t
    err = np.linalg.norm(aligned - G[:, :3, 3], axis=1)

    # RPE: error of the relative motion; a rigid world change cancels, only the scale matters.
    E[:, :3, 3] *= s
    d = rpe_delta
    rel_g = invert(G[:-d]) @ G[d:]
    rel_e = invert(E[:-d]) @ E[d:]
    rel_err = invert(rel_g) @ rel_e
    rpe_t = np.linalg.norm(rel_err[:, :3, 3], axis=1)
    rpe_r = np.degrees(_angle(rel_err[:, :3, :3]))

    path = float(np.linalg.norm(np.diff(G[:, :3, 3], axis=0), axis=1).sum())
    ate_rmse = _rmse(err)
    return EvalResult(
        align=align, matched=n, gt_count=len(gt), est_count=len(est), max_dt=float(max_dt),
        ate_rmse=ate_rmse, ate_mean=float(err.mean()), ate_median=float(np.median(err)),
        ate_max=float(err.max()), scale=float(s), rpe_delta=int(d),
        rpe_trans_rmse=_rmse(rpe_t), rpe_rot_rmse=_rmse(rpe_r), path_length=path,
        ate_percent_of_path=100.0 * ate_rmse / path if path > 0 else float("nan"),
    )


def _column_count(path: Path) -> int:
    """Number of fields on the first data line (comments and blank lines skipped); 0 if none."""
    try:
        with open(path) as f:
            for line in f:
                line = line.strip().replace(",", " ")
                if line and not line.startswith("#"):
                    return len(line.split())
    except OSError:
        pass  # let the reader raise its DatasetError naming the file
    return 0


def read_trajectory(path: str | Path) -> Trajectory:
    """TUM file (``t tx ty tz qx qy qz qw``), or KITTI poses (12 numbers per line, stamps k * 0.1 s)
    detected by column count."""
    path = Path(path)
    return read_kitti_poses(path) if _column_count(path) == 12 else read_tum(path)


def evaluate_files(gt_path: str | Path, est_path: str | Path, align: str = "se3", max_dt: float = 0.02,
                   as_json: bool = False, rpe_delta: int = 1) -> str:
    """Evaluate an estimate file against a ground-truth file (TUM or KITTI poses, see
    ``read_trajectory``) and return the report: ``EvalResult.format()`` text, or a JSON object
    when ``as_json``. Raises DatasetError for unreadable files, ValueError as ``evaluate``."""
    res = evaluate(read_trajectory(gt_path), read_trajectory(est_path), align=align, max_dt=max_dt,
                   rpe_delta=rpe_delta)
    return json.dumps(res.to_dict(), indent=2) if as_json else res.format()


def _node_truth(gt: Trajectory, stamps: np.ndarray, max_dt: float) -> np.ndarray:
    """(n, 4, 4) ground-truth pose of each keyframe stamp; NaN where none is within `max_dt`."""
    gi, ei = associate_stamps(gt.stamps, stamps, max_dt)
    P = np.full((len(stamps), 4, 4), np.nan)
    P[ei] = gt.poses[gi]
    return P


def _link_errors(P: np.ndarray, node_ids, from_ids, to_ids, transforms):
    """Errors of links T_from_to against the keyframes' true poses `P` (rows in `node_ids`
    order; NaN: no ground truth), vectorized over the links. Returns ((rows of the from
    keyframes, rows of the to keyframes), kept: mask over the links with both keyframes in
    `P`) packed as ((ka, kb, kept), translation error m, rotation error deg) for the kept
    links: the error is the transform between the measured and the true relative pose."""
    ids = np.asarray(node_ids, np.int64)
    order = np.argsort(ids, kind="stable")
    a, b = np.asarray(from_ids, np.int64).reshape(-1), np.asarray(to_ids, np.int64).reshape(-1)

    def rows(x):
        k = np.clip(np.searchsorted(ids[order], x), 0, max(len(ids) - 1, 0))
        found = (ids[order][k] == x) if len(ids) else np.zeros(len(x), bool)
        return order[k] if len(ids) else k, found

    (ka, fa), (kb, fb) = rows(a), rows(b)
    kept = fa & fb
    kept[kept] &= ~np.isnan(P[ka[kept], 0, 0]) & ~np.isnan(P[kb[kept], 0, 0])
    ka, kb = ka[kept], kb[kept]
    T = np.asarray(transforms, np.float64).reshape(-1, 4, 4)[kept] if kept.any() else np.zeros((0, 4, 4))
    e = invert(invert(P[ka]) @ P[kb]) @ T
    return (ka, kb, kept), np.linalg.norm(e[:, :3, 3], axis=1), np.degrees(_angle(e[:, :3, :3]))


@dataclass
class LoopReport:
    """Loop links against ground truth: precision (true links / links) and recall (keyframes
    that revisit a place seen ≥ `min_age` s earlier and got a true link)."""

    links: int
    false_links: int
    precision: float
    revisits: int
    recalled: int
    recall: float
    link_error_median: float  # metres
    link_error_max: float

    def format(self) -> str:
        """One line; without links or without revisits it says so instead of a vacuous ratio
        (precision / recall default to 1.0 then) and NaN link errors."""
        if self.links:
            parts = [f"{self.links} links, {self.false_links} false (precision {self.precision:.3f})"]
        else:
            parts = ["no loop links"]
        if self.revisits:
            parts.append(f"recall {self.recall:.3f} ({self.recalled}/{self.revisits} revisiting keyframes)")
        else:
            parts.append("no true revisits (no keyframe came back to a place seen earlier)")
        if self.links:
            parts.append(f"link error median {self.link_error_median * 100:.2f} cm, "
                         f"max {self.link_error_max * 100:.2f} cm")
        return "loops        " + "; ".join(parts)


def evaluate_loops(gt: Trajectory, node_ids, node_stamps, links, min_age: float = 10.0,
                   revisit_radius: float = 0.5, revisit_angle_deg: float = 30.0, max_dt: float = 0.02,
                   true_link: tuple[float, float] = (0.10, 5.0)) -> LoopReport:
    """Score loop links `links` = [(from_id, to_id, T_from_to)] between keyframes
    (`node_ids`, `node_stamps`) against ground truth.

    A link is true when its transform is within `true_link` (metres, degrees) of the true
    relative pose. A keyframe revisits when an older keyframe (by `min_age` s or more) has
    its true camera within `revisit_radius` and its optical axis within `revisit_angle_deg`.
    Keyframes without a ground-truth pose within `max_dt` count as neither."""
    stamps = np.asarray(node_stamps, np.float64)
    P = _node_truth(gt, stamps, max_dt)
    links = list(links)
    scored, err, err_deg = _link_errors(P, node_ids, [a for a, _, _ in links], [b for _, b, _ in links],
                                        [T for _, _, T in links])
    true = (err < true_link[0]) & (err_deg < true_link[1])
    linked = np.zeros(len(stamps), bool)
    linked[scored[0][true]] = linked[scored[1][true]] = True
    n = len(err)
    false = n - int(true.sum())
    has = ~np.isnan(P[:, 0, 0])
    pos, fwd = P[:, :3, 3], P[:, :3, 2]
    dist = np.linalg.norm(pos[:, None] - pos[None], axis=2)
    with np.errstate(invalid="ignore"):
        ang = np.degrees(np.arccos(np.clip(fwd @ fwd.T, -1, 1)))
        older = stamps[None, :] <= stamps[:, None] - min_age
        revisit = ((dist < revisit_radius) & (ang < revisit_angle_deg) & older & has[None, :]).any(axis=1) & has
    recalled = int((revisit & linked).sum())
    return LoopReport(n, false, (n - false) / n if n else 1.0, int(revisit.sum()), recalled,
                      recalled / revisit.sum() if revisit.any() else 1.0,
                      float(np.median(err)) if n else float("nan"), float(err.max()) if n else float("nan"))


def evaluate_map_loops(gt: Trajectory, db_path: str | Path, min_age: float = 10.0, types=None,
                       session_id: int | None = None, **options) -> LoopReport:
    """`evaluate_loops` (with `options`) over the links of a map database of the given
    `types` (LinkType values; default: every loop link, appearance and proximity by space, and
    rehearsal's `merged` links: a keyframe merged into the node of a place seen before closed
    that revisit as a loop link would, with the merge link's relative pose). With
    `session_id`, only that session's keyframes and the links between them (the ground truth
    is one session's: another session's stamps mean other poses)."""
    from mnemoslam.storage import LinkType, MapStore

    types = (LinkType.GLOBAL_CLOSURE, LinkType.LOCAL_SPACE, LinkType.MERGED) if types is None else types
    with MapStore(db_path, create=False) as store:
        nodes, links = _session_graph(store, session_id, types)
    return evaluate_loops(gt, [n.id for n in nodes], [n.stamp for n in nodes],
                          [(x.from_id, x.to_id, x.transform) for x in links], min_age=min_age, **options)


# -- link accuracy ------------------------------------------------------------------------------

LINK_KINDS = LINK_NAMES
"""Report names of the graph's link types: the one table, `storage.LINK_NAMES` (by LinkType,
which looks up by its int value too; `storage.link_name` names an unknown type by its number)."""

LINK_CSV_COLUMNS = ("from_id", "to_id", "type", "error_cm", "error_deg")


@dataclass
class LinkTypeAccuracy:
    """The links of one type against ground truth (errors of their measured relative pose)."""

    kind: str
    count: int  # links with both keyframes in the ground truth
    median_cm: float
    max_cm: float
    median_deg: float
    max_deg: float
    beyond: int  # links beyond either bound (LinkReport.bounds)
    unmatched: int = 0  # links of this type left out: a keyframe without a ground-truth pose


@dataclass
class LinkReport:
    """Per-type accuracy of a pose graph's links and the per-link errors (`rows`: from id,
    to id, kind, error cm, error deg)."""

    bounds: tuple[float, float]  # (cm, deg): a link beyond either is counted in `beyond`
    types: list[LinkTypeAccuracy]
    rows: list[tuple[int, int, str, float, float]]

    def by_kind(self) -> dict[str, LinkTypeAccuracy]:
        return {t.kind: t for t in self.types}

    def format(self) -> str:
        """One line per link type; "links        none" without links."""
        if not self.types:
            return "links        none with ground truth"
        cm, deg = self.bounds
        lines = []
        for t in self.types:
            if not t.count:
                lines.append(f"links        {t.kind:<10} {t.unmatched} without ground truth")
                continue
            lines.append(f"links        {t.kind:<10} {t.count:4d}: median {t.median_cm:.2f} cm / "
                         f"{t.median_deg:.2f} deg, worst {t.max_cm:.2f} cm / {t.max_deg:.2f} deg, "
                         f"{t.beyond} beyond {cm:g} cm or {deg:g} deg"
                         + (f" ({t.unmatched} without ground truth)" if t.unmatched else ""))
        return "\n".join(lines)

    def to_dict(self) -> dict:
        """The summary (no per-link rows), JSON-serialisable."""
        return {"bounds_cm_deg": list(self.bounds),
                "types": [{k: (None if isinstance(v, float) and not np.isfinite(v) else v)
                           for k, v in asdict(t).items()} for t in self.types]}

    def write(self, folder: str | Path) -> None:
        """`links.csv` (one row per link with ground truth) and `links.json` (the summary)."""
        folder = Path(folder)
        with open(folder / "links.csv", "w") as f:
            f.write(",".join(LINK_CSV_COLUMNS) + "\n")
            f.writelines(f"{a},{b},{k},{e:.4f},{d:.4f}\n" for a, b, k, e, d in self.rows)
        (folder / "links.json").write_text(json.dumps(self.to_dict(), indent=2) + "\n")


def evaluate_links(gt: Trajectory, node_ids, node_stamps, links, max_dt: float = 0.02,
                   bounds: tuple[float, float] = (5.0, 3.0)) -> LinkReport:
    """Accuracy of graph links `links` = [(from_id, to_id, type, T_from_to)] between keyframes
    (`node_ids`, `node_stamps`) against ground truth, per type (`storage.LINK_NAMES` names; an
    unknown type by its number): the error of a link is the rigid transform between its
    measured T_from_to and the true relative pose of the two keyframes' stamps; count,
    median and worst (cm, degrees), and how many are beyond `bounds` (cm, degrees).
    Types are listed in their numeric order."""
    links = list(links)
    stamps = np.asarray(node_stamps, np.float64)
    P = _node_truth(gt, stamps, max_dt)
    types = np.array([int(t) for _, _, t, _ in links], np.int64)
    (ka, kb, kept), err, err_deg = _link_errors(P, node_ids, [x[0] for x in links], [x[1] for x in links],
                                                np.stack([np.asarray(x[3], np.float64) for x in links])
                                                if links else np.zeros((0, 4, 4)))
    err_cm = err * 100.0
    kinds = [link_name(t) for t in types]
    ids = np.asarray(node_ids, np.int64)
    kept_types = types[kept]
    out = []
    for t in np.unique(types).tolist():
        sel = kept_types == t
        e, d = err_cm[sel], err_deg[sel]
        n = int(sel.sum())
        out.append(LinkTypeAccuracy(
            link_name(t), n, float(np.median(e)) if n else float("nan"),
            float(e.max()) if n else float("nan"), float(np.median(d)) if n else float("nan"),
            float(d.max()) if n else float("nan"), int(((e > bounds[0]) | (d > bounds[1])).sum()),
            int((types == t).sum()) - n))
    kept_kinds = [k for k, keep in zip(kinds, kept) if keep]
    rows = [(int(ids[a]), int(ids[b]), k, float(e), float(d))
            for a, b, k, e, d in zip(ka, kb, kept_kinds, err_cm, err_deg)]
    return LinkReport((float(bounds[0]), float(bounds[1])), out, rows)


def _session_graph(store, session_id: int | None, types=None) -> tuple[list, list]:
    """(nodes, links of `types` or all) of the map, or of one session (links inside it)."""
    nodes = store.nodes(limit=None, session_id=session_id)
    links = [x for t in types for x in store.links(type=t)] if types is not None else store.links()
    if session_id is not None:
        mine = {n.id for n in store.nodes(limit=None, session_id=session_id, merged=None)}
        links = [x for x in links if x.from_id in mine and x.to_id in mine]
    return nodes, links


def evaluate_map_links(gt: Trajectory, db_path: str | Path, max_dt: float = 0.02,
                       bounds: tuple[float, float] = (5.0, 3.0), session_id: int | None = None) -> LinkReport:
    """`evaluate_links` over every link of a map database (every session, merged keyframes
    included; with `session_id`, as `evaluate_map_loops`)."""
    from mnemoslam.storage import MapStore

    with MapStore(db_path, create=False) as store:
        nodes, links = _session_graph(store, session_id)
    return evaluate_links(gt, [n.id for n in nodes], [n.stamp for n in nodes],
                          [(x.from_id, x.to_id, int(x.type), x.transform) for x in links], max_dt, bounds)
