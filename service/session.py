"""One robot's SLAM session inside the service: a bounded frame queue, a worker thread that
runs the pipeline, and the counters the REST API shows.

A robot gets a session (a slot) only once its camera's calibration is known, so frames are
decoded against the calibration's image size and nothing a robot sends is held before it.
Frames arrive from Zenoh's callback thread (`submit`); a frame whose stamp does not increase
is rejected and counted, unless its stamp is more than `service.restart_gap` seconds older
than the last one: that is a camera (or clock) restart, and the robot's session ends
("restarted") and a new one starts with that frame (the frames queued before it still go to
the old session, which is closed on a thread of its own); when the pipeline falls behind,
the queue (bounded in frames and in decoded bytes) drops its *oldest* frame (a camera wants
the freshest pose, not a growing backlog) and counts the drop. The bytes counted are every
array the frame holds: image, depth, right image and the arrays in `frame.extras` (a label
image sent with the frame).
"""
from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Callable

from mnemoslam.client.kernel.frames import Calibration, Frame
from mnemoslam.client.kernel.protocol import Limits

from .config import Config
from .pipeline import FrameResult, Pipeline

log = logging.getLogger("mnemoslam.session")


@dataclass
class SessionStats:
    received: int = 0  # frames accepted into the queue
    labelled: int = 0  # of those, frames that came with a label image (extras["labels"])
    processed: int = 0
    dropped_queue: int = 0  # oldest frame dropped because the queue was full
    rejected: dict = field(default_factory=dict)  # reason -> count, for frames this session refused
    tracked: int = 0
    lost: int = 0
    keyframes: int = 0
    last_stamp: float | None = None
    last_status: str | None = None
    previous_status: str | None = None  # status of the frame before the last one
    processing_ms: float = 0.0  # exponential mean of the pipeline time per frame
    fps: float = 0.0  # processed frames per second over the last few seconds
    position: tuple | None = None  # map-frame camera position of the last tracked frame (REST: where the robot is)
    pose: tuple | None = None  # ... and its whole pose (16 numbers, row-major 4×4 camera-to-map)
    # its latest keyframe in the map (localization only: the map's keyframe its keyframes are linked
    # to, None while it is not relocalized)
    node_id: int | None = None
    restarts: int = 0  # camera restarts (stamps back by more than service.restart_gap): sessions ended "restarted"


