"""ROS 2 robots over Zenoh: the camera topics of robots bridged by zenoh-bridge-ros2dds (or
read through rmw_zenoh), mapped like native cameras, and their poses published back as
geometry_msgs/PoseStamped. No ROS install: CDR is `client.ros_cdr` (rosbags).

Configuration (`ros` in the config; off by default)::

    ros:
      enabled: true
      robots:
        - robot: r1                                        # the robot id in the service (REST, map)
          color: r1/camera/color/image_raw                 # sensor_msgs/Image or CompressedImage
          depth: r1/camera/aligned_depth_to_color/image_raw  # aligned to the colour image (its size and intrinsics)
          info: r1/camera/color/camera_info                # sensor_msgs/CameraInfo of the colour camera
          pose: r1/mnemoslam/pose                          # optional: PoseStamped out
          intrinsics: k                                    # optional: k (default) | p (image_rect topics)
          imu: r1/camera/imu                               # optional: sensor_msgs/Imu, the grid's up
          imu_axes: optical                                # optional: optical | body | A:B:C (client/imu.py)

A key is the Zenoh key of the topic: zenoh-bridge-ros2dds bridges the ROS 2 topic
``/r1/camera/color/image_raw`` to ``r1/camera/color/image_raw`` (after the bridge's namespace,
if it has one). Keys may hold Zenoh wildcards; rmw_zenoh's data keys are
``<domain>/<topic>/<type>/<type hash>``, so ``0/r1/camera/color/image_raw/*/*`` subscribes to
the topic in domain 0 (not tested against a ROS system here). The pose goes out as a plain
put, which the bridge turns into a ROS message for ROS subscribers of the topic; rmw_zenoh
subscribers need its liveliness tokens and attachments, which we do not send.

RGB-D only: the depth must be registered to the colour image (same size and intrinsics, e.g.
a RealSense's aligned_depth_to_color); stereo pairs and colour-only cameras are not supported
(the pipeline needs depth).

With an ``imu`` key (sensor_msgs/Imu), each frame gets the IMU's linear_acceleration at its
stamp (linear between the readings either side, none farther than 50 ms; the last 2 s are
kept) in the camera's optical axes as ``frame.extras["accel"]``, as the rosbag player gives
it: the occupancy grid's up direction (docs/grid.md). The IMU's axes: ``imu_axes``, else by
the Imu's frame name ("..._optical_frame", e.g. a RealSense's camera_imu_optical_frame: the
camera's axes; any other: REP 103 body axes of a frame aligned with the camera). There is no
tf here: an IMU mounted otherwise needs ``imu_axes``.

Message types: a key whose topic ends in ``/compressed`` or ``/compressedDepth``
(image_transport's names), or whose sample key names ``CompressedImage_`` (rmw_zenoh), carries
sensor_msgs/CompressedImage; any other colour / depth key sensor_msgs/Image. Encodings: see
`client.ros_cdr`.

How a ROS robot is mapped: its camera info (ROS publishes it with every image) admits it as a
native camera info does (`SlamService.admit`: a slot when one is free; a changed calibration
is counted). Colour and depth images are paired by header stamp: a new image pairs with the
unpaired image of the other stream whose stamp is nearest, within `ros.sync_tolerance`; the
pair's older unpaired images are dropped and counted ``unpaired``, as are images that waited in
vain: once their own stream is `ros.sync_window` (0.5 s) past them, or pushed out of a stream's
buffer (`ros.sync_queue`, a memory cap). The window is in stamp time, not a count: the two keys'
callbacks can run several images apart when frames come in bursts. Each pair becomes one frame
(seq counting pairs from 0, stamp = the colour image's) that takes the native path from there:
held while the robot has
no slot (`service.hold_frames`), checked against the calibration (``size_mismatch``), stamp
order, the robot's queue and its drops. CDR that does not decode is counted ``bad_cdr`` (per
robot too once it has a slot), never a crash. The native JSON pose is published on
``<prefix>/<robot>/pose`` as for any robot; with a ``pose`` key, every tracked frame's pose
also goes out there as CDR PoseStamped: header.stamp = the colour image's stamp (exact to the
nanosecond), frame_id `ros.frame_id`, the camera's optical frame (OpenCV axes: x right, y down,
z forward) in the map frame, whose origin is the session's first camera pose. Untracked frames
publish nothing.
"""
from __future__ import annotations

import logging
import threading
from collections import OrderedDict, deque
from dataclasses import dataclass, field

