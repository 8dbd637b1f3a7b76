"""Offline runs: play a dataset through the pipeline and write the trajectories."""
from __future__ import annotations

import contextlib
import csv
import json
import logging
import tempfile
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from mnemoslam.client.datasets import Dataset
from mnemoslam.client.kernel.frames import DatasetError
from mnemoslam.client.kernel.geometry import invert
from mnemoslam.client.kernel.trajectory import Trajectory, write_tum
from mnemoslam.storage import MapStore

from .builder import build_pipeline
from .config import Config
from .evaluation import LinkReport, evaluate_map_links
from .pipeline import FrameResult, Pipeline

log = logging.getLogger("mnemoslam.run")


@dataclass
class RunSummary:
    dataset: str
    frames: int
    tracked: int
    keyframes: int
    lost: int
    skipped: int
    bad: int  # frames whose files could not be read
    segments: int
    seconds: float
    fps: float
    loops: int = 0  # accepted loop closures
    merged: int = 0  # keyframes merged into a node the map had (rehearsal): the map has keyframes - merged nodes
    links_dropped: int = 0  # verified loop / proximity links refused because their estimated uncertainty was too large
    # the map database's session of the run, and which map it ended in (its own, or an older one it joined:
    # `run --db` onto an existing map); joined_* say when (its keyframe at the joining link, that keyframe's stamp)
    session: int | None = None
    map: int | None = None
    joined: bool = False
    joined_keyframe: int | None = None
    joined_stamp: float | None = None
    joined_index: int | None = None  # the dataset's frame index of that keyframe
    cross_links: int = 0  # links between the session's keyframes and other sessions' (all types)
    cross_links_by_type: dict | None = None  # {link type name: count}
    sessions_before: int = 0  # sessions the map database had before the run
    # localization only (memory.incremental: false, with --db): nothing was written to the map; the
    # frame (index, stamp) whose pose first went out in the map's frame, and how many tracked frames did
    localization: bool = False
    relocalized_index: int | None = None
    relocalized_stamp: float | None = None
    frames_in_map: int = 0
    forgotten: int = 0  # keyframes the localizer forgot (it keeps the newest memory.localization_nodes)
    held: int = 0  # ... and those its graph held at the end (at most twice that)

    def line(self) -> str:
        merged = f" ({self.merged} merged)" if self.merged else ""
        dropped = f" ({self.links_dropped} inaccurate link(s) dropped)" if self.links_dropped else ""
        return (f"{self.dataset}: {self.frames} frames, {self.tracked} tracked, {self.keyframes} keyframes{merged}, "
                f"{self.lost} lost, {self.skipped} skipped, {self.bad} unreadable, {self.segments} segment(s), "
                f"{self.loops} loop(s){dropped}, {self.fps:.1f} frames/s")

    def map_line(self) -> str | None:
        """Where the session ended up in a map with older sessions (None for a run into a new map)."""
        if self.localization:
            if self.relocalized_index is None:
                return ("localization only: never relocalized in the map (every pose in the run's own frame); "
                        "nothing written to it")
            return (f"localization only: relocalized in map {self.map} at frame {self.relocalized_index} (stamp "
                    f"{self.relocalized_stamp:.3f} s); {self.frames_in_map} of {self.tracked} tracked frames in "
                    f"the map's frame; nothing written to it")
        if self.session is None or not self.sessions_before:
            return None
        by_type = ", ".join(f"{n} {k}" for k, n in sorted((self.cross_links_by_type or {}).items()))
        links = f"{self.cross_links} cross-session link(s)" + (f" ({by_type})" if by_type else "")
        if self.joined:
            return (f"session {self.session} joined map {self.map} at keyframe {self.joined_keyframe} (frame "
                    f"{self.joined_index}, stamp {self.joined_stamp:.3f} s); {links}; trajectories in map "
                    f"{self.map}'s frame")
        return (f"session {self.session} did not join the map's {self.sessions_before} older session(s): a map of "
                f"its own ({self.map}); {links}; trajectories in its own frame")