class RobotSession:
    """Owns the pipeline of one robot; `on_result(session, frame, result)` is called from
    the worker thread after every processed frame. `limits` bound its frame messages (their
    image size is the calibration's, their label ids the class table's). `classes`: the class
    table of the camera info (None: the default, ADE20K-32). `localize`: the camera asked for
    localization only (camera info `localize`; the service's `memory.incremental: false` makes
    every robot localize): `mode` is then "localization"."""

    def __init__(self, robot: str, config: Config, calibration: Calibration, limits: Limits,
                 make_pipeline: Callable[[Calibration], Pipeline],
                 on_result: Callable[["RobotSession", Frame, FrameResult], None],
                 classes: tuple[str, ...] | None = None,
                 on_event: Callable[[str, dict], None] | None = None, localize: bool = False):
        self.robot = robot
        self.config = config
        self.localize = bool(localize)
        self.mode = "localization" if localize or not config.memory.incremental else "mapping"
        self.map_frame: int | None = None  # (localization) the map its poses went out in last; the service's
        self.calibration = calibration
        self.classes = classes
        self.limits = limits  # what its frame messages may be: the calibration's image size
        self.pipeline: Pipeline | None = None  # made on the worker thread with the first frame
        self.stats = SessionStats()
        self.last_active = time.monotonic()  # last frame (or the calibration) received
        self._make_pipeline = make_pipeline
        self._on_result = on_result
        self._on_event = on_event or (lambda kind, data: None)  # the robot's events (session_ended)
        self._queue: deque[tuple[int, Frame, int, int]] = deque()  # (seq, frame, decoded bytes, generation)
        self._queued_bytes = 0
        self._last_stamp: float | None = None  # of the last frame accepted
        self._generation = 0  # the camera's run: +1 at each restart; a queued frame carries the one it came in
        self._pipeline_generation = 0  # the run of `pipeline`
        self._ending: dict[threading.Thread, Pipeline] = {}  # sessions of earlier runs being closed
        self._ended_progress = (0, 0)  # map_progress of the sessions of earlier runs, once closed
        self._cond = threading.Condition()
        self._stopping = False
        self._rate_window: deque[float] = deque(maxlen=60)
        # when the worker thread processed its last frames (monotonic start, end) and the frame it
        # is on: its frame-time margin (`needs_cpu`, the semantic worker's probe)
        self._spans: deque[tuple[float, float]] = deque(maxlen=120)
        self._frame_started: float | None = None
        self._first_started: float | None = None  # its first frame's start (a young session's margin is not known)
        self._thread = threading.Thread(target=self._run, name=f"slam-{robot}", daemon=True)
        self._thread.start()

    # -- called from the transport thread --------------------------------------------
    @property
    def state(self) -> str:
        if self._stopping:
            return "stopped"
        if self.stats.last_status is None:
            return "waiting_for_frames"
        return "lost" if self.stats.last_status == "lost" else "tracking"

    @property
    def session_id(self) -> int | None:
        return self.pipeline.session_id if self.pipeline else None

    @property
    def queue_depth(self) -> int:
        return len(self._queue)

    def busy_share(self, now: float | None = None, window: float = 1.0) -> float:
        """The share of the last `window` seconds the worker thread spent processing frames
        (1 - its frame-time margin: 0.9 = a frame takes 90 % of the time between frames).
        A session younger than `window` (from its first frame) has no margin known yet: 1.0.
        (Measured over its short life instead, the share swings with every few milliseconds
        a frame comes late: the semantic worker took a stream's first keyframe while
        tracking had no margin.)"""
        now = time.monotonic() if now is None else now
        first = self._first_started
        if first is None:
            return 0.0
        if now - first < window:
            return 1.0
        start = now - window
        spans = list(self._spans)
        busy = sum(e - max(s, start) for s, e in spans if e > start)
        current = self._frame_started
        if current is not None:
            busy += now - max(current, start)
        return min(1.0, busy / (now - start))

    def needs_cpu(self, queued: int, slack: float) -> bool:
        """Whether this robot's tracking needs the cores now (the semantic worker then waits):
        more than `queued` frames wait in its queue, or it had less than `slack` of the last
        second to spare (`busy_share`). False once stopping."""
        if self._stopping:
            return False
        return len(self._queue) > queued or (slack > 0 and self.busy_share() > 1.0 - slack)

    def idle(self, now: float) -> float:
        """Seconds since the last frame arrived (or the session was made)."""
        return now - self.last_active

    @staticmethod
    def frame_bytes(frame: Frame) -> int:
        """The memory a queued frame holds: its images and the arrays in its extras (labels)."""
        arrays = (frame.image, frame.depth, frame.right, *frame.extras.values())
        return sum(a.nbytes for a in arrays if hasattr(a, "nbytes"))

    def submit(self, seq: int, frame: Frame) -> str | None:
        """Queue a decoded frame. A stamp that does not increase is rejected ("stamp_order",
        returned; None when queued), unless it is more than `service.restart_gap` seconds older
        than the last: a camera restart, the frame starts the robot's next session."""
        size = self.frame_bytes(frame)
        limit = self.config.service.queue_mb * 1024 * 1024
        gap = self.config.service.restart_gap
        with self._cond:
            self.last_active = time.monotonic()
            if self._last_stamp is not None and not frame.stamp > self._last_stamp:
                if not (gap > 0 and frame.stamp < self._last_stamp - gap):
                    self.reject("stamp_order")  # (the condition's lock is reentrant)
                    return "stamp_order"
                self._generation += 1
                self.stats.restarts += 1
                log.warning("camera restart robot=%s session=%s last_stamp=%.3f stamp=%.3f back_s=%.3f "
                            "restart_gap=%.1f restarts=%d: the session ends (restarted), a new one starts",
                            self.robot, self.session_id, self._last_stamp, frame.stamp,
                            self._last_stamp - frame.stamp, gap, self.stats.restarts)
            self._last_stamp = frame.stamp
            self.stats.received += 1
            self.stats.labelled += "labels" in frame.extras
            while self._queue and (len(self._queue) >= max(1, self.config.service.queue_size)
                                   or self._queued_bytes + size > limit):
                self._queued_bytes -= self._queue.popleft()[2]
                self.stats.dropped_queue += 1
            self._queue.append((seq, frame, size, self._generation))
            self._queued_bytes += size
            self._cond.notify()
        return None

    def reject(self, reason: str) -> None:
        with self._cond:
            self.stats.rejected[reason] = self.stats.rejected.get(reason, 0) + 1

    def stop(self, timeout: float = 10.0, reason: str = "stopped") -> None:
        """Finish the frame in progress (the queue's backlog is dropped) and end the pipeline's
        session for `reason` (its map update finishes the keyframes it was given)."""
        with self._cond:
            self._stopping = True
            self._cond.notify()
        self._thread.join(timeout)
        for t in list(self._ending):  # sessions of earlier runs still closing
            t.join()
        if self.pipeline is not None:
            self._end(self.pipeline, reason)

    def _end(self, pipeline: Pipeline, reason: str, announce: bool = True) -> None:
        """Close a pipeline's session for `reason`, announced first (session_ended: it takes no
        more frames; its map update then finishes the keyframes it was given)."""
        session_id = pipeline.session_id
        if announce:
            self._on_event("session_ended", {"session_id": session_id, "reason": reason})
        pipeline.close(reason)
        log.info("session ended robot=%s session=%s reason=%s", self.robot, session_id, reason)

    def _restart(self, generation: int) -> None:
        """(worker thread) The camera restarted: the current session ends ("restarted") on a
        thread of its own (its map update finishes meanwhile, tracking goes on), and the next
        frame makes the new one."""
        old, self.pipeline, self._pipeline_generation = self.pipeline, None, generation
        if old is None:
            return
        self._on_event("session_ended", {"session_id": old.session_id, "reason": "restarted"})

        def end() -> None:
            try:
                self._end(old, "restarted", announce=False)
            except Exception:
                log.exception("robot %s: ending session %s failed", self.robot, old.session_id)
            finally:
                mapped, submitted = old.map_progress
                with self._cond:
                    done = self._ended_progress
                    self._ended_progress = (done[0] + mapped, done[1] + submitted)
                    del self._ending[thread]

        thread = threading.Thread(target=end, name=f"end-{self.robot}-{old.session_id}", daemon=True)
        with self._cond:
            self._ending[thread] = old
        thread.start()

    # -- worker thread -----------------------------------------------------------------
    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._stopping and not self._queue:
                    self._cond.wait()
                if self._stopping:
                    return
                seq, frame, size, generation = self._queue.popleft()
                self._queued_bytes -= size
            try:
                if generation != self._pipeline_generation:
                    self._restart(generation)
                self._process(seq, frame)
            except Exception:  # never let one frame kill the robot's session
                log.exception("robot %s: frame %d failed", self.robot, seq)
                self.reject("pipeline_error")

    def _process(self, seq: int, frame: Frame) -> None:
        if self.pipeline is None:
            self.pipeline = self._make_pipeline(self.calibration)
        t = time.perf_counter()
        self._frame_started = started = time.monotonic()
        if self._first_started is None:
            self._first_started = started
        try:
            result = self.pipeline.process(frame)
        finally:
            self._frame_started = None
            self._spans.append((started, time.monotonic()))
        ms = (time.perf_counter() - t) * 1e3
        s = self.stats
        s.processed += 1
        s.tracked += result.tracked
        s.lost += result.status == "lost"
        s.keyframes += bool(result.keyframe)
        s.previous_status = s.last_status
        s.last_stamp, s.last_status = frame.stamp, result.status
        s.processing_ms = ms if s.processed == 1 else 0.9 * s.processing_ms + 0.1 * ms
        if result.pose is not None:
            s.position = tuple(float(v) for v in result.pose[:3, 3])
            s.pose = tuple(round(float(v), 9) for v in result.pose.reshape(-1))
        if self.mode == "localization":  # (its keyframes are not the map's: the map keyframe it is linked to)
            if result.tracked or result.anchor is not None:
                s.node_id = None if result.anchor is None else int(result.anchor)
        elif result.node_id is not None:
            s.node_id = int(result.node_id)
        now = time.monotonic()
        self._rate_window.append(now)
        if len(self._rate_window) > 1:
            s.fps = (len(self._rate_window) - 1) / max(now - self._rate_window[0], 1e-6)
        self._on_result(self, frame, result)

    def snapshot(self) -> dict:
        s = self.stats
        mapped, submitted = self.pipeline.map_progress if self.pipeline else (0, 0)
        with self._cond:  # and the sessions of earlier runs (camera restarts): closed, or still closing
            for p in [*self._ending.values(), self._ended_progress]:
                m, n = p if isinstance(p, tuple) else p.map_progress
                mapped, submitted = mapped + m, submitted + n
        return {
            "robot": self.robot, "mode": self.mode, "state": self.state, "queue_depth": self.queue_depth,
            "queue_mb": round(self._queued_bytes / 2**20, 1),
            "frames_received": s.received, "frames_labelled": s.labelled, "frames_processed": s.processed,
            "frames_dropped": s.dropped_queue,
            "frames_rejected": dict(s.rejected), "tracked": s.tracked, "lost": s.lost, "keyframes": s.keyframes,
            "fps": round(s.fps, 2), "processing_ms": round(s.processing_ms, 2), "last_stamp": s.last_stamp,
            "session_id": self.session_id,
            "position": None if s.position is None else list(s.position), "node_id": s.node_id,
            "pose": None if s.pose is None else list(s.pose),
            # the map update (loop closure, graph) runs behind tracking: keyframes it has done,
            # and those still waiting (0 = the map served over REST includes every keyframe)
            "keyframes_mapped": mapped,
            "map_backlog": submitted - mapped,
            "restarts": s.restarts,
        }