from mnemoslam.client import ros_cdr
from mnemoslam.client.imu import IMU, ImuBuffer, parse_axes, reading
from mnemoslam.client.kernel.frames import DatasetError, Frame
from mnemoslam.client.kernel.protocol import ROBOT_PATTERN, ProtocolError
from mnemoslam.client.transport import undeclare_all

from .config import ConfigError, RosConfig

log = logging.getLogger("mnemoslam.ros")

ROBOT_FIELDS = ("robot", "color", "depth", "info", "pose", "intrinsics", "localize", "imu", "imu_axes")


@dataclass(frozen=True)
class RosRobot:
    robot: str
    color: str
    depth: str
    info: str
    pose: str | None = None
    intrinsics: str = "k"
    localize: bool = False  # localization only for this robot (nothing of it written to the map)
    imu: str | None = None  # sensor_msgs/Imu: each frame's accelerometer reading (the grid's up)
    imu_axes: str | None = None  # the IMU's axes in the camera's (client.imu.parse_axes); None: by its frame's name


def _check_key(key, where: str, wildcards: bool = True) -> str:
    import zenoh

    if not isinstance(key, str) or not key:
        raise ConfigError(f"{where}: expected a Zenoh key (a string), got {key!r}")
    if not wildcards and "*" in key:
        raise ConfigError(f"{where}: {key!r} must not hold wildcards (the service puts on it)")
    try:
        zenoh.KeyExpr(key)
    except Exception:
        raise ConfigError(f"{where}: {key!r} is not a Zenoh key expression "
                          "(no leading, trailing or double '/')") from None
    return key


def parse_robots(config: RosConfig) -> list[RosRobot]:
    """The `ros.robots` entries, checked (ConfigError naming the entry)."""
    import math

    if not (math.isfinite(config.sync_tolerance) and config.sync_tolerance >= 0):
        raise ConfigError(f"ros.sync_tolerance: expected seconds >= 0, got {config.sync_tolerance!r}")
    if not (math.isfinite(config.sync_window) and config.sync_window > 0):
        raise ConfigError(f"ros.sync_window: expected seconds > 0, got {config.sync_window!r}")
    if config.sync_queue < 1:
        raise ConfigError(f"ros.sync_queue: expected >= 1, got {config.sync_queue!r}")
    out: list[RosRobot] = []
    for i, entry in enumerate(config.robots):
        where = f"ros.robots[{i}]"
        if not isinstance(entry, dict):
            raise ConfigError(f"{where}: expected a mapping with robot, color, depth, info (and pose, intrinsics)")
        unknown = sorted(set(entry) - set(ROBOT_FIELDS))
        if unknown:
            raise ConfigError(f"{where}: unknown key {unknown[0]!r}; known: {', '.join(ROBOT_FIELDS)}")
        robot = entry.get("robot")
        if not isinstance(robot, str) or not ROBOT_PATTERN.fullmatch(robot):
            raise ConfigError(f"{where}.robot: {robot!r} is not a robot id ([A-Za-z0-9_-], 1..64)")
        if robot in {r.robot for r in out}:
            raise ConfigError(f"{where}.robot: {robot!r} is listed twice")
        for name in ("color", "depth", "info"):
            if name not in entry:
                raise ConfigError(f"{where}: {name} (the Zenoh key of its topic) is required")
        intrinsics = entry.get("intrinsics", "k")
        if intrinsics not in ("k", "p"):
            raise ConfigError(f"{where}.intrinsics: expected k or p, got {intrinsics!r}")
        localize = entry.get("localize", False)
        if not isinstance(localize, bool):
            raise ConfigError(f"{where}.localize: expected true or false, got {localize!r}")
        axes = entry.get("imu_axes")
        if axes is not None:
            try:
                parse_axes(str(axes))
            except DatasetError as e:
                raise ConfigError(f"{where}.{e}") from None
        out.append(RosRobot(
            robot, _check_key(entry["color"], f"{where}.color"), _check_key(entry["depth"], f"{where}.depth"),
            _check_key(entry["info"], f"{where}.info"),
            None if entry.get("pose") is None else _check_key(entry["pose"], f"{where}.pose", wildcards=False),
            intrinsics, localize, None if entry.get("imu") is None else _check_key(entry["imu"], f"{where}.imu"),
            None if axes is None else str(axes)))
    return out


