"""The SLAM service: Zenoh ingest for all robots, one session per robot, poses and events
published back, keyframes persisted to the SQLite long-term memory.

Transport threads only decode and enqueue; each robot's pipeline runs on its own worker
thread (numpy/OpenCV release the GIL in their kernels). A message that cannot be decoded is
counted by reason and dropped; nothing a client sends can stop the service.

Labels: a frame message with a label image reaches the pipeline with
``frame.extras["labels"]`` (H×W uint8 / uint16 class ids) and, when the robot's camera info had
a class table, ``frame.extras["label_names"]`` (tuple; absent = the default ADE20K-32 table).
Ids beyond the robot's table (or the default's 32) are refused as ``bad_labels``.
"""
from __future__ import annotations

import logging
import threading
import time
from collections import Counter, deque

import numpy as np

from mnemoslam.client.kernel import protocol
from mnemoslam.client.kernel.frames import Calibration, Frame
from mnemoslam.client.kernel.geometry import invert
from mnemoslam.client.transport import ZenohSettings, open_session, undeclare_all
from mnemoslam.storage import MapStore, StoreError, link_name
from mnemoslam.storage.connectivity import MapIndex, SessionJoin

from . import malloc
from .builder import build_pipeline, build_semantics
from .config import Config, to_dict
from .mapping.process import MappingProcess
from .pipeline import FrameResult, Pipeline
from .recovery import recover
from .semantics.worker import SemanticWorker
from .session import RobotSession

log = logging.getLogger("mnemoslam.service")


