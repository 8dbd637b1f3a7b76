"""ROS bags as datasets: rosbag2 folders (sqlite3 or mcap storage; a lone `.db3` / `.mcap`
file too) and ROS 1 `.bag` files, read with the pure-Python `rosbags` library (no ROS
install).

Topics, by message type (and, for `sensor_msgs/Image`, by the encoding of its first message):

- colour: `sensor_msgs/Image` rgb8, bgr8, rgba8, bgra8, mono8 (grey frames), 8UC3 (as
  bgr8), 8UC1 (as mono8); or `sensor_msgs/CompressedImage` (JPEG / PNG, any format string
  without "compressedDepth"; 16-bit PNG keeps its high bytes);
- depth: `sensor_msgs/Image` 16UC1 / mono16 (millimetres) or 32FC1 (metres; NaN = no
  measurement), or `CompressedImage` of image_transport's compressed_depth_image_transport
  (format like "16UC1; compressedDepth png": a small config header then a 16-bit PNG; for
  32FC1 the PNG holds quantized inverse depth). 0 means "no measurement" in every encoding;
  depth must be registered to the colour image (same size);
- camera info: `sensor_msgs/CameraInfo` (its first message). Intrinsics are K and the
  lens distortion D (plumb_bob / rational_polynomial) goes into the calibration: the images
  are delivered raw, as the depth is registered to the raw colour image, and the service
  undistorts feature coordinates (`PinholeCamera.distortion`); only equidistant (fisheye)
  images are undistorted here (colour bilinear, depth nearest). For a colour topic whose name
  contains "rect" the images are already rectified and the intrinsics are P's;
- ground truth (optional): `geometry_msgs/PoseStamped`, `PoseWithCovarianceStamped` or
  `nav_msgs/Odometry`, taken as the camera's pose in the world (camera-to-world; ATE uses
  the positions);
- IMU (optional): `sensor_msgs/Imu`. Each frame gets its `linear_acceleration` at the frame's
  stamp (linear between the readings either side; none farther than 50 ms) in the camera's
  optical axes as `frame.extras["accel"]`, which the occupancy grid takes its up direction
  from (docs/grid.md). The IMU's axes in the camera's: `--topics imu_axes=optical|body|A:B:C`,
  else the bag's /tf_static chain between the Imu's frame and the colour image's, else by the
  Imu frame's name (`client.imu`: "..._optical_frame" the camera's axes, any other REP 103
  body axes of a frame aligned with the camera).

Each role is found automatically when the bag has exactly one topic of that kind (for the
camera info, with several: the one in the colour topic's namespace, e.g.
/camera/rgb/image_raw -> /camera/rgb/camera_info) and is chosen with `topics` otherwise
(`mnemoslam run BAG --topics color=/cam/rgb,depth=/cam/depth,info=/cam/rgb/camera_info`;
keys `color`, `depth`, `info`, `pose`, `imu`). A bag without a pose topic has no ground truth,
one without an Imu topic no accelerometer readings.

Frames are the colour messages that have a depth message within `MAX_DT` (20 ms) by header
stamp, matched one to one as the TUM player does, stamped with the colour header stamp (a
topic whose header stamps are all unset, 0, uses the bag's receive times); the depth header
stamp is `frame.extras["depth_stamp"]` when both topics have header stamps. Opening the bag reads
every colour and depth message once to index their header stamps (`(topic, receive time,
rank)` per message, a few numbers each); frames are then read message by message: one cursor
walks the colour and depth messages in receive order as the players read frames in order, and
restarts through the bag's own time index when a frame is asked out of order. The bag is
never held in RAM.
"""
from __future__ import annotations

import logging
import struct
import threading
import weakref
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Iterable

import cv2
import numpy as np

from ..imu import IMU, accel_at, axes_by_name, parse_axes, reading
from ..kernel.frames import Calibration, DatasetError, Frame
from ..kernel.geometry import quat_to_rot
from ..kernel.trajectory import Trajectory
from ._io import MAX_DT, check_index, frame_count, pinhole, sample_poses
from .base import Dataset
from .tum import associate

log = logging.getLogger(__name__)

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
POSE_TYPES = ("geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/PoseWithCovarianceStamped", "nav_msgs/msg/Odometry")

COLOR_ENCODINGS = ("rgb8", "bgr8", "rgba8", "bgra8", "mono8", "8UC3", "8UC1")
DEPTH_ENCODINGS = ("16UC1", "mono16", "32FC1")
DEPTH_SCALE = 1000.0  # raw units per metre of 16UC1 depth (millimetres), the calibration's depth_scale