def compressed_key(configured: str, sample_key: str) -> bool:
    """Whether a sample carries sensor_msgs/CompressedImage (else sensor_msgs/Image): rmw_zenoh
    keys name the type; otherwise the topic's last name (after any wildcard chunks) is
    image_transport's ``compressed`` / ``compressedDepth``."""
    if "::CompressedImage_" in sample_key:
        return True
    if "::Image_" in sample_key:
        return False
    chunks = [c for c in configured.split("/") if "*" not in c]
    return bool(chunks) and chunks[-1] in ("compressed", "compressedDepth")


@dataclass
class RosPair:
    """A colour image and its depth image, deserialized, not yet decoded; what the service
    holds / queues as a robot's raw frame. len() = its CDR bytes."""

    seq: int
    ns: int  # the colour image's header stamp
    color: object
    depth: object
    nbytes: int

    def __len__(self) -> int:
        return self.nbytes


@dataclass
class _Stream:
    robot: RosRobot
    # pairing; taken before the service's lock, never after
    lock: threading.Lock = field(default_factory=threading.Lock)
    colors: deque = field(default_factory=deque)  # (ns, msg, bytes), unpaired, in arrival order
    depths: deque = field(default_factory=deque)
    seq: int = 0
    stamps: OrderedDict = field(default_factory=OrderedDict)  # frame stamp (s) -> ns, for the pose's header
    # (a leaf lock: decode runs under the service's)
    stamps_lock: threading.Lock = field(default_factory=threading.Lock)
    imu: ImuBuffer | None = None  # the last seconds of its Imu readings, with an imu key


