"""The SLAM service: Zenoh ingest for all robots, one session per robot, poses and events
published back, keyframes persisted to the SQLite long-term memory.

Transport threads only decode and enqueue; each robot's pipeline runs on its own worker
thread (numpy/OpenCV release the GIL in their kernels). A message that cannot be decoded is
counted by reason and dropped; nothing a client sends can stop the service.
"""
from __future__ import annotations

import logging
import threading
import time
from collections import Counter

from client import protocol
from client.frames import Calibration, Frame
from client.transport import ZenohSettings, open_session
from storage import MapStore

from .config import Config, to_dict
from .mapping import Mapper
from .mapping_process import MappingProcess
from .memory import Memory
from .pipeline import FrameResult, Pipeline
from .recovery import recover
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
        self.mapping: MappingProcess | None = None  # every robot's map update (loop.process)
        self.zenoh = None
        self.sessions: dict[str, RobotSession] = {}
        self.rejected: Counter = Counter()  # reason -> messages refused before reaching a session
        self.started_at = time.time()
        self._lock = threading.Lock()
        self._subscribers = []
        self._info_requests: set[str] = set()

    # -- life cycle --------------------------------------------------------------------
    def start(self) -> "SlamService":
        z = self.config.zenoh
        self.store = MapStore(self.config.storage.path)
        recover(self.config)  # sessions a kill left open end "crashed"; their map backlog is done, before any writer starts
        if self.config.loop.enabled and self.config.loop.process:
            self.mapping = MappingProcess(self.config.storage.path, self.config.loop)
        self.zenoh = open_session(ZenohSettings(z.mode, list(z.listen), list(z.connect),
                                                z.multicast_scouting, z.gossip_scouting))
        self._subscribers = [
            self.zenoh.declare_subscriber(self.keys.frames_wildcard(), self._on_frame_sample),
            self.zenoh.declare_subscriber(self.keys.info_wildcard(), self._on_info_sample),
        ]
        log.info("service started: listen=%s prefix=%s db=%s", z.listen, z.prefix, self.config.storage.path)
        return self

    def stop(self) -> None:
        """Stop ingest, let every session finish its current frame, end the sessions and
        close the database (every stored keyframe is already committed)."""
        for sub in self._subscribers:
            try:
                sub.undeclare()
            except Exception:  # already closed
                pass
        self._subscribers = []
        for s in list(self.sessions.values()):
            s.stop()
            if s.pipeline is not None and s.pipeline.mapper is not None:
                s.pipeline.mapper.close()  # finish the queued map updates before the database closes
            memory = s.pipeline.memory if s.pipeline else None
            if memory is not None:
                self.store.end_session(memory.session_id, reason="stopped")
        if self.mapping is not None:
            self.mapping.close()  # every robot's updates are done: stop the child before the database closes
        if self.zenoh is not None:
            self.zenoh.close()
            self.zenoh = None
        if self.store is not None:
            self.store.close()
            self.store = None
        log.info("service stopped")

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()

    # -- ingest (Zenoh threads) ------------------------------------------------------------
    def _on_frame_sample(self, sample) -> None:
        key = str(sample.key_expr)
        robot = self.keys.robot_of(key)
        try:
            payload = sample.payload.to_bytes()
            msg = protocol.decode_frame(payload, self.limits)
            if robot is None or msg.robot != robot:
                raise protocol.ProtocolError("robot_mismatch", f"header robot {msg.robot!r} on key {key!r}")
        except protocol.ProtocolError as e:
            self._count_reject(e.reason, key, e)
            return
        except Exception as e:  # a bug in decoding must not reach Zenoh's thread
            self._count_reject("internal", key, e)
            return
        session = self._session(robot)
        if session is None:
            self._count_reject("too_many_robots", key, None)
            return
        session.submit(msg.seq, msg.frame)

    def _on_info_sample(self, sample) -> None:
        try:
            robot, calibration = protocol.decode_info(sample.payload.to_bytes())
        except protocol.ProtocolError as e:
            self._count_reject("bad_info", str(sample.key_expr), e)
            return
        session = self.sessions.get(robot)
        if session is not None:
            session.set_calibration(calibration)

    def _count_reject(self, reason: str, key: str, err) -> None:
        with self._lock:
            self.rejected[reason] += 1
            n = self.rejected[reason]
        if n <= 3 or n % 1000 == 0:  # structured, rate-limited
            log.warning("rejected message reason=%s key=%s count=%d detail=%s", reason, key, n, err)

    def _session(self, robot: str) -> RobotSession | None:
        s = self.sessions.get(robot)
        if s is not None:
            return s
        with self._lock:
            s = self.sessions.get(robot)
            if s is None:
                if len(self.sessions) >= self.config.service.max_robots:
                    return None
                s = RobotSession(robot, self.config, lambda cal, r=robot: self._make_pipeline(r, cal), self._on_result)
                self.sessions[robot] = s
                log.info("new robot=%s", robot)
                threading.Thread(target=self._fetch_info, args=(s,), daemon=True, name=f"info-{robot}").start()
        return s

    def _fetch_info(self, session: RobotSession) -> None:
        """Ask the camera's queryable for its calibration until it answers (or arrives by put)."""
        while session.calibration is None and self.zenoh is not None and session.state != "stopped":
            try:
                for reply in self.zenoh.get(self.keys.info(session.robot), timeout=self.config.service.info_timeout):
                    if reply.ok is None:
                        continue
                    robot, calibration = protocol.decode_info(reply.ok.payload.to_bytes())
                    if robot == session.robot:
                        session.set_calibration(calibration)
                        break
            except protocol.ProtocolError as e:
                self._count_reject("bad_info", self.keys.info(session.robot), e)
                time.sleep(self.config.service.info_timeout)
            except Exception as e:  # session closed while asking
                log.debug("info query for %s failed: %s", session.robot, e)
                time.sleep(0.2)

    # -- per-frame output (worker threads) ---------------------------------------------
    def _make_pipeline(self, robot: str, calibration: Calibration) -> Pipeline:
        memory = Memory(self.store, robot, calibration, self.config)
        self._publish(self.keys.events(robot), protocol.encode_event(robot, "session_started", session_id=memory.session_id))
        log.info("session started robot=%s session=%d camera=%dx%d kind=%s", robot, memory.session_id,
                 calibration.camera.width, calibration.camera.height, calibration.kind)
        mapper = None
        if self.config.loop.enabled:
            events = self.keys.events(robot)
            on_event = lambda kind, data: self._publish(events, protocol.encode_event(robot, kind, **data))
            if self.mapping is not None:
                mapper = self.mapping.mapper(robot, calibration.camera, on_event)
            else:
                mapper = Mapper(calibration.camera, self.config.loop, self.store, background=True, on_event=on_event)
        return Pipeline(calibration, self.config, memory, mapper)

    def _on_result(self, session: RobotSession, frame: Frame, result: FrameResult) -> None:
        robot = session.robot
        self._publish(self.keys.pose(robot), protocol.encode_pose(
            robot, frame.index, frame.stamp, result.status, result.pose, bool(result.keyframe), result.segment,
            result.node_id))
        if result.node_id is not None:
            self._publish(self.keys.events(robot), protocol.encode_event(
                robot, "keyframe_added", node_id=result.node_id, seq=frame.index, stamp=frame.stamp))
        if result.status == "lost" and session.stats.previous_status != "lost":
            self._publish(self.keys.events(robot), protocol.encode_event(robot, "tracking_lost", seq=frame.index, stamp=frame.stamp))

    def _publish(self, key: str, payload: bytes) -> None:
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
            "rejected": dict(self.rejected),
            "rejected_total": sum(self.rejected.values()),
            "mapping_process": self.mapping.stats() if self.mapping is not None else None,
            "config": to_dict(self.config),
        }