ROLES = ("color", "depth", "info", "pose", "imu")
OPTIONAL = ("pose", "imu")  # roles a bag may lack
_ALIASES = {"colour": "color", "rgb": "color", "image": "color", "camera_info": "info", "gt": "pose",
            "groundtruth": "pose", "odometry": "pose", "accel": "imu"}
TF_STATIC = "tf2_msgs/msg/TFMessage"
_PNG = b"\x89PNG\r\n\x1a\n"
JUMP_NS = 2_000_000_000  # a frame this far (receive time) beyond the cursor: restart the cursor there
EARLY = 16  # messages read ahead of their frame kept at most (a few in order: depth before colour, ...)


# ------------------------------------------------------------------------------------------
# Paths and options

def bag_path(path: str | Path) -> Path | None:
    """The path the bag reader opens for `path` if it is a ROS bag, else None: a folder with
    metadata.yaml (rosbag2), a `.bag` file (ROS 1), a `.db3` / `.mcap` file (its rosbag2
    folder when it sits in one, else the lone storage file)."""
    path = Path(path)
    if path.is_dir():
        return path if (path / "metadata.yaml").is_file() else None
    if path.is_file():
        suffix = path.suffix.lower()
        if suffix == ".bag":
            return path
        if suffix in (".db3", ".mcap"):
            return path.parent if (path.parent / "metadata.yaml").is_file() else path
    return None


def parse_topics(spec: str | Iterable[str] | dict | None) -> dict[str, str]:
    """`--topics` as {role: topic}: "color=/cam/rgb,depth=/cam/depth,info=/cam/info" (or
    several such strings, e.g. the option given more than once). Roles: color (colour),
    depth, info (camera_info), pose (gt), imu (accel); and `imu_axes` (not a topic: the IMU's
    axes in the camera's, client.imu.parse_axes). A role given twice, an unknown role or an
    empty topic is a DatasetError."""
    if spec is None:
        return {}
    if isinstance(spec, dict):
        items = [f"{k}={v}" for k, v in spec.items()]
    else:
        items = [spec] if isinstance(spec, str) else list(spec)
    out: dict[str, str] = {}
    for item in items:
        for part in str(item).split(","):
            part = part.strip()
            if not part:
                continue
            role, sep, topic = part.partition("=")
            role, topic = role.strip().lower(), topic.strip()
            role = _ALIASES.get(role, role)
            if not sep or not topic:
                raise DatasetError(f"--topics: expected ROLE=TOPIC, got {part!r} (roles: {', '.join(ROLES)})")
            if role not in ROLES and role != "imu_axes":
                raise DatasetError(f"--topics: unknown role {role!r} in {part!r} (roles: {', '.join(ROLES)}; "
                                   "and imu_axes=optical|body|A:B:C)")
            if role in out and out[role] != topic:
                raise DatasetError(f"--topics: {role} given twice ({out[role]}, {topic})")
            out[role] = topic
    return out


# ------------------------------------------------------------------------------------------
# Decoding (vectorized: numpy views and OpenCV)

def header_stamp_ns(raw: bytes | memoryview, ros2: bool) -> int:
    """The header stamp (ns) of a serialized message that starts with a std_msgs/Header,
    read from its bytes without deserializing the rest (the image data). ROS 2 CDR: a
    4-byte encapsulation header (byte 1: 0 big, 1 little endian), then sec (int32) and
    nanosec (uint32); ROS 1: seq (uint32), secs, nsecs (little endian)."""
    if len(raw) < 12:
        raise DatasetError(f"message of {len(raw)} bytes is too short for a header")
    if ros2:
        sec, nsec = struct.unpack_from("<iI" if raw[1] & 1 else ">iI", raw, 4)
    else:
        sec, nsec = struct.unpack_from("<II", raw, 4)
    return int(sec) * 1_000_000_000 + int(nsec)


def _pixels(msg, dtype: str, channels: int) -> np.ndarray:
    """An Image message's pixels as an (H, W[, C]) array of `dtype` (row padding of `step`
    dropped, big-endian data swapped to native)."""
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    dt = np.dtype(dtype)
    if dt.itemsize > 1:
        dt = dt.newbyteorder(">" if msg.is_bigendian else "<")
    row = w * channels * dt.itemsize
    data = np.asarray(msg.data, dtype=np.uint8).reshape(-1)
    if h <= 0 or w <= 0 or step < row or data.size < step * h:
        raise DatasetError(f"{msg.encoding} image {w}x{h}, step {step}: {data.size} bytes of data do not fit")
    a = np.ascontiguousarray(data[:step * h].reshape(h, step)[:, :row]).view(dt)
    if dt.itemsize > 1 and not dt.isnative:
        a = a.astype(dt.newbyteorder("="))
    return a.reshape(h, w, channels) if channels > 1 else a.reshape(h, w)