@dataclass
class RunOutput:
    summary: RunSummary
    trajectory: Trajectory  # every tracked frame at its final map pose (anchored on its keyframe)
    keyframes: Trajectory  # keyframes at their final (optimized) poses
    results: list[FrameResult]
    online: Trajectory | None = None  # every tracked frame as published while running (map at that time)
    # synthetic + semantics: frames in which ≥ 200 px of each instance id were visible
    instance_frames: np.ndarray | None = None
    links: "LinkReport | None" = None  # the map's links against ground truth, per type (datasets with ground truth)
    grid: dict | None = None  # the map grid's files and figures (grid.enabled, with out_dir): see write_run_grids

    def __post_init__(self):
        if self.online is None:
            self.online = self.trajectory


def run_dataset(dataset: Dataset, config: Config, out_dir: str | Path | None = None,
                progress: bool = True, db: str | Path | None = None) -> RunOutput:
    """Run every frame of `dataset` through one pipeline; write `trajectory.tum`,
    `keyframes.tum` (and `groundtruth.tum` when the dataset has it), the map database
    `map.db` (the same one the service writes; a run replaces it) or, with `db`, a new session
    in that map database (made when absent: the run continues the map, and its trajectories are
    in the map's frame once the session joined it, `RunSummary.joined`) and, with grid.enabled, the map's occupancy
    grid and cloud (`grid.pgm`, `grid.yaml`, `cloud.ply`; synthetic: `groundtruth_grid.*`)
    into `out_dir`; with `memory.incremental` false (localization only; needs `db`) the map
    is opened read-only and nothing is written to it: `trajectory.tum` holds the poses as
    they went out, in the map's frame from the first relocalization on
    (`RunSummary.relocalized_index`; before it in the run's own frame); with semantics on also
    `objects.json` (the fused objects at their final positions) and, for synthetic data,
    `groundtruth_objects.json` (the scene's objects and how many frames saw them)."""
    with contextlib.ExitStack() as stack:
        if out_dir is None:  # the map still lives in a database: a temporary one
            out_dir_db = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="mnemoslam-run-")))
        else:
            out_dir = Path(out_dir)
            out_dir.mkdir(parents=True, exist_ok=True)
            out_dir_db = out_dir
        localize = not config.memory.incremental
        if localize and (db is None or not Path(db).is_file()):
            raise DatasetError("memory.incremental=false (localization only) needs a map to localize in: --db MAP.db"
                               + ("" if db is None else f" ({db} does not exist)"))
        if db is None:
            db = out_dir_db / "map.db"
            for p in (db, db.with_name("map.db-wal"), db.with_name("map.db-shm")):
                p.unlink(missing_ok=True)  # a run replaces the previous run's map
        else:  # a session more in that map (a new file when absent; its folder must exist)
            db = Path(db)
            if not db.parent.is_dir():
                raise DatasetError(f"--db {db}: the folder {db.parent} does not exist")
        store = stack.enter_context(MapStore(db, readonly=localize))
        before = len(store.sessions())
        pipeline = build_pipeline(store, dataset.name, dataset.calibration, config)  # map update inline
        out = _run(dataset, pipeline, progress)
        pipeline.close()  # the graph's final poses to the database, the session ended
        mapper = pipeline.mapper
        if localize:
            _localized(store, pipeline, out, before)
        elif mapper is not None:  # keyframes, and every frame through its keyframe, at their final poses
            final = mapper.keyframe_poses()
            ids = [r.node_id for r in out.results if r.node_id is not None]
            out.keyframes = Trajectory(np.array([r.stamp for r in out.results if r.node_id is not None]),
                                       np.stack([final[i] for i in ids]) if ids else np.zeros((0, 4, 4)))
            out.online = out.trajectory
            out.trajectory = _anchored(out.results, final)
            out.summary.loops = len(mapper.loops)
            out.summary.merged = mapper.merged
            out.summary.links_dropped = mapper.links_dropped
        if not localize:
            _session_map(store, pipeline.session_id, out, before)
        if dataset.ground_truth is not None and not localize:  # every link of the map against the true relative poses
            out.links = evaluate_map_links(dataset.ground_truth, db, session_id=pipeline.session_id)
    if out_dir is not None:
        write_tum(out_dir / "trajectory.tum", out.trajectory)
        write_tum(out_dir / "trajectory_online.tum", out.online)
        write_tum(out_dir / "keyframes.tum", out.keyframes)
        if dataset.ground_truth is not None:
            write_tum(out_dir / "groundtruth.tum", dataset.ground_truth)
        if out.links is not None:
            out.links.write(out_dir)
        (out_dir / "summary.json").write_text(json.dumps(asdict(out.summary), indent=2) + "\n")
        if mapper is not None and not localize:
            with MapStore(db, create=False) as reader:  # every update's statistics (the mapper keeps the last ones)
                write_updates(out_dir / "updates.csv", ((n, reader.statistics(n)) for n in ids))
        if pipeline.semantics is not None:
            with MapStore(db, create=False) as reader:
                write_objects(out_dir / "objects.json", reader.objects())
            if hasattr(dataset, "scene"):
                write_groundtruth_objects(out_dir / "groundtruth_objects.json", dataset.scene, out.instance_frames)
        if config.grid.enabled and not localize:
            out.grid = write_run_grids(db, out_dir, config, dataset, out.keyframes)
    return out