class SlamService:
    def __init__(self, config: Config):
        self.config = config
        self.keys = protocol.KeySpace(config.zenoh.prefix)
        self.limits = protocol.Limits(
            max_message_bytes=int(config.service.max_message_mb * 1024 * 1024),
            max_width=config.service.max_image_side, max_height=config.service.max_image_side,
        )
        self.store: MapStore | None = None
        self.maps = MapIndex()  # which map each keyframe and session is in (storage.connectivity)
        # joins seen (and when), announced once their map update is written
        self._joins_pending: list[tuple[SessionJoin, float]] = []
        self._maps_lock = threading.Lock()
        self._own_maps: dict[int, int | None] = {}  # session -> its own map id (pose messages' frame before it joined)
        self.mapping: MappingProcess | None = None  # every robot's map update (loop.process)
        # the map's semantic worker, shared by every robot (one object set), and why it is off
        self.semantics: tuple[SemanticWorker | None, str | None] = (None, "service not started")
        self.zenoh = None
        self.sessions: dict[str, RobotSession] = {}
        self.rejected: Counter = Counter()  # reason -> messages refused before reaching a session
        self.started_at = time.time()
        self._lock = threading.RLock()  # (re-entered: a held frame's decode error is counted under it)
        # robot -> (first held, newest raw frame messages): frames of a robot without a slot, kept
        # undecoded while its camera info is asked for (a stream's first frame can beat its info)
        self._held: dict[str, tuple[float, deque]] = {}
        self._held_bytes = 0
        self._subscribers = []
        self._info_requests: dict[str, float] = {}  # robot -> when its camera info was last asked for
        self._info_slots = threading.BoundedSemaphore(4)  # info queries in flight
        self._stopped = threading.Event()
        self._janitor: threading.Thread | None = None
        self.ros = None  # service.ros.RosIngest: the ROS 2 robots of config.ros (bridged topics, CDR)
        if config.ros.enabled:
            from .ros import RosIngest

            self.ros = RosIngest(self, config.ros)  # (ConfigError for a bad ros.robots entry)

    # -- life cycle --------------------------------------------------------------------
    def start(self) -> "SlamService":
        z = self.config.zenoh
        if self.localization_only:  # memory.incremental: false: the map file is opened read-only, nothing writes it
            try:
                self.store = MapStore(self.config.storage.path, readonly=True)
            except StoreError as e:
                raise StoreError(f"localization only (memory.incremental: false) needs a map to localize in: {e}") \
                    from None
            self.semantics = (None, "localization only (memory.incremental: false): nothing is written to the map")
        else:
            self.store = MapStore(self.config.storage.path)
            # sessions a kill left open end "crashed"; their map backlog is done, before any writer starts
            recover(self.config)
            if self.config.loop.enabled and self.config.loop.process:
                self.mapping = MappingProcess(self.config.storage.path, self.config.loop, self.config.memory)
            self.semantics = build_semantics(self.store, self.config, background=True)
        if self.semantics[0] is not None:  # tracking first: the worker waits while a robot's tracking is busy
            self.semantics[0].tracking_busy = self.tracking_busy
        self.maps = MapIndex()
        self.maps.refresh(self.store)  # the joins of the sessions before this start are history: no event
        self.zenoh = open_session(ZenohSettings(z.mode, list(z.listen), list(z.connect),
                                                z.multicast_scouting, z.gossip_scouting, z.shared_memory))
        self._subscribers = [
            self.zenoh.declare_subscriber(self.keys.frames_wildcard(), self._on_frame_sample),
            self.zenoh.declare_subscriber(self.keys.info_wildcard(), self._on_info_sample),
        ]
        if self.ros is not None:
            self.ros.start(self.zenoh)
        self._janitor = threading.Thread(target=self._expire_idle, name="robot-slots", daemon=True)
        self._janitor.start()
        log.info("service started: listen=%s prefix=%s db=%s%s", z.listen, z.prefix, self.config.storage.path,
                 " (localization only: read-only)" if self.localization_only else "")
        return self

    def stop(self) -> None:
        """Stop ingest, let every session finish its current frame, end the sessions and
        close the database (every stored keyframe is already committed)."""
        undeclare_all(self._subscribers)
        self._subscribers = []
        if self.ros is not None:
            self.ros.stop()
        self._stopped.set()
        if self._janitor is not None:
            self._janitor.join()
        for s in list(self.sessions.values()):
            s.stop()  # its pipeline finishes the queued map updates and ends its database session
        if self.semantics[0] is not None:  # after every session's final poses: objects are written against them
            self.semantics[0].close()
            self.semantics = (None, "service stopped")
        if self.mapping is not None:
            self.mapping.close()  # every robot's updates are done: stop the child before the database closes
        if self.zenoh is not None:
            self.zenoh.close()
            self.zenoh = None
        if self.store is not None:
            self.store.close()
            self.store = None
        log.info("service stopped")

    @property
    def localization_only(self) -> bool:
        """memory.incremental: false: every robot localizes, the map is opened read-only."""
        return not self.config.memory.incremental

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()

    # -- ingest (Zenoh threads) ------------------------------------------------------------
    def _on_frame_sample(self, sample) -> None:
        """Decode a frame of an admitted robot against its calibration's image size and queue
        it; anything else is counted and dropped before it costs memory."""
        key = str(sample.key_expr)
        robot = self.keys.robot_of(key)
        if robot is None:
            self.count_reject("bad_key", key, None)
            return
        self.ingest(robot, key, sample.payload.to_bytes())

    def ingest(self, robot: str, key: str, payload, decode=None, ask_info: bool = True) -> None:
        """A raw frame of `robot` received on `key`: decoded and queued on the robot's session,
        or held while it has no slot (`_hold`; with `ask_info` its camera info is asked for).
        `decode(payload, session) -> (seq, Frame)` (raising ProtocolError) decodes other
        formats than the native frame message (the ROS 2 ingest: `service.ros`); `len(payload)`
        is its size in bytes."""
        session = self.sessions.get(robot)
        if session is None:  # no slot: the robot's camera info has not arrived (ask for it)
            if self._hold(robot, key, payload, decode) is None and ask_info:  # (else admitted meanwhile: queued)
                self._request_info(robot)
            return
        self._submit(session, key, payload, decode)

    def _submit(self, session: RobotSession, key: str, payload, decode=None) -> None:
        try:
            if decode is not None:
                seq, frame = decode(payload, session)
            else:
                msg = protocol.decode_frame(payload, session.limits, label_names=session.classes)
                if msg.robot != session.robot:
                    raise protocol.ProtocolError("robot_mismatch", f"header robot {msg.robot!r} on key {key!r}")
                seq, frame = msg.seq, msg.frame
        except protocol.ProtocolError as e:
            session.reject(e.reason)
            self.count_reject(e.reason, key, e, payload if decode is None else None)
            return
        except Exception as e:  # a bug in decoding must not reach Zenoh's thread
            session.reject("internal")
            self.count_reject("internal", key, e, payload if decode is None else None)
            return
        refused = session.submit(seq, frame)
        if refused is not None:  # (counted by the session: /robots/{id})
            self._announce_reject(session.robot, refused, seq, f"stamp {frame.stamp:.6f} s is not after the "
                                  f"robot's last; a jump back by more than service.restart_gap "
                                  f"({self.config.service.restart_gap:g} s) would be a camera restart")

    def _hold(self, robot: str, key: str, payload, decode=None) -> RobotSession | None:
        """Keep a frame of a robot without a slot, undecoded, until its camera info arrives
        (its newest `service.hold_frames`, for at most 4 robots at a time, `service.queue_mb` in
        all, `service.info_timeout` + 1 s at most). Frames that cannot be held are counted
        `no_calibration`. Returns the robot's session when it was admitted meanwhile (the
        frame is then queued)."""
        cfg = self.config.service
        dropped = 0
        with self._lock:
            session = self.sessions.get(robot)
            if session is not None:  # admitted between the caller's look and this lock
                self._submit(session, key, payload, decode)
                return session
            held = self._held.get(robot)
            if cfg.hold_frames <= 0 or (held is None and len(self._held) >= 4) \
                    or self._held_bytes + len(payload) > cfg.queue_mb * 1024 * 1024:
                dropped = 1
            else:
                if held is None:
                    held = self._held[robot] = (time.monotonic(), deque())
                held[1].append((key, payload, decode))
                self._held_bytes += len(payload)
                while len(held[1]) > cfg.hold_frames:
                    self._held_bytes -= len(held[1].popleft()[1])
                    dropped += 1
        for _ in range(dropped):
            self.count_reject("no_calibration", key, "no camera info (calibration) of the robot", payload)
        return None

    def _release_held(self, robot: str, session: RobotSession | None) -> None:
        """Queue a robot's held frames on its new session (None: count them dropped). The
        caller holds the lock, so no newer frame of the robot overtakes them."""
        held = self._held.pop(robot, None)
        if held is None:
            return
        for key, payload, decode in held[1]:
            self._held_bytes -= len(payload)
            if session is None:
                self.count_reject("no_calibration", key, "no camera info (calibration) of the robot", payload)
            else:
                self._submit(session, key, payload, decode)

    def _on_info_sample(self, sample) -> None:
        key = str(sample.key_expr)
        try:
            info = protocol.decode_info_message(sample.payload.to_bytes())
            if info.robot != self.keys.robot_of(key):
                raise protocol.ProtocolError("robot_mismatch", f"camera info of {info.robot!r} on key {key!r}")
        except protocol.ProtocolError as e:
            self.count_reject("bad_info", key, e)
            return
        self.admit(info.robot, info.calibration, info.classes, localize=info.localize)

    def count_reject(self, reason: str, key: str, err, payload=None) -> None:
        """Count a refused message; a frame on a robot's frame key is also announced on the
        robot's events key (frame_rejected, with its seq when `payload`'s header says it)."""
        with self._lock:
            self.rejected[reason] += 1
            n = self.rejected[reason]
        if n <= 3 or n % 1000 == 0:  # structured, rate-limited
            log.warning("rejected message reason=%s key=%s count=%d detail=%s", reason, key, n, err)
        parsed = self.keys.parse(key)
        if parsed is not None and parsed[1] == "camera/frame":
            self._announce_reject(parsed[0], reason, None if payload is None else protocol.peek_seq(payload), err)

    def _announce_reject(self, robot: str, reason: str, seq: int | None, detail) -> None:
        """frame_rejected on the robot's events key: its camera learns that the frame will not
        be answered, and why."""
        text = "" if detail is None else str(detail)
        self.publish(self.keys.events(robot), protocol.encode_event(
            robot, "frame_rejected", reason=reason, seq=seq, detail=text[:300]))

    def admit(self, robot: str, calibration: Calibration,
              classes: tuple[str, ...] | None = None, localize: bool = False) -> RobotSession | None:
        """The robot's session, made when its calibration arrives and a slot is free. A camera
        that restarts with another calibration or class table keeps its session (counted, not
        applied). `localize`: the camera asked for localization only (nothing of the robot is
        written to the map; every robot localizes with memory.incremental: false)."""
        with self._lock:
            s = self.sessions.get(robot)
            if s is not None:
                if s.calibration != calibration:
                    s.reject("calibration_changed")
                if s.classes != classes:
                    s.reject("classes_changed")
                if s.localize != bool(localize):  # (its mode stays until its slot is freed)
                    s.reject("localize_changed")
                return s
            if len(self.sessions) >= self.config.service.max_robots:
                self.rejected["too_many_robots"] += 1
                n = self.rejected["too_many_robots"]
            else:
                cam = calibration.camera
                limits = protocol.Limits(self.limits.max_message_bytes, self.limits.max_width,
                                         self.limits.max_height, size=(cam.width, cam.height),
                                         classes=len(classes if classes is not None else protocol.DEFAULT_CLASSES))
                s = RobotSession(robot, self.config, calibration, limits,
                                 lambda cal, r=robot, loc=localize: self._make_pipeline(r, cal, loc), self._on_result,
                                 classes=classes, on_event=self._event_publisher(robot), localize=localize)
                self._release_held(robot, s)  # before the slot is visible: frames stay in order
                self.sessions[robot] = s
            if s is None:
                self._release_held(robot, None)
        if s is None:
            if n <= 3 or n % 1000 == 0:
                log.warning("robot=%s refused: all %d robot slots taken count=%d", robot,
                            self.config.service.max_robots, n)
            return None
        log.info("robot admitted robot=%s camera=%dx%d kind=%s mode=%s slots=%d/%d", robot, cam.width, cam.height,
                 calibration.kind, s.mode, len(self.sessions), self.config.service.max_robots)
        return s

    def _request_info(self, robot: str) -> None:
        """Ask robot's camera for its info (its queryable), at most once per info_timeout per
        robot and a few robots at a time, so frames of unknown robots cost no more than that."""
        now = time.monotonic()
        with self._lock:
            last = self._info_requests.get(robot)
            if (last is not None and now - last < self.config.service.info_timeout) \
                    or not self._info_slots.acquire(blocking=False):
                return
            self._info_requests[robot] = now
            if len(self._info_requests) > 4 * self.config.service.max_robots:  # forget the oldest asks
                for r, _ in sorted(self._info_requests.items(), key=lambda kv: kv[1])[:len(self._info_requests) // 2]:
                    del self._info_requests[r]
        threading.Thread(target=self._fetch_info, args=(robot,), daemon=True, name=f"info-{robot}").start()

    def _fetch_info(self, robot: str) -> None:
        try:
            z = self.zenoh
            if z is None:
                return
            for reply in z.get(self.keys.info(robot), timeout=self.config.service.info_timeout):
                if reply.ok is None:
                    continue
                try:
                    info = protocol.decode_info_message(reply.ok.payload.to_bytes())
                except protocol.ProtocolError as e:
                    self.count_reject("bad_info", self.keys.info(robot), e)
                    continue
                if info.robot == robot:
                    self.admit(robot, info.calibration, info.classes, localize=info.localize)
                    return
                self.count_reject("bad_info", self.keys.info(robot), f"camera info of {info.robot!r}")
        except Exception as e:  # the session closed while asking
            log.debug("info query for %s failed: %s", robot, e)
        finally:
            self._info_slots.release()

    def _expire_idle(self) -> None:
        """Free the slots of robots that sent nothing for idle_timeout seconds: their session
        ends (the pipeline finishes its map update and closes its database session). Also gives
        the C heap's free pages back every `service.malloc_trim_s` (service/malloc.py)."""
        last_trim = time.monotonic()
        while not self._stopped.wait(min(1.0, self.config.service.idle_timeout / 4, self.config.service.info_timeout)):
            now = time.monotonic()
            self.check_relocalized()
            if 0 < self.config.service.malloc_trim_s <= now - last_trim:  # the C heap's free pages back (issue 24)
                malloc.trim()
                last_trim = now
            with self._lock:  # held frames of robots whose camera never answered
                for robot in [r for r, (t, _) in self._held.items()
                              if now - t > self.config.service.info_timeout + 1.0]:
                    self._release_held(robot, None)
            for robot, s in list(self.sessions.items()):
                if s.idle(now) > self.config.service.idle_timeout:
                    with self._lock:
                        if self.sessions.get(robot) is not s:
                            continue
                        del self.sessions[robot]
                    log.info("robot expired robot=%s idle_s=%.0f frames=%d session=%s", robot, s.idle(now),
                             s.stats.processed, s.session_id)
                    s.stop(reason="idle")

    # -- per-frame output (worker threads) ---------------------------------------------
    def _event_publisher(self, robot: str):
        """on_event(kind, data) publishing the robot's events on its events key (the session's
        and the pipeline's)."""
        events = self.keys.events(robot)

        def on_event(kind: str, data: dict) -> None:
            self.publish(events, protocol.encode_event(robot, kind, **data))
            if kind in ("map_corrected", "loop_closed"):  # (the map update's: a join shows first here)
                self.check_relocalized()
        return on_event

    def check_relocalized(self) -> list[dict]:
        """Read the links stored since the last look (`MapIndex`); for each session whose
        keyframes first joined an older map, once that keyframe's map update is written (its
        statistics are its last write: the poses it moved are stored; at the latest 5 s after
        the join was seen), a log line and a
        `relocalized` event on its robot's events key. Returns the events' data."""
        store = self.store
        if store is None:
            return []
        out = []
        with self._maps_lock:
            try:
                now = time.monotonic()
                self._joins_pending += [(j, now) for j in self.maps.refresh(store)]
                # (at the latest 5 s after it was seen: a keyframe rehearsal merged may have no statistics)
                ready = [j for j, seen in self._joins_pending
                         if now - seen > 5.0 or store.statistics(j.node) is not None]
                if not ready:
                    return []
                self._joins_pending = [(j, seen) for j, seen in self._joins_pending if j not in ready]
                sessions = {s.id: s for s in store.sessions()}
                for j in ready:
                    j = self.maps.join(j.session_id) or j
                    first = store.get_node(j.first_node)
                    s = sessions.get(j.session_id)
                    if first is None or s is None:
                        continue
                    data = {"session_id": j.session_id, "map": j.map, "node_id": j.node, "stamp": j.stamp,
                            "peer": j.peer, "link": link_name(j.link),
                            "T_map_session": [round(float(v), 9) for v in first.pose.reshape(-1)]}
                    log.info("relocalized robot=%s session=%d map=%s keyframe=%d stamp=%.3f peer=%d link=%s "
                             "T_map_session.t=[%.3f, %.3f, %.3f]", s.robot, j.session_id, j.map, j.node, j.stamp,
                             j.peer, data["link"], *first.pose[:3, 3])
                    self.publish(self.keys.events(s.robot), protocol.encode_event(s.robot, "relocalized", **data))
                    out.append(data)
            except StoreError as e:  # a store closing under a stopping service
                log.debug("relocalization check: %s", e)
        return out

    def _make_pipeline(self, robot: str, calibration: Calibration, localize: bool = False) -> Pipeline:
        on_event = self._event_publisher(robot)
        pipeline = build_pipeline(self.store, robot, calibration, self.config, mapping=self.mapping,
                                  background=True, on_event=on_event, semantics=self.semantics,
                                  incremental=not localize)
        on_event("session_started", {"session_id": pipeline.session_id})
        if pipeline.localizing:
            log.info("localization started robot=%s camera=%dx%d kind=%s: nothing of it is written to the map",
                     robot, calibration.camera.width, calibration.camera.height, calibration.kind)
        else:
            log.info("session started robot=%s session=%d camera=%dx%d kind=%s", robot, pipeline.session_id,
                     calibration.camera.width, calibration.camera.height, calibration.kind)
        return pipeline

    def frame_of(self, session: RobotSession, result: FrameResult) -> int | None:
        """The map id whose frame a result's pose is in (the pose message's `map`): a mapping
        robot's session's map (its own until it relocalizes in an older one); a localizing
        robot's anchor's map, None before it relocalized (its own odometry frame)."""
        pipeline = session.pipeline
        if pipeline is None:
            return None
        if pipeline.localizing:
            return None if result.anchor is None else self.maps.map_of(result.anchor)
        sid = pipeline.session_id
        if sid is None:
            return None
        j = self.maps.join(sid)
        if j is not None:
            return j.map
        own = self._own_maps.get(sid)  # (a session the map index has not read yet: its own map)
        if own is None and self.store is not None:
            try:
                rec = self.store.session(sid)
            except StoreError:
                rec = None
            own = self._own_maps[sid] = None if rec is None else rec.map_id
        return own

    def _localized(self, session: RobotSession, frame: Frame, result: FrameResult, map_id: int | None) -> None:
        """A localizing robot's frame changed (relocalized in a map, or lost it): logged, and a
        `relocalized` event when it entered a map's frame (`T_map_session`: its own odometry
        frame in the map's, `peer` the map keyframe it is linked to)."""
        previous = session.map_frame
        session.map_frame = map_id
        if map_id == previous:
            return
        if map_id is None:
            log.info("localization lost robot=%s map=%s stamp=%.3f: poses in its own frame until it relocalizes",
                     session.robot, previous, frame.stamp)
            return
        T = result.pose @ invert(result.odometry_pose) if result.odometry_pose is not None else np.eye(4)
        data = {"session_id": None, "map": map_id, "node_id": None, "stamp": frame.stamp, "peer": result.anchor,
                "link": "loop", "T_map_session": [round(float(v), 9) for v in T.reshape(-1)], "seq": frame.index,
                "localization": True}
        log.info("relocalized robot=%s (localization only) map=%s seq=%d stamp=%.3f peer=%d "
                 "T_map_session.t=[%.3f, %.3f, %.3f]", session.robot, map_id, frame.index, frame.stamp,
                 result.anchor, *T[:3, 3])
        self.publish(self.keys.events(session.robot), protocol.encode_event(session.robot, "relocalized", **data))

    def _on_result(self, session: RobotSession, frame: Frame, result: FrameResult) -> None:
        robot = session.robot
        map_id = self.frame_of(session, result)
        localizing = session.pipeline is not None and session.pipeline.localizing
        if localizing and result.tracked:
            self._localized(session, frame, result, map_id)
        self.publish(self.keys.pose(robot), protocol.encode_pose(
            robot, frame.index, frame.stamp, result.status, result.pose, bool(result.keyframe), result.segment,
            None if localizing else result.node_id, queue_depth=session.queue_depth,
            dropped=session.stats.dropped_queue, map=map_id))
        if result.node_id is not None and not localizing:
            self.publish(self.keys.events(robot), protocol.encode_event(
                robot, "keyframe_added", node_id=result.node_id, seq=frame.index, stamp=frame.stamp))
        if result.status == "lost" and session.stats.previous_status != "lost":
            self.publish(self.keys.events(robot),
                         protocol.encode_event(robot, "tracking_lost", seq=frame.index, stamp=frame.stamp))
        if self.ros is not None:  # a ROS robot's pose key: CDR PoseStamped
            self.ros.on_result(robot, frame, result.pose)

    def publish(self, key: str, payload: bytes) -> None:
        z = self.zenoh
        if z is None:
            return
        try:
            z.put(key, payload)
        except Exception as e:  # session closing
            log.debug("publish on %s failed: %s", key, e)

    # -- state for the REST API ----------------------------------------------------------
    def robots(self) -> list[dict]:
        return [s.snapshot() for s in list(self.sessions.values())]

    def status(self) -> dict:
        return {
            "uptime_s": round(time.time() - self.started_at, 1),
            "robots": len(self.sessions),
            "robot_slots": self.config.service.max_robots,
            "rejected": dict(self.rejected),
            "rejected_total": sum(self.rejected.values()),
            "mapping_process": self.mapping.stats() if self.mapping is not None else None,
            "config": to_dict(self.config),
        }

    def delete_object(self, object_id: int) -> int:
        """Delete a stored object while semantics run: through the map's semantic worker, which
        would otherwise write the object it holds again. Returns the rows deleted."""
        worker = self.semantics[0]
        if worker is None:
            return self.store.delete_objects([int(object_id)])
        return worker.delete(object_id)

    def tracking_busy(self, margin: bool = True) -> bool:
        """Whether some robot's tracking needs the cores now (`RobotSession.needs_cpu` with
        `semantics.yield_queue`, and with `margin` `semantics.min_slack`): the semantic
        worker's probe."""
        s = self.config.semantics
        slack = float(s.min_slack) if margin else 0.0
        return any(r.needs_cpu(int(s.yield_queue), slack) for r in list(self.sessions.values()))

    def semantics_status(self) -> dict:
        """{"enabled", "source", "model", "reason" (why off, or None), "model_reason",
        "classes"} of the semantic map, plus "coverage": {"keyframes" of the map, "segmented"
        (in the semantic map), "skipped" (nothing to segment), "share"}, "worker": the map's
        semantic worker's counts (keyframes processed, deferred, back-filled, failed;
        objects), and "workers": the same counts of each connected robot's keyframes."""
        from .semantics.segmentation import semantics_status

        out = semantics_status(self.config.semantics)
        worker = self.semantics[0]
        if self.store is not None:  # coverage: what share of the map's keyframes the semantic map has taken
            try:
                c = self.store.segmentation_coverage()
                out["coverage"] = {**c, "share": c["segmented"] / c["keyframes"] if c["keyframes"] else None}
            except StoreError as e:  # a store closing under a stopping service
                log.debug("semantic coverage: %s", e)
        out["worker"] = worker.stats() if worker is not None else None
        out["workers"] = {robot: worker.stats(robot) for robot in list(self.sessions)} if worker is not None else {}
        return out