def decode_color(msg) -> np.ndarray:
    """A colour Image or CompressedImage message as BGR uint8 (H, W, 3), or grey (H, W) for
    mono8 / 8UC1 and grey JPEG / PNG."""
    if hasattr(msg, "format"):  # CompressedImage
        img = cv2.imdecode(np.asarray(msg.data, dtype=np.uint8).reshape(-1), cv2.IMREAD_UNCHANGED)
        if img is None or img.size == 0:
            raise DatasetError(f"CompressedImage ({msg.format!r}): not a decodable JPEG / PNG image")
        if img.dtype == np.uint16:  # bgr16 / mono16 PNG: the high bytes
            img = (img >> 8).astype(np.uint8)
        elif img.dtype != np.uint8:
            raise DatasetError(f"CompressedImage ({msg.format!r}): {img.dtype} pixels, expected 8- or 16-bit colour")
        if img.ndim == 3 and img.shape[2] == 4:
            return cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
        return img
    enc = msg.encoding
    if enc in ("bgr8", "8UC3"):
        return _pixels(msg, "u1", 3)
    if enc == "rgb8":
        return cv2.cvtColor(_pixels(msg, "u1", 3), cv2.COLOR_RGB2BGR)
    if enc == "bgra8":
        return cv2.cvtColor(_pixels(msg, "u1", 4), cv2.COLOR_BGRA2BGR)
    if enc == "rgba8":
        return cv2.cvtColor(_pixels(msg, "u1", 4), cv2.COLOR_RGBA2BGR)
    if enc in ("mono8", "8UC1"):
        return _pixels(msg, "u1", 1)
    raise DatasetError(f"colour Image encoding {enc!r} not supported ({', '.join(COLOR_ENCODINGS)})")


def decode_compressed_depth(data, fmt: str) -> np.ndarray:
    """compressed_depth_image_transport's payload as float32 metres (0 = no measurement):
    a config header (compression format and two float32 depth quantization parameters A, B,
    12 bytes; the header is everything before the PNG signature), then a 16-bit PNG holding
    millimetres (16UC1) or quantized inverse depth v for 32FC1, depth = A / (v - B), v = 0
    invalid. RVL payloads are not supported."""
    data = np.asarray(data, dtype=np.uint8).reshape(-1)
    encoding = fmt.split(";")[0].strip() if ";" in fmt else "16UC1"
    head = data[:64].tobytes()
    at = head.find(_PNG)
    if at < 0:
        kind = "RVL" if "rvl" in fmt.lower() else "unknown"
        raise DatasetError(f"compressedDepth ({fmt!r}): no PNG payload ({kind} compression is not supported)")
    img = cv2.imdecode(data[at:], cv2.IMREAD_UNCHANGED)
    if img is None or img.ndim != 2 or img.dtype != np.uint16:
        raise DatasetError(f"compressedDepth ({fmt!r}): not a single-channel 16-bit PNG")
    if encoding in ("16UC1", "mono16"):
        return img.astype(np.float32) / np.float32(DEPTH_SCALE)
    if encoding == "32FC1":
        if at < 8:
            raise DatasetError(f"compressedDepth ({fmt!r}): no quantization parameters before the PNG")
        qa, qb = np.frombuffer(head[at - 8:at], dtype="<f4")
        v = img.astype(np.float32)
        with np.errstate(divide="ignore", invalid="ignore"):
            depth = qa / (v - qb)
        return np.where((img > 0) & np.isfinite(depth) & (depth > 0), depth, np.float32(0)).astype(np.float32)
    raise DatasetError(f"compressedDepth encoding {encoding!r} not supported (16UC1, 32FC1)")


def decode_depth(msg) -> np.ndarray:
    """A depth Image or compressedDepth CompressedImage message as float32 metres, 0 where
    there is no measurement (16UC1 / mono16: millimetres, 0 invalid; 32FC1: metres, NaN and
    non-positive invalid)."""
    if hasattr(msg, "format"):
        return decode_compressed_depth(msg.data, msg.format)
    enc = msg.encoding
    if enc in ("16UC1", "mono16"):
        return _pixels(msg, "u2", 1).astype(np.float32) / np.float32(DEPTH_SCALE)
    if enc == "32FC1":
        d = _pixels(msg, "f4", 1)
        return np.where(np.isfinite(d) & (d > 0), d, np.float32(0)).astype(np.float32)
    raise DatasetError(f"depth Image encoding {enc!r} not supported ({', '.join(DEPTH_ENCODINGS)})")