def _localized(store, pipeline: Pipeline, out: RunOutput, sessions_before: int) -> None:
    """A localization run's summary: when its poses first went out in the map's frame, in which
    map (storage.connectivity.MapIndex), how many did; `keyframes` as they went out."""
    from mnemoslam.storage.connectivity import MapIndex

    s = out.summary
    s.localization, s.sessions_before = True, sessions_before
    s.loops = len(pipeline.mapper.loops) if pipeline.mapper is not None else 0
    s.forgotten = getattr(pipeline.mapper, "forgotten", 0)
    s.held = getattr(pipeline.mapper, "held", 0)
    first = next((r for r in out.results if r.anchor is not None), None)
    s.frames_in_map = sum(r.anchor is not None for r in out.results)
    if first is not None:
        index = MapIndex()
        index.refresh(store)
        s.map, s.relocalized_index, s.relocalized_stamp = index.map_of(first.anchor), first.index, first.stamp


def _session_map(store, session_id: int | None, out: RunOutput, sessions_before: int) -> None:
    """The summary's session, its map and join (storage.connectivity.MapIndex), and its links
    to other sessions' keyframes."""
    from mnemoslam.storage import link_name
    from mnemoslam.storage.connectivity import MapIndex

    s = out.summary
    s.session, s.sessions_before = session_id, sessions_before
    if session_id is None:
        return
    index = MapIndex()
    index.refresh(store)
    j = index.join(session_id)
    s.map = j.map if j is not None else None
    if j is not None and j.joined:
        s.joined, s.joined_keyframe, s.joined_stamp = True, j.node, j.stamp
        s.joined_index = next((r.index for r in out.results if r.node_id == j.node), None)
    mine = {n.id for n in store.nodes(session_id=session_id, limit=None, merged=None)}
    by_type: dict[str, int] = {}
    for lk in store.links(session_id=session_id):
        if (lk.from_id in mine) != (lk.to_id in mine):
            by_type[link_name(lk.type)] = by_type.get(link_name(lk.type), 0) + 1
    s.cross_links, s.cross_links_by_type = sum(by_type.values()), by_type


