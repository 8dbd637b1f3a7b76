"""Offline runs: play a dataset through the pipeline and write the trajectories."""
from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from client.datasets import Dataset
from client.frames import DatasetError
from client.trajectory import Trajectory, write_tum

from .config import Config
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

    def line(self) -> str:
        return (f"{self.dataset}: {self.frames} frames, {self.tracked} tracked, {self.keyframes} keyframes, "
                f"{self.lost} lost, {self.skipped} skipped, {self.bad} unreadable, {self.segments} segment(s), "
                f"{self.fps:.1f} frames/s")


@dataclass
class RunOutput:
    summary: RunSummary
    trajectory: Trajectory  # every tracked frame
    keyframes: Trajectory
    results: list[FrameResult]


def run_dataset(dataset: Dataset, config: Config, out_dir: str | Path | None = None,
                progress: bool = True) -> RunOutput:
    """Run every frame of `dataset` through one pipeline; write `trajectory.tum`,
    `keyframes.tum` (and `groundtruth.tum` when the dataset has it) into `out_dir`."""
    pipeline = Pipeline(dataset.calibration, config)
    results: list[FrameResult] = []
    bad = 0
    start = time.perf_counter()
    bar = tqdm(total=len(dataset), desc=dataset.name, unit="frame", disable=not progress, leave=False)
    for i in range(len(dataset)):
        try:
            frame = dataset.frame(i)
        except DatasetError as e:
            log.error("frame %d skipped: %s", i, e)
            bad += 1
            bar.update()
            continue
        results.append(pipeline.process(frame))
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
    out = RunOutput(summary, _trajectory(tracked), _trajectory(keyframes), results)
    if out_dir is not None:
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        write_tum(out_dir / "trajectory.tum", out.trajectory)
        write_tum(out_dir / "keyframes.tum", out.keyframes)
        if dataset.ground_truth is not None:
            write_tum(out_dir / "groundtruth.tum", dataset.ground_truth)
        (out_dir / "summary.json").write_text(json.dumps(asdict(summary), indent=2) + "\n")
    return out


def _trajectory(results: list[FrameResult]) -> Trajectory:
    if not results:
        return Trajectory(np.zeros(0), np.zeros((0, 4, 4)))
    return Trajectory(np.array([r.stamp for r in results]), np.stack([r.pose for r in results]))