def _field(msg, name: str):
    """A CameraInfo field by its ROS 2 (k, d, p) or ROS 1 (K, D, P) name."""
    value = getattr(msg, name, None)
    return getattr(msg, name.upper()) if value is None else value


def pose_matrices(msgs: list) -> np.ndarray:
    """(N, 4, 4) poses of PoseStamped / PoseWithCovarianceStamped / Odometry messages."""
    poses = []
    for m in msgs:
        p = m.pose
        p = getattr(p, "pose", p)  # PoseWithCovariance / Odometry: .pose.pose
        poses.append((p.position.x, p.position.y, p.position.z,
                      p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w))
    a = np.array(poses, dtype=np.float64).reshape(-1, 7)
    out = np.tile(np.eye(4), (len(a), 1, 1))
    if len(a):
        out[:, :3, :3] = quat_to_rot(a[:, 3:])
        out[:, :3, 3] = a[:, :3]
    return out


# ------------------------------------------------------------------------------------------
# The dataset

@dataclass
class _Stream:
    """One topic's messages in the bag: where to find each (receive time, rank among the
    topic's messages with that receive time) and its header stamp."""

    topic: str
    msgtype: str
    connections: list
    logtimes: np.ndarray  # int64 ns
    ranks: np.ndarray  # int
    stamps: np.ndarray  # int64 ns, header stamps (receive times if the header's are unset)
    header_stamps: bool = True  # False: `stamps` are the receive times


def _nearest_info(infos: list[str], color: str) -> list[str]:
    """Of several camera info topics, the one whose namespace is the deepest that contains the
    colour topic (/camera/rgb/camera_info for /camera/rgb/image_raw/compressed); all of them
    when that does not single one out."""
    parts = PurePosixPath(color).parts
    depth = {}
    for n in infos:
        ns = PurePosixPath(n).parent.parts
        if parts[:len(ns)] == ns:
            depth[n] = len(ns)
    if not depth:
        return infos
    best = max(depth.values())
    near = [n for n, d in depth.items() if d == best]
    return near if len(near) == 1 else infos