def write_run_grids(db: Path, out_dir: Path, config: Config, dataset: Dataset, keyframes: Trajectory) -> dict | None:
    """DIR/grid.pgm + grid.yaml and DIR/cloud.ply of the run's map (service/grid/files.py); for
    the synthetic scene also DIR/groundtruth_grid.pgm + .yaml, its true floor plan on the same
    cells (the map frame placed in the scene by the first keyframe's true pose), and the
    grid's agreement with it. Returns {"cells": observed, "agree": share, ...} or None."""
    from .evaluation import associate_stamps
    from .grid.files import agreement, groundtruth_grid, write_grid, write_map_files

    with MapStore(db, create=False) as store:
        maps = write_map_files(store, out_dir, config.grid)
    if not maps:
        return None
    m = min(maps)
    grid = maps[m]["grid"]
    info = {"map": m, "observed": int((grid.states >= 0).sum()), "width": grid.width, "height": grid.height,
            "files": [str(p) for p in maps[m]["files"]]}
    if hasattr(dataset, "scene") and dataset.ground_truth is not None and len(keyframes):
        ig, ie = associate_stamps(dataset.ground_truth.stamps, keyframes.stamps)
        if len(ie):
            world_from_map = dataset.ground_truth.poses[ig[0]] @ invert(keyframes.poses[ie[0]])
            truth = groundtruth_grid(dataset.scene, grid, world_from_map)
            info["files"] += [str(p) for p in write_grid(out_dir, truth, "groundtruth_grid")]
            info.update({f"groundtruth_{k}": v for k, v in agreement(grid, truth).items()})
    return info


def object_dict(o) -> dict:
    """An object (storage.ObjectRecord) as objects.json and the REST API show it."""
    return {"id": o.id, "label": o.label, "confidence": round(float(o.confidence), 4),
            "position": [round(float(v), 4) for v in o.position], "extent": [round(float(v), 4) for v in o.extent],
            "observations": int(o.observations), "node_id": int(o.node_id)}


def write_objects(path: Path, objects) -> None:
    """objects.json: the fused objects, positions in the trajectory's frame (final graph poses)."""
    path.write_text(json.dumps([object_dict(o) for o in objects], indent=1) + "\n")


def write_groundtruth_objects(path: Path, scene, instance_frames: np.ndarray | None) -> None:
    """groundtruth_objects.json of a synthetic run: the scene's objects (id, label, centroid,
    extent, world frame) and `observed_frames`, in how many frames of the run at least
    `VISIBLE_PIXELS` of the object were visible (its id in the frames' `extras["instances"]`)."""
    seen = np.zeros(0, np.int64) if instance_frames is None else instance_frames
    out = [{"id": o.instance_id, "label": o.class_name, "name": o.name,
            "centroid": [round(float(v), 4) for v in o.center],
            "extent": [round(float(b - a), 4) for a, b in zip(o.bbox_min, o.bbox_max)],
            "observed_frames": int(seen[o.instance_id]) if o.instance_id < len(seen) else 0} for o in scene.objects]
    path.write_text(json.dumps(out, indent=1) + "\n")


VISIBLE_PIXELS = 200  # an object counts as seen in a frame with at least this many of its pixels


UPDATE_COLUMNS = ("keyframe", "stamp", "update_ms", "stm", "wm", "ltm", "transferred", "retrieved", "merged", "words")
UPDATE_STEPS = ("local_ba", "rehearsal", "graph", "vocabulary", "detection", "verification_optimization", "proximity",
                "path", "memory")


def write_updates(path: Path, statistics) -> None:
    """One row per map update (keyframe): its time in all and per step (ms), the STM / WM /
    LTM sizes after it, how many nodes it transferred to LTM, retrieved and merged, and the
    vocabulary's searchable words. `statistics`: (node id, its stored statistics dict) in
    keyframe order; keyframes without statistics are left out."""
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(UPDATE_COLUMNS + tuple(f"{s}_ms" for s in UPDATE_STEPS))
        for node, st in statistics:
            if not st:
                continue
            w.writerow(update_row(node, st.get("memory") or {}, st.get("timings_ms") or {}))


def update_row(node: int, memory: dict, timings: dict) -> list:
    """The updates.csv row of one map update from its statistics' `memory` and `timings_ms`."""
    m, t = memory, timings
    return [node, f"{m.get('stamp', float('nan')):.6f}", f"{sum(t.values()):.3f}", m.get("stm", ""), m.get("wm", ""),
            m.get("ltm", ""), len(m.get("transferred", ())), len(m.get("retrieved", ())), len(m.get("merged", ())),
            m.get("words", "")] + [f"{t.get(s, 0.0):.3f}" for s in UPDATE_STEPS]