class RosIngest:
    """Subscribes to the configured robots' topics on the service's Zenoh session and feeds
    the service's admission path (`SlamService.admit`, `SlamService.ingest`)."""

    def __init__(self, service, config: RosConfig):
        self.service = service
        self.config = config
        self.robots = {r.robot: _Stream(r) for r in parse_robots(config)}
        for st in self.robots.values():
            if st.robot.imu is not None:
                st.imu = ImuBuffer(None if st.robot.imu_axes is None else parse_axes(st.robot.imu_axes))
        self._subscribers = []

    def start(self, zenoh_session) -> None:
        for st in self.robots.values():
            r = st.robot
            self._subscribers.append(zenoh_session.declare_subscriber(r.info, lambda s, st=st: self._on_info(st, s)))
            self._subscribers.append(zenoh_session.declare_subscriber(
                r.color, lambda s, st=st: self._on_image(st, s, False)))
            self._subscribers.append(zenoh_session.declare_subscriber(
                r.depth, lambda s, st=st: self._on_image(st, s, True)))
            if r.imu is not None:
                self._subscribers.append(zenoh_session.declare_subscriber(r.imu, lambda s, st=st: self._on_imu(st, s)))
            log.info("ROS robot robot=%s color=%s depth=%s info=%s pose=%s", r.robot, r.color, r.depth, r.info, r.pose)

    def stop(self) -> None:
        undeclare_all(self._subscribers)
        self._subscribers = []

    # -- Zenoh threads -------------------------------------------------------------------
    def _drop(self, robot: str, reason: str, key: str, err) -> None:
        session = self.service.sessions.get(robot)
        if session is not None:
            session.reject(reason)
        self.service.count_reject(reason, key, err)

    def _on_info(self, st: _Stream, sample) -> None:
        key = str(sample.key_expr)
        try:
            msg = ros_cdr.deserialize(sample.payload.to_bytes(), ros_cdr.CAMERA_INFO,
                                      self.service.limits.max_message_bytes)
            cal = ros_cdr.calibration(msg, st.robot.intrinsics, self.service.config.service.max_image_side)
        except ProtocolError as e:
            self.service.count_reject(e.reason if e.reason == "bad_cdr" else "bad_info", key, e)
            return
        except Exception as e:  # a bug here must not reach Zenoh's thread
            self.service.count_reject("internal", key, e)
            return
        self.service.admit(st.robot.robot, cal, None, localize=st.robot.localize)

    def _on_imu(self, st: _Stream, sample) -> None:
        """An Imu message: its linear_acceleration kept (in the camera's axes) for the frames
        around its stamp; a message without one (covariance[0] = -1) is skipped."""
        key = str(sample.key_expr)
        try:
            msg = ros_cdr.deserialize(sample.payload.to_bytes(), IMU, self.service.limits.max_message_bytes)
            r = reading(msg)
            if r is not None and st.imu is not None:
                st.imu.add(ros_cdr.seconds(ros_cdr.stamp_ns(msg)), *r)
        except ProtocolError as e:
            self.service.count_reject(e.reason, key, e)
        except Exception as e:  # a bug here must not reach Zenoh's thread
            self.service.count_reject("internal", key, e)

    def _on_image(self, st: _Stream, sample, is_depth: bool) -> None:
        key = str(sample.key_expr)
        robot = st.robot.robot
        payload = sample.payload.to_bytes()
        configured = st.robot.depth if is_depth else st.robot.color
        typename = ros_cdr.COMPRESSED if compressed_key(configured, key) else ros_cdr.IMAGE
        try:
            msg = ros_cdr.deserialize(payload, typename, self.service.limits.max_message_bytes)
            ns = ros_cdr.stamp_ns(msg)
        except ProtocolError as e:
            self._drop(robot, e.reason, key, e)
            return
        except Exception as e:
            self._drop(robot, "internal", key, e)
            return
        with st.lock:  # pairs leave in order: one robot's frames never overtake each other
            mine, other = (st.depths, st.colors) if is_depth else (st.colors, st.depths)
            tol = int(round(self.config.sync_tolerance * 1e9))
            best = None
            for i, (ons, _, _) in enumerate(other):
                if abs(ons - ns) <= tol and (best is None or abs(ons - ns) < abs(other[best][0] - ns)):
                    best = i
            if best is None:
                mine.append((ns, msg, len(payload)))
                oldest = ns - int(round(self.config.sync_window * 1e9))
                while mine and (len(mine) > self.config.sync_queue or mine[0][0] < oldest):
                    mine.popleft()
                    self._drop(robot, "unpaired", key, "no partner image in time")
                return
            ons, omsg, obytes = other[best]
            del other[best]
            for buf, limit in ((other, ons), (mine, ns)):  # images older than the pair: their partner is gone
                kept = [x for x in buf if x[0] >= limit]
                for _ in range(len(buf) - len(kept)):
                    self._drop(robot, "unpaired", key, "an image older than a pair")
                buf.clear()
                buf.extend(kept)
            color, depth, cns = (omsg, msg, ons) if is_depth else (msg, omsg, ns)
            self._emit(st, key, cns, color, depth, len(payload) + obytes)

    def _emit(self, st: _Stream, key: str, ns: int, color, depth, nbytes: int) -> None:
        pair = RosPair(st.seq, ns, color, depth, nbytes)
        st.seq += 1
        self.service.ingest(st.robot.robot, key, pair, self.decode, ask_info=False)

    def decode(self, pair: RosPair, session) -> tuple[int, Frame]:
        """A pair to the frame the native decoder would make of the same images (ProtocolError
        for anything that does not fit the robot's calibration)."""
        st = self.robots[session.robot]
        size = session.limits.size
        side = max(session.limits.max_width, session.limits.max_height)
        image = ros_cdr.decode_color(pair.color, size, side)
        depth = ros_cdr.decode_depth(pair.depth, size, side)
        stamp = ros_cdr.seconds(pair.ns)
        if st.robot.pose is not None:
            with st.stamps_lock:
                st.stamps[stamp] = pair.ns
                while len(st.stamps) > 4096:
                    st.stamps.popitem(last=False)
        # the depth image's own stamp, as the rosbag player gives it: the tracker moves the depth
        # to the colour image's time (odometry.depth_time_compensation)
        extras = {"depth_stamp": ros_cdr.seconds(ros_cdr.stamp_ns(pair.depth))}
        if st.imu is not None:  # the accelerometer at the frame's stamp, as the rosbag player gives it
            a = st.imu.at(stamp)
            if a is not None:
                extras["accel"] = a
        return pair.seq, Frame(index=pair.seq, stamp=stamp, image=image, depth=depth,
                               source=f"{session.robot}#{pair.seq}", extras=extras)

    # -- worker threads --------------------------------------------------------------------
    def on_result(self, robot: str, frame: Frame, pose) -> None:
        """Publish a processed frame's pose as CDR PoseStamped on the robot's pose key."""
        st = self.robots.get(robot)
        if st is None or st.robot.pose is None or pose is None:
            return
        with st.stamps_lock:
            ns = st.stamps.pop(frame.stamp, None)
        if ns is None:  # (evicted: the stamp's float is exact to ~0.1 µs)
            ns = int(round(frame.stamp * 1e9))
        try:
            payload = ros_cdr.encode_pose_stamped(pose, ns, self.config.frame_id)
        except Exception as e:  # never let the pose kill the robot's worker
            log.warning("robot %s: pose not published: %s", robot, e)
            return
        self.service.publish(st.robot.pose, payload)