class RosbagDataset(Dataset):
    """A ROS 1 or ROS 2 bag of an RGB-D camera (see the module's docstring)."""

    format = "rosbag"

    def __init__(self, path: str | Path, *, topics: str | dict | Iterable[str] | None = None,
                 max_frames: int | None = None, max_dt: float = MAX_DT, imu_axes=None):
        try:
            from rosbags.highlevel import AnyReader
            from rosbags.typesys import Stores, get_typestore
        except ImportError as e:  # pragma: no cover - a declared dependency
            raise DatasetError(f"reading ROS bags needs the rosbags package ({e})") from None
        given = Path(path)
        where = bag_path(given)
        if where is None:
            raise DatasetError(f"{given}: not a ROS bag (a rosbag2 folder with metadata.yaml, a .db3 / .mcap file "
                               f"or a ROS 1 .bag file)")
        self.path = where
        self.name = where.stem if where.is_file() else where.resolve().name
        chosen = parse_topics(topics)
        axes = chosen.pop("imu_axes", None) if imu_axes is None else imu_axes
        self._imu_axes = None if axes is None else parse_axes(axes)
        self._lock = threading.Lock()
        try:
            # bags without message definitions (rosbag2 before Iron) decode with the standard types
            reader = AnyReader([where], default_typestore=get_typestore(Stores.LATEST))
            reader.open()
        except Exception as e:  # rosbags raises its own errors, and struct / OS errors on damaged files
            raise DatasetError(f"{given}: cannot read the ROS bag ({type(e).__name__}: {e})") from None
        self._reader = reader
        self._closer = weakref.finalize(self, _close_reader, reader)
        try:
            self._open(chosen, max_frames, max_dt)
        except DatasetError:
            self.close()
            raise
        except Exception as e:
            self.close()
            raise DatasetError(f"{given}: cannot read the ROS bag ({type(e).__name__}: {e})") from None

    # -- opening ----------------------------------------------------------------------------

    def _open(self, chosen: dict[str, str], max_frames: int | None, max_dt: float) -> None:
        reader = self._reader
        self._ros2 = bool(reader.is2)
        topics = {name: info for name, info in reader.topics.items() if info.msgcount}
        roles = self._choose(topics, chosen)
        self.topics = dict(roles)
        log.info("%s: colour %s, depth %s, info %s, pose %s, imu %s", self.path, roles["color"], roles["depth"],
                 roles["info"], roles.get("pose"), roles.get("imu"))
        color, depth = self._index(topics, roles["color"], roles["depth"])
        ia, ib = associate(color.stamps / 1e9, depth.stamps / 1e9, max_dt)
        if not len(ia):
            raise DatasetError(f"{self.path}: no {color.topic} image has a {depth.topic} image within "
                               f"{max_dt * 1e3:.0f} ms (header stamps)")
        n = frame_count(len(ia), max_frames, self.path)
        ia, ib = ia[:n], ib[:n]
        self._color, self._depth = color, depth
        self._ci, self._di = ia, ib
        self.stamps = color.stamps[ia] / 1e9
        self._wanted = {self._key(color, int(k)) for k in ia} | {self._key(depth, int(k)) for k in ib}
        self._cursor, self._pos, self._last, self._early = None, -1, {}, {}
        first, _ = self._read(0, depth=False)
        h, w = first.shape[:2]
        self._shape = (h, w)
        self.calibration, self._maps = self._calibration(topics[roles["info"]], roles["info"], w, h)
        self.ground_truth = None
        if roles.get("pose"):
            gt = self._poses(topics[roles["pose"]], roles["pose"])
            self.ground_truth = sample_poses(gt, self.stamps)
        #: (N, 4): stamp, the Imu's linear_acceleration in the camera's axes; empty without an Imu topic
        self.accel = np.zeros((0, 4))
        self.imu_axes, self.imu_axes_source = None, None  # camera ← IMU rotation, and where it came from
        if roles.get("imu"):
            self._read_imu(topics, roles["imu"], roles["color"])

    def _first(self, info):
        """The first message of a topic, deserialized."""
        gen = self._reader.messages(connections=info.connections)
        try:
            conn, _, raw = next(gen)
        finally:
            gen.close()
        return self._reader.deserialize(raw, conn.msgtype)

    def _kind(self, name: str, info) -> str | None:
        """A topic's role by its type (and, for Image / CompressedImage, its first message)."""
        t = info.msgtype
        if t == CAMERA_INFO:
            return "info"
        if t in POSE_TYPES:
            return "pose"
        if t == IMU:
            return "imu"
        if t == IMAGE:
            enc = self._first(info).encoding
            return "color" if enc in COLOR_ENCODINGS else "depth" if enc in DEPTH_ENCODINGS else None
        if t == COMPRESSED:
            return "depth" if "compresseddepth" in self._first(info).format.lower() else "color"
        return None

    def _choose(self, topics: dict, chosen: dict[str, str]) -> dict[str, str | None]:
        listing = ", ".join(f"{n} ({i.msgtype})" for n, i in sorted(topics.items())) or "none"
        for role, topic in chosen.items():
            if topic not in topics:
                raise DatasetError(f"{self.path}: --topics {role}={topic}: no such topic with messages in the bag "
                                   f"(topics: {listing})")
        kinds = {}
        for name, info in topics.items():
            if info.msgtype in (IMAGE, COMPRESSED, CAMERA_INFO, IMU) + POSE_TYPES:
                kinds[name] = self._kind(name, info)
        by_role = {r: sorted(n for n, k in kinds.items() if k == r) for r in ROLES}
        what = {"color": "colour image (sensor_msgs/Image rgb8/bgr8/mono8 or CompressedImage)",
                "depth": "depth image (sensor_msgs/Image 16UC1/32FC1 or compressedDepth)",
                "info": "camera info (sensor_msgs/CameraInfo)",
                "pose": "pose (PoseStamped/PoseWithCovarianceStamped/Odometry)",
                "imu": "IMU (sensor_msgs/Imu)"}
        roles: dict[str, str | None] = {}
        for role in ROLES:
            if role in chosen:
                topic = chosen[role]
                if kinds.get(topic) != role:
                    raise DatasetError(f"{self.path}: --topics {role}={topic}: {topic} is not a {what[role]} topic "
                                       f"({topics[topic].msgtype})")
                roles[role] = topic
                continue
            found = by_role[role]
            if role == "info" and len(found) > 1:
                found = _nearest_info(found, roles["color"])
            if len(found) == 1:
                roles[role] = found[0]
            elif role in OPTIONAL:
                if found:
                    log.warning("%s: %d %s topics (%s); none is used unless one is chosen with "
                                "--topics %s=TOPIC", self.path, len(found), role, ", ".join(found), role)
                roles[role] = None
            elif not found:
                raise DatasetError(f"{self.path}: no {what[role]} topic in the bag (topics: {listing})")
            else:
                raise DatasetError(f"{self.path}: {len(found)} {what[role]} topics ({', '.join(found)}): choose one "
                                   f"with --topics {role}=TOPIC")
        return roles

    def _index(self, topics: dict, color_topic: str, depth_topic: str) -> tuple[_Stream, _Stream]:
        """One pass over the colour and depth messages: receive time, rank and header stamp of
        each (the image data is read but not decoded)."""
        rows = {color_topic: [], depth_topic: []}
        last = {color_topic: (None, 0), depth_topic: (None, 0)}
        conns = topics[color_topic].connections + topics[depth_topic].connections
        for conn, t, raw in self._reader.messages(connections=conns):
            topic = conn.topic
            prev, rank = last[topic]
            rank = rank + 1 if prev == t else 0
            last[topic] = (t, rank)
            rows[topic].append((t, rank, header_stamp_ns(raw, self._ros2)))
        streams = []
        for topic in (color_topic, depth_topic):
            a = np.array(rows[topic], dtype=np.int64).reshape(-1, 3)
            stamps = a[:, 2]
            unset = bool(len(a) and (stamps == 0).all())
            if unset:
                log.warning("%s: %s has unset header stamps; using the bag's receive times", self.path, topic)
                stamps = a[:, 0]
            order = np.argsort(stamps, kind="stable")
            keep = order[np.r_[True, np.diff(stamps[order]) > 0]] if len(a) else order  # one message per stamp
            if len(keep) < len(a):
                log.warning("%s: %s: %d messages repeat a header stamp; the first of each is used", self.path, topic,
                            len(a) - len(keep))
            info = topics[topic]
            streams.append(_Stream(topic, info.msgtype, info.connections, a[keep, 0], a[keep, 1], stamps[keep],
                                   header_stamps=not unset))
        return streams[0], streams[1]

    def _read_imu(self, topics: dict, imu_topic: str, color_topic: str) -> None:
        """Every Imu reading of the bag (stamp, linear_acceleration in the camera's axes): the
        axes configured, else from /tf_static between the Imu's frame and the colour image's,
        else by the Imu frame's name (client.imu)."""
        rows, frame = [], None
        for conn, t, raw in self._reader.messages(connections=topics[imu_topic].connections):
            msg = self._reader.deserialize(raw, conn.msgtype)
            r = reading(msg)
            if r is None:
                continue
            s = msg.header.stamp
            rows.append((int(s.sec) * 1_000_000_000 + int(s.nanosec), t, *r[0]))
            frame = frame or r[1]
        if not rows:
            log.warning("%s: %s has no linear_acceleration readings", self.path, imu_topic)
            return
        a = np.array(rows, np.float64)
        stamps = a[:, 1] if (a[:, 0] == 0).all() else a[:, 0]  # unset header stamps: receive times
        a = np.column_stack([stamps / 1e9, a[:, 2:]])
        a = a[np.argsort(a[:, 0], kind="stable")]
        if self._imu_axes is not None:
            R, how = self._imu_axes, "configured"
        else:
            cam = str(self._first(topics[color_topic]).header.frame_id)
            R = self._tf_rotation(topics, cam, frame)
            how = f"/tf_static {frame} -> {cam}"
            if R is None:
                R, how = axes_by_name(frame)
        a[:, 1:] = a[:, 1:] @ R.T
        self.accel, self.imu_axes, self.imu_axes_source = a, R, how
        log.info("%s: %d IMU readings from %s (frame %s; axes in the camera's: %s)", self.path, len(a), imu_topic,
                 frame, how)

    def _tf_rotation(self, topics: dict, target: str, source: str) -> np.ndarray | None:
        """The rotation target ← source from the bag's /tf_static (None without a chain)."""
        edges: dict[str, list[tuple[str, np.ndarray]]] = {}
        for name, info in topics.items():
            if info.msgtype != TF_STATIC or name.rstrip("/").split("/")[-1] != "tf_static":
                continue
            for conn, _, raw in self._reader.messages(connections=info.connections):
                for tr in self._reader.deserialize(raw, conn.msgtype).transforms:
                    q = tr.transform.rotation
                    R = quat_to_rot(np.array([q.x, q.y, q.z, q.w]))  # parent ← child
                    parent, child = str(tr.header.frame_id).lstrip("/"), str(tr.child_frame_id).lstrip("/")
                    edges.setdefault(parent, []).append((child, R))
                    edges.setdefault(child, []).append((parent, R.T))
        target, source = target.lstrip("/"), source.lstrip("/")
        if target == source:
            return np.eye(3)
        seen, todo = {target: np.eye(3)}, [target]  # breadth first: target ← frame
        while todo:
            f = todo.pop(0)
            for g, R in edges.get(f, []):
                if g not in seen:
                    seen[g] = seen[f] @ R
                    todo.append(g)
        return seen.get(source)

    def _calibration(self, info, topic: str, width: int, height: int):
        """Calibration from the first CameraInfo message, and undistortion maps (or None)."""
        msg = self._first(info)
        K = np.asarray(_field(msg, "k"), dtype=np.float64).reshape(-1)
        P = np.asarray(_field(msg, "p"), dtype=np.float64).reshape(-1)
        D = np.asarray(_field(msg, "d"), dtype=np.float64).reshape(-1)
        w, h = int(msg.width) or width, int(msg.height) or height
        if (w, h) != (width, height):
            raise DatasetError(f"{self.path}: camera info {topic} is for {w}x{h} images, the colour images are "
                               f"{width}x{height}")
        rectified = "rect" in self._color.topic
        if rectified:
            if len(P) != 12 or P[0] <= 0 or P[5] <= 0:
                raise DatasetError(f"{self.path}: camera info {topic}: no projection matrix P for the rectified "
                                   f"images of {self._color.topic}")
            fx, fy, cx, cy = P[0], P[5], P[2], P[6]
        else:
            if len(K) != 9 or K[0] <= 0 or K[4] <= 0:
                raise DatasetError(f"{self.path}: camera info {topic}: no intrinsics (K is {K.tolist()}; "
                                   f"an uncalibrated camera)")
            fx, fy, cx, cy = K[0], K[4], K[2], K[5]
        maps, distortion = None, ()
        if not rectified and len(D) and np.abs(D).max() > 0:
            model = str(msg.distortion_model)
            if model in ("plumb_bob", "rational_polynomial") and len(D) in (4, 5, 8):
                # the images stay raw (the depth is registered to them): the service undistorts
                # feature coordinates and dense back-projection rays (PinholeCamera.distortion)
                distortion = tuple(float(v) for v in D)
                log.info("%s: lens distortion %s D=%s (the images stay raw, feature coordinates are undistorted)",
                         self.path, model, np.round(D, 5).tolist())
            elif model == "equidistant" and len(D) >= 4:
                Km = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
                maps = cv2.fisheye.initUndistortRectifyMap(Km, D[:4], np.eye(3), Km, (w, h), cv2.CV_32FC1)
                log.info("%s: images undistorted (%s, D=%s)", self.path, model, np.round(D, 5).tolist())
            else:
                raise DatasetError(f"{self.path}: camera info {topic}: distortion model {model!r} with {len(D)} "
                                   f"coefficients not supported (plumb_bob, rational_polynomial, equidistant)")
        return Calibration(pinhole(fx, fy, cx, cy, w, h, distortion), None, DEPTH_SCALE), maps

    def _poses(self, info, topic: str) -> Trajectory:
        stamps, msgs = [], []
        for conn, t, raw in self._reader.messages(connections=info.connections):
            m = self._reader.deserialize(raw, conn.msgtype)
            s = m.header.stamp
            stamps.append((int(s.sec) * 1_000_000_000 + int(s.nanosec), t))
            msgs.append(m)
        a = np.array(stamps, dtype=np.int64).reshape(-1, 2)
        stamps = a[:, 1] if len(a) and (a[:, 0] == 0).all() else a[:, 0]  # unset header stamps: receive times
        order = np.argsort(stamps, kind="stable")
        return Trajectory(stamps[order] / 1e9, pose_matrices(msgs)[order])

    # -- frames -----------------------------------------------------------------------------

    def _key(self, stream: _Stream, k: int) -> tuple[str, int, int]:
        return stream.topic, int(stream.logtimes[k]), int(stream.ranks[k])

    def _fetch(self, keys: list[tuple[str, int, int]]) -> dict:
        """The serialized messages of `keys` ((topic, receive time, rank)) as {key: (connection,
        bytes)}. Frames are read in order by the players, so one cursor walks the colour and
        depth messages in receive order and keeps the few read early (a depth message before
        its colour message, ...); a key behind the cursor or far ahead of it restarts the
        cursor there through the bag's time index."""
        out = {k: self._early.pop(k) for k in keys if k in self._early}
        missing = [k for k in keys if k not in out]
        if not missing:
            return out
        lo = min(k[1] for k in missing)
        passed = any(t < self._pos or (t == self._pos and self._last.get(topic, (None, -1))[0] == t
                                       and self._last[topic][1] >= r) for topic, t, r in missing)
        if self._cursor is None or passed or lo > self._pos + JUMP_NS:
            self._restart(lo)
        want = set(missing)
        for conn, t, raw in self._cursor:
            prev, rank = self._last.get(conn.topic, (None, -1))
            rank = rank + 1 if prev == t else 0
            self._last[conn.topic], self._pos = (t, rank), t
            key = (conn.topic, t, rank)
            if key in want:
                out[key] = (conn, raw)
                want.discard(key)
                if not want:
                    return out
            elif key in self._wanted:
                self._early[key] = (conn, raw)
                while len(self._early) > EARLY:
                    self._early.pop(next(iter(self._early)))
        self._cursor = None
        topic, t, _ = min(want, key=lambda k: k[1])
        raise DatasetError(f"{self.path}: {topic} message received at {t} ns is missing")

    def _restart(self, start: int) -> None:
        if self._cursor is not None:
            self._cursor.close()
        conns = self._color.connections + self._depth.connections
        self._cursor = self._reader.messages(connections=conns, start=start)
        self._pos, self._last = start - 1, {}

    def _where(self, stream: _Stream, k: int) -> str:
        return f"{self.path}:{stream.topic}@{stream.stamps[k] / 1e9:.6f}"

    def _read(self, i: int, depth: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """Frame i's colour image and (with `depth`) depth, decoded."""
        parts = [(self._color, int(self._ci[i]), decode_color)]
        if depth:
            parts.append((self._depth, int(self._di[i]), decode_depth))
        keys = [self._key(stream, k) for stream, k, _ in parts]
        with self._lock:
            if self._reader is None:
                raise DatasetError(f"{self.path}: the bag is closed")
            try:
                raw = self._fetch(keys)
            except DatasetError:
                raise
            except Exception as e:  # a damaged bag: the reader's own errors
                self._cursor = None
                raise DatasetError(f"{self._where(*parts[0][:2])}: unreadable ({type(e).__name__}: {e})") from None
            msgs = [self._reader.deserialize(raw[key][1], raw[key][0].msgtype) if key in raw else None for key in keys]
        out = []
        for (stream, k, decode), msg in zip(parts, msgs):
            try:
                out.append(decode(msg))
            except DatasetError as e:
                raise DatasetError(f"{self._where(stream, k)}: {e}") from None
            except Exception as e:
                raise DatasetError(f"{self._where(stream, k)}: unreadable ({type(e).__name__}: {e})") from None
        return out[0], (out[1] if depth else None)

    def __len__(self) -> int:
        return len(self.stamps)

    def frame(self, i: int) -> Frame:
        i = check_index(i, len(self))
        image, depth = self._read(i)
        source = (f"{self._where(self._color, int(self._ci[i]))}, "
                  f"{self._depth.topic}@{self._depth.stamps[self._di[i]] / 1e9:.6f}")
        for what, a in (("colour", image), ("depth", depth)):
            if a.shape[:2] != self._shape:
                raise DatasetError(f"{source}: {what} image is {a.shape[1]}x{a.shape[0]}, expected "
                                   f"{self._shape[1]}x{self._shape[0]} (depth must be registered to colour)")
        if self._maps is not None:
            image = cv2.remap(image, *self._maps, cv2.INTER_LINEAR)
            depth = cv2.remap(depth, *self._maps, cv2.INTER_NEAREST)
        # the depth image's own stamp (the tracker moves the depth by the motion in between:
        # odometry.depth_time_compensation); not when either topic's stamps are receive times
        extras = {"depth_stamp": float(self._depth.stamps[self._di[i]] / 1e9)} \
            if self._color.header_stamps and self._depth.header_stamps else {}
        a = accel_at(self.accel, float(self.stamps[i]))
        if a is not None:  # the IMU's reading at the frame's stamp (the grid's up: docs/grid.md)
            extras["accel"] = a
        return Frame(i, float(self.stamps[i]), image, depth=depth, source=source, extras=extras)

    def close(self) -> None:
        """Close the bag (frames can no longer be read). Also done when the dataset is
        garbage collected."""
        with self._lock:
            self._reader = None
            if getattr(self, "_cursor", None) is not None:
                self._cursor.close()
                self._cursor = None
        self._closer()

    release = close  # the name `mnemoslam stream` calls when it is done with a source


def _close_reader(reader) -> None:
    try:
        reader.close()
    except Exception:  # already closed, or the files went away
        pass