def read_ahead(dataset: Dataset, ahead: int = 2):
    """The dataset's frames in order, each read (decoded or rendered) `ahead` frames early on
    one reader thread, so that decoding (which releases the GIL) overlaps the pipeline's
    work on the other core; a frame that cannot be read comes as its DatasetError. One
    reader, in order: the frames are the same as read one by one."""
    def read(i: int):
        try:
            return dataset.frame(i)
        except DatasetError as e:
            return e

    n = len(dataset)
    with ThreadPoolExecutor(1, thread_name_prefix="frame-reader") as pool:
        pending = deque(pool.submit(read, i) for i in range(min(ahead, n)))
        for i in range(n):
            frame = pending.popleft().result()
            if i + ahead < n:
                pending.append(pool.submit(read, i + ahead))
            yield frame


def _run(dataset: Dataset, pipeline: Pipeline, progress: bool) -> RunOutput:
    results: list[FrameResult] = []
    bad = 0
    seen = None  # per instance id: frames that showed ≥ VISIBLE_PIXELS of it (synthetic, semantics on)
    start = time.perf_counter()
    bar = tqdm(total=len(dataset), desc=dataset.name, unit="frame", disable=not progress, leave=False)
    for i, frame in enumerate(read_ahead(dataset)):
        if isinstance(frame, DatasetError):
            log.error("frame %d skipped: %s", i, frame)
            bad += 1
            bar.update()
            continue
        results.append(pipeline.process(frame))
        if pipeline.semantics is not None and frame.extras.get("instances") is not None:
            counts = np.bincount(frame.extras["instances"].ravel().astype(np.int64))
            seen = counts[:0] if seen is None else seen
            if len(counts) > len(seen):
                seen = np.pad(seen, (0, len(counts) - len(seen)))
            seen[:len(counts)] += counts >= VISIBLE_PIXELS
        bar.update()
    bar.close()
    seconds = time.perf_counter() - start
    tracked = [r for r in results if r.tracked]
    keyframes = [r for r in tracked if r.keyframe]
    summary = RunSummary(
        dataset.name, len(dataset), len(tracked), len(keyframes),
        sum(r.status == "lost" for r in results), sum(r.status == "skipped" for r in results), bad,
        1 + max((r.segment for r in results), default=0), seconds, len(results) / seconds if seconds else 0.0,
    )
    return RunOutput(summary, _trajectory(tracked), _trajectory(keyframes), results, instance_frames=seen)


def _anchored(results: list[FrameResult], keyframe_poses: dict[int, np.ndarray]) -> Trajectory:
    """Every tracked frame at its final map pose: its keyframe's optimized pose composed with
    the odometry from that keyframe (the last one of the same segment before it), as ORB-SLAM
    saves its trajectories. A frame without such a keyframe keeps its published pose."""
    stamps, poses = [], []
    ref = None  # (segment, T_map_odom of the keyframe: final pose · odometry pose⁻¹)
    for r in results:
        if not r.tracked:
            continue
        if r.node_id is not None and r.node_id in keyframe_poses and r.odometry_pose is not None:
            ref = (r.segment, keyframe_poses[r.node_id] @ invert(r.odometry_pose))
        use = ref is not None and ref[0] == r.segment and r.odometry_pose is not None
        stamps.append(r.stamp)
        poses.append(ref[1] @ r.odometry_pose if use else r.pose)
    return Trajectory(np.array(stamps), np.stack(poses)) if poses else _trajectory([])


def _trajectory(results: list[FrameResult]) -> Trajectory:
    if not results:
        return Trajectory(np.zeros(0), np.zeros((0, 4, 4)))
    return Trajectory(np.array([r.stamp for r in results]), np.stack([r.pose for r in results]))
