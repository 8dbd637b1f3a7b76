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

    def line(self) -> str:
        merged = f" ({self.merged} merged)" if self.merged else ""
        dropped = f" ({self.links_dropped} inaccurate link(s) dropped)" if self.links_dropped else ""
        return (f"{self.dataset}: {self.frames} frames, {self.tracked} tracked, {self.keyframes} keyframes{merged}, "
                f"{self.lost} lost, {self.skipped} skipped, {self.bad} unreadable, {self.segments} segment(s), "
                f"{self.loops} loop(s){dropped}, {self.fps:.1f} frames/s")


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

    def __post_init__(self):
        if self.online is None:
            self.online = self.trajectory


def run_dataset(dataset: Dataset, config: Config, out_dir: str | Path | None = None,
                progress: bool = True) -> RunOutput:
    """Run every frame of `dataset` through one pipeline; write `trajectory.tum`,
    `keyframes.tum` (and `groundtruth.tum` when the dataset has it) and the map database
    `map.db` (the same one the service writes) into `out_dir`; with semantics on also
    `objects.json` (the fused objects at their final positions) and, for synthetic data,
    `groundtruth_objects.json` (the scene's objects and how many frames saw them)."""
    with contextlib.ExitStack() as stack:
        if out_dir is None:  # the map still lives in a database: a temporary one
            out_dir_db = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="mnemoslam-run-")))
        else:
            out_dir = Path(out_dir)
            out_dir.mkdir(parents=True, exist_ok=True)
            out_dir_db = out_dir
        db = out_dir_db / "map.db"
        for p in (db, db.with_name("map.db-wal"), db.with_name("map.db-shm")):
            p.unlink(missing_ok=True)  # a run replaces the previous run's map
        store = stack.enter_context(MapStore(db))
        pipeline = build_pipeline(store, dataset.name, dataset.calibration, config)  # map update inline
        out = _run(dataset, pipeline, progress)
        pipeline.close()  # the graph's final poses to the database, the session ended
        mapper = pipeline.mapper
        if mapper is not None:  # keyframes, and every frame through its keyframe, at their final poses
            final = mapper.keyframe_poses()
            ids = [r.node_id for r in out.results if r.node_id is not None]
            out.keyframes = Trajectory(np.array([r.stamp for r in out.results if r.node_id is not None]),
                                       np.stack([final[i] for i in ids]) if ids else np.zeros((0, 4, 4)))
            out.online = out.trajectory
            out.trajectory = _anchored(out.results, final)
            out.summary.loops = len(mapper.loops)
            out.summary.merged = mapper.merged
            out.summary.links_dropped = mapper.links_dropped
        if dataset.ground_truth is not None:  # every link of the map against the true relative poses
            out.links = evaluate_map_links(dataset.ground_truth, db)
    if out_dir is not None:
        write_tum(out_dir / "trajectory.tum", out.trajectory)
        write_tum(out_dir / "trajectory_online.tum", out.online)
        write_tum(out_dir / "keyframes.tum", out.keyframes)
        if dataset.ground_truth is not None:
            write_tum(out_dir / "groundtruth.tum", dataset.ground_truth)
        if out.links is not None:
            out.links.write(out_dir)
        (out_dir / "summary.json").write_text(json.dumps(asdict(out.summary), indent=2) + "\n")
        if mapper is not None:
            with MapStore(db, create=False) as reader:  # every update's statistics (the mapper keeps the last ones)
                write_updates(out_dir / "updates.csv", ((n, reader.statistics(n)) for n in ids))
        if pipeline.semantics is not None:
            with MapStore(db, create=False) as reader:
                write_objects(out_dir / "objects.json", reader.objects())
            if hasattr(dataset, "scene"):
                write_groundtruth_objects(out_dir / "groundtruth_objects.json", dataset.scene, out.instance_frames)
    return out


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


def _frames(dataset: Dataset, ahead: int = 2):
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
    for i, frame in enumerate(_frames(dataset)):
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
