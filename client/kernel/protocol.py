"""The mnemoslam wire protocol, version 2: what cameras and the service say to each other over
Zenoh. This docstring is the protocol's documentation; client and service both import this
module, so they cannot disagree.

Key expressions
===============
Everything lives under a configurable prefix (default ``mnemoslam``), one subtree per robot::

    <prefix>/<robot>/camera/frame   camera -> service   binary frame message (below), one per frame
    <prefix>/<robot>/camera/info    camera -> service   JSON camera info; put once when the camera
                                                        starts AND answered by a queryable on the
                                                        same key, so a late service can `get` it
    <prefix>/<robot>/pose           service -> anyone   JSON pose message, one per processed frame
    <prefix>/<robot>/events         service -> anyone   JSON event message

``<robot>`` matches ``^[A-Za-z0-9_-]{1,64}$``. The prefix is one or more ``/``-separated chunks
of ``[A-Za-z0-9_.-]`` (no wildcards). The service subscribes to ``<prefix>/*/camera/frame``
(`KeySpace.frames_wildcard`) and reads the robot from the key (`KeySpace.robot_of`); the
robot id inside the message must agree with the key (the service checks that).

Versions
========
Frame messages carry a version (`FRAME_VERSIONS`, readers accept both): version 1 is a frame
without a label image, version 2 adds an optional per-pixel class-id image (a camera that
segments on board). Writers send version 1 whenever a frame goes without labels - byte for
byte what writers sent before version 2 existed - so a camera streams to an older service
unchanged unless it sends labels (which an older service refuses as ``bad_version``). JSON
messages stay at ``"version": 1`` (`JSON_VERSION`); the camera info's class table is an
optional field older readers ignore. `PROTOCOL_VERSION` (2) is the newest frame version.

Sensor fields (any version) ride in the header's extension bytes, announced by `flags` bits,
so a reader that predates them skips them (it ignores flags and skips up to header_len) and a
frame without them is byte for byte what writers sent before they existed:

- bit 0 (`FLAG_DEPTH_STAMP`), rgbd only: ``depth_stamp`` f64, the capture time of the depth
  image in seconds (a Kinect stamps depth and colour apart; the tracker moves the depth to the
  colour image's time with it: ``frame.extras["depth_stamp"]``); finite, >= 0, else
  ``bad_stamp``;
- bit 1 (`FLAG_ACCEL`): ``accel`` 3 x f64, an accelerometer reading at the frame's time in the
  camera's axes (x right, y down, z forward; the specific force in m/s^2, +g along up when
  still: ``frame.extras["accel"]``, which the occupancy grid takes its up direction from);
  finite and at most `MAX_ACCEL` in magnitude, else ``bad_header``.

They follow the version's last field (v1: at 47 + n, v2: at 53 + n) in bit order, each only
when its bit is set; header_len covers them. Other bits are reserved: writers send 0, readers
ignore them (a later field comes after these, so the offsets above stay valid).

Frame message (binary, all integers little-endian)
==================================================
======  ====  ==================  =============================================================
offset  size  field               meaning
======  ====  ==================  =============================================================
0       4     magic               ``b"MSLF"``
4       2     version   u16       1 or 2 (`FRAME_VERSIONS`); any other value -> ``bad_version``
6       2     header_len u16      bytes from offset 0 to the first payload byte (= 47 + n in
                                  v1, 53 + n in v2). Readers skip bytes between the last
                                  field of the message's version and header_len (room for
                                  later additions); 47 + n (v2: 53 + n) <= header_len <= 1024
8       2     flags     u16       which sensor fields follow (see "Sensor fields"); 0 for
                                  none. Unknown bits are ignored
10      8     seq       u64       per-robot frame counter, increasing by 1 from 0 on each
                                  (re)start of the camera
18      8     stamp     f64       capture time in seconds (the source's clock); finite, >= 0
26      1     kind      u8        0 rgbd, 1 stereo, 2 mono
27      1     color_enc u8        encoding of the (left) image: 0 raw, 1 png, 2 jpeg
28      1     second_enc u8       encoding of the second image: 0 none, 1 raw, 2 png
                                  (rgbd: depth as uint16, raw little-endian or 16-bit grey
                                  PNG; stereo: right image as uint8 grey, raw or 8-bit PNG;
                                  mono: must be 0)
29      2     width     u16       image width in pixels, 1..Limits.max_width
31      2     height    u16       image height in pixels, 1..Limits.max_height
33      1     channels  u8        channels of the (left) image: 1 grey or 3 BGR
34      4     depth_scale f32     raw depth units per metre (1000 = millimetres); 1e-3..1e9
                                  for rgbd, finite >= 0 otherwise (writers send theirs)
38      1     n         u8        length of the robot id in bytes
39      n     robot               utf-8 robot id (same rules as in the key)
39+n    4     color_len u32       byte length of payload 1
43+n    4     second_len u32      byte length of payload 2 (0 when second_enc is none)
47+n    1     label_enc u8        (v2 only) encoding of the label image: 0 none, 1 raw, 2 png
48+n    1     label_bytes u8      (v2 only) bytes per label pixel: 1 (uint8 class ids) or 2
                                  (uint16, for class tables of more than 256 classes); 0 when
                                  label_enc is none
49+n    4     label_len u32       (v2 only) byte length of payload 3 (0 when label_enc is none)
47+n    ...                       v1: the sensor fields the flags announce, then
                                  (optional extension bytes up to header_len)
53+n    ...                       v2: the same
header_len    color_len bytes     payload 1: the (left) image
...           second_len bytes    payload 2: depth or right image
...           label_len bytes     payload 3 (v2): the label image
======  ====  ==================  =============================================================

The message is exactly ``header_len + color_len + second_len`` (v2: ``+ label_len``) bytes
long.

Label image (v2): per-pixel class ids of the (left) image, W x H like it (pixel (u, v) of the
labels is pixel (u, v) of the image); the ids index the camera info's class table (``classes``,
default `DEFAULT_CLASSES`, ADE20K-32: 0 other, 1 wall, ..., 15 door, ..., 31 armchair). Raw:
W*H bytes (uint8) or W*H uint16 little-endian; PNG: 8-bit (uint8) or 16-bit (uint16) grey, as
``cv2.imencode`` writes them, checked like depth (dimensions and bit depth from the IHDR before
decoding). Lossless either way; label PNGs are small (piecewise constant: ~5 KB at 640 x 480
for the synthetic scene against 300 KB raw). Writers send uint8 when every id is < 256. The
decoder returns the image as ``frame.extras["labels"]`` (H x W uint8 / uint16) and, when the
receiver passes the camera's class table, the names as ``frame.extras["label_names"]`` (a
tuple). A receiver that knows the table (`Limits.classes`) rejects ids beyond it
(``bad_labels``).

Payloads: raw images are row-major H x W x C uint8 (BGR for C = 3), exactly W*H*C bytes; raw
depth is W*H uint16 little-endian, raw right image W*H uint8. PNG colour is 8-bit grey
(C = 1) or 8-bit RGB (C = 3) - as ``cv2.imencode`` writes them; depth PNG is 16-bit grey;
right PNG is 8-bit grey. JPEG has 1 (grey) or 3 (colour) components. Width, height, bit
depth and component count of PNG / JPEG payloads are read from their headers and checked
against the message header BEFORE decoding, so a small payload cannot make the receiver
allocate more than its `Limits` allow.

Depth travels as uint16 in depth_scale units: ``q = round(metres * depth_scale)`` clipped to
1..65535; invalid depth (0, negative, NaN, inf) travels as 0 and decodes to 0.0. The decoder
returns ``q / depth_scale`` as float32 metres, so raw and PNG depth are exact to 1/depth_scale
(1 mm at the default 1000). JPEG colour is lossy (quality 90 by default). The encoder writes
PNG at zlib level 1 (`png_compression`), depth PNG with the Z_RLE strategy (faster and smaller
on noisy sensor depth); readers accept any valid PNG of the right format.

Decoding and errors
===================
`decode_frame` checks, in this order, before it decodes any image: message size (`Limits.
max_message_bytes`), magic, version, fixed header present, header_len, robot id, payload
lengths against the message length, kind / encodings / channels / depth_scale, width and
height against the limits, stamp, raw payload lengths (== W*H*C), PNG / JPEG header
dimensions. Any malformed input raises `ProtocolError(reason, message)` and nothing else;
``reason`` is one of these stable codes (count drops per reason with them):

================  ===============================================================
reason            cause
================  ===============================================================
bad_type          the input is not bytes-like
too_large         the message (or a JSON message) exceeds the limits
truncated         shorter than its header or than header + payload lengths
bad_length        longer than header + payload lengths (trailing bytes)
bad_magic         does not start with b"MSLF"
bad_version       version is not in FRAME_VERSIONS (JSON: "version" is not 1)
bad_header        header_len out of range, unknown kind / encoding / channel count,
                  kind and encodings inconsistent, bad depth_scale; label encoding
                  unknown, label_bytes not 1 or 2 (wrong label dtype), or label
                  bytes without a label encoding; a depth stamp in a frame without
                  depth; an accelerometer field not finite or beyond MAX_ACCEL
bad_size          width / height 0 or above the limits, raw payload length != W*H*C
                  (raw labels: != W*H*label_bytes), empty compressed payload
bad_robot         robot id not utf-8 or not matching the robot pattern
bad_stamp         stamp (or depth_stamp) NaN, infinite or negative
bad_seq           seq not an integer in 0..2**64-1 (encoding / JSON)
decode_failed     PNG / JPEG payload is corrupt, of the wrong format or bit depth (a
                  label PNG whose bit depth disagrees with label_bytes)
size_mismatch     image dimensions in the PNG / JPEG header, or of the decoded image,
                  differ from the message header; or the header's differ from
                  `Limits.size` (the receiver's expected size, e.g. the calibration's)
bad_labels        a label id >= the number of classes in the camera's class table
                  (`Limits.classes`, when the receiver sets it)
bad_frame         (encoding only) the Frame cannot be sent: wrong dtype / shape (also
                  of its labels), or labels asked for and frame.extras has none, or
                  its extras' accel is not 3 finite numbers within MAX_ACCEL
bad_json          JSON message not utf-8 JSON object, or a field of the wrong type
bad_field         JSON field out of range (non-finite or non-positive focal length...)
bad_kind          unknown camera kind or event kind
================  ===============================================================

`ProtocolError` subclasses `ValueError`.

Camera info message (JSON, utf-8, on ``<prefix>/<robot>/camera/info``)
=====================================================================
``{"version": 1, "robot": "r1", "kind": "rgbd" | "stereo" | "mono", "fx": 525.0, "fy": 525.0,
"cx": 319.5, "cy": 239.5, "width": 640, "height": 480, "baseline": null | metres,
"depth_scale": 1000.0}`` - pinhole intrinsics of the images. fx, fy
finite > 0; cx, cy finite; width, height integers 1..65535; baseline finite > 0 for stereo
and null otherwise; depth_scale finite > 0. Unknown extra fields are ignored.

Optional ``"distortion": [k1, k2, p1, p2, k3]``: the lens distortion of the images the camera
sends (OpenCV's radial-tangential order; 4, 5 or 8 finite numbers, ``bad_field`` otherwise).
Absent, null or all zeros: the images are undistorted. The camera sends its raw images (an
RGB-D camera's depth registered to the raw colour image) and the service undistorts feature
coordinates; stereo images must be rectified (no distortion). Writers leave the field out
when there is none, so an older service reads the message as before.

Optional ``"classes": ["other", "wall", ...]``: the class table of the camera's label images,
names indexed by class id: 1..65536 (`MAX_CLASSES`) distinct names of 1..64 printable
characters (``bad_json`` if not a list of strings, ``bad_field`` otherwise). Absent or null:
the default table `DEFAULT_CLASSES` (ADE20K-32, 32 names). Sent once with the camera info, not
with every frame; the service takes the table of the robot's first camera info (like the
calibration) and hands it to the pipeline as ``frame.extras["label_names"]``.

Optional ``"localize": true``: the robot asks for localization only (the service's
``memory.incremental: false`` for this robot alone, RTAB-Map's ``Mem/IncrementalMemory``): it is
tracked and relocalizes in the stored map, and nothing of it is written to the map (``bad_field``
if not a JSON boolean). Absent or false: the service's mode (it maps unless it localizes only).
Writers leave the field out unless it is true, so an older service reads the message as before
(and maps).

Pose message (JSON, on ``<prefix>/<robot>/pose``)
=================================================
``{"version": 1, "robot", "seq", "stamp", "status", "pose", "keyframe", "segment", "node_id"}``:
seq (integer 0..2**64-1) and stamp (seconds, finite >= 0) of the frame it answers; status a
lower-case word ``[a-z_]{1,32}`` (the pipeline uses "ok", "init", "lost", "skipped"); pose a
4 x 4 row-major nested list of finite numbers with last row 0 0 0 1, the camera-to-world
transform (OpenCV camera axes) in the map frame of ``segment``, or null when not tracked;
keyframe true / false (JSON booleans only); segment an integer 0..2**31-1, the map the pose is
expressed in (the service decides when a new one starts, e.g. after tracking was lost);
node_id the pose-graph node of the keyframe (integer >= 0) or null. Back-pressure, optional
(absent = unknown): queue_depth, the robot's frames waiting in the service when the pose was
sent, and dropped, how many of its frames the service has dropped so far because its queue was
full (integers >= 0). A camera that sees dropped grow sends too fast for the service. Frame,
optional (absent = unknown: an older service): ``map``, the map id whose frame the pose is in (a
mapping robot: its own session's map until it relocalizes in an older one, then that map's), or
null while the pose is in a frame no map names (a localizing robot before it relocalized: its own
odometry frame).

Event message (JSON, on ``<prefix>/<robot>/events``)
====================================================
``{"version": 1, "robot", "kind", "data": {...}}`` with kind one of `EVENT_KINDS`
("keyframe_added", "loop_closed", "tracking_lost", "map_corrected", "session_started",
"session_ended", "frame_rejected", "relocalized") and JSON data (numpy scalars / arrays are converted to
numbers / lists). The service sends:

==================  ==========================================================================
kind                data
==================  ==========================================================================
session_started     ``session_id``: the map database's session of this robot
keyframe_added      ``node_id``, ``seq``, ``stamp`` of the frame that became a keyframe
tracking_lost       ``seq``, ``stamp`` of the first lost frame
loop_closed         ``from``, ``to`` (node ids: the older keyframe, the new one), ``inliers``
                    (verified correspondences), ``link``: the new link's type, by its name
                    in ``storage.LINK_NAMES``: "loop" (bag-of-words, by appearance),
                    "proximity" (a keyframe the graph placed near the new one) or "merged"
                    (rehearsal: ``to`` was merged into the older node ``from``)
map_corrected       ``nodes``: how many keyframe poses the map update moved
relocalized         the robot's session joined an older map (once per session, when a link
                    first joins its keyframes to that map's): ``session_id``, ``map`` (the map
                    id it is in now), ``node_id`` and ``stamp`` (its keyframe at the joining
                    link), ``peer`` (the map's keyframe at that link), ``link`` (its type's
                    name), ``T_map_session`` (16 numbers, row-major 4×4: the session's own frame,
                    its first keyframe's camera, in the map's frame); poses published from then
                    on are in that map's frame. A localizing robot (camera info ``localize``,
                    or the service's ``memory.incremental: false``) has no session: its event
                    has ``session_id`` null, ``localization`` true, ``seq`` and ``stamp`` of
                    its first frame in the map's frame, ``node_id`` null, ``peer`` the map's
                    keyframe its keyframes are linked to, ``T_map_session`` its odometry
                    frame in the map's (once per relocalization: again after it lost it)
session_ended       ``session_id``, ``reason``: "restarted" (the camera's stamps jumped back by
                    more than ``service.restart_gap``: a camera or clock restart; a
                    ``session_started`` of the new session follows), "idle" or "stopped"
frame_rejected      ``reason`` (a `ProtocolError` reason, or the service's: "stamp_order",
                    "no_calibration", "too_many_robots", ...), ``seq`` of the refused frame
                    (null when its header could not be read), ``detail`` (text, may be empty);
                    one per frame the service refused on the robot's frame key, so a camera
                    knows a frame will not be answered
==================  ==========================================================================
"""
from __future__ import annotations

import json
import math
import re
import struct
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .frames import Calibration, Frame, PinholeCamera

PROTOCOL_VERSION = 2  # the newest frame message version this module reads and writes
FRAME_VERSIONS = (1, 2)  # frame message versions read: 1 (no labels) and 2 (optional label image)
JSON_VERSION = 1  # the "version" of the JSON messages (camera info, pose, event)
MAGIC = b"MSLF"
DEFAULT_PREFIX = "mnemoslam"

KINDS = {"rgbd": 0, "stereo": 1, "mono": 2}
COLOR_ENCODINGS = {"raw": 0, "png": 1, "jpeg": 2}
SECOND_ENCODINGS = {"none": 0, "raw": 1, "png": 2}
LABEL_ENCODINGS = {"none": 0, "raw": 1, "png": 2}
EVENT_KINDS = ("keyframe_added", "loop_closed", "tracking_lost", "map_corrected", "session_started", "session_ended",
               "frame_rejected", "relocalized")
_KIND_NAMES = {v: k for k, v in KINDS.items()}
_COLOR_NAMES = {v: k for k, v in COLOR_ENCODINGS.items()}
_SECOND_NAMES = {v: k for k, v in SECOND_ENCODINGS.items()}
_LABEL_NAMES = {v: k for k, v in LABEL_ENCODINGS.items()}

# The default class table: ADE20K reduced to 32 classes (the default segmentation model's, see
# ../shared/models/README.md; the synthetic scene labels with these ids). A camera info without
# "classes" means this table.
DEFAULT_CLASSES: tuple[str, ...] = (
    "other", "wall", "building", "sky", "floor", "tree", "ceiling", "road", "bed", "windowpane", "grass",
    "cabinet", "sidewalk", "person", "earth", "door", "table", "mountain", "plant", "curtain", "chair", "car",
    "water", "painting", "sofa", "shelf", "house", "sea", "mirror", "rug", "field", "armchair")
MAX_CLASSES = 65536  # class ids travel as uint8 or uint16
MAX_CLASS_NAME = 64  # characters

ROBOT_PATTERN = re.compile(r"[A-Za-z0-9_\-]{1,64}")
_PREFIX_CHUNK = re.compile(r"[A-Za-z0-9_.\-]+")
_STATUS_PATTERN = re.compile(r"[a-z_]{1,32}")

# magic, version, header_len, flags, seq, stamp, kind, color_enc, second_enc, width, height,
# channels, depth_scale, robot_len
_FIXED = struct.Struct("<4sHHHQdBBBHHBfB")
_LENGTHS = struct.Struct("<II")
_LABEL_FIELDS = struct.Struct("<BBI")  # v2: label_enc, label_bytes, label_len (after the lengths)
FLAG_DEPTH_STAMP, FLAG_ACCEL = 1, 2  # flags bits: the sensor fields that follow the version's fields
_DEPTH_STAMP = struct.Struct("<d")
_ACCEL = struct.Struct("<ddd")
MAX_ACCEL = 1000.0  # m/s²: an accelerometer reading beyond this is not one
FIXED_HEADER_BYTES = _FIXED.size  # 39
MAX_HEADER_BYTES = 1024
MIN_DEPTH_SCALE, MAX_DEPTH_SCALE = 1e-3, 1e9  # raw depth units per metre accepted for rgbd frames
_U64_MAX = 2**64 - 1

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}

assert FIXED_HEADER_BYTES == 39 and _LABEL_FIELDS.size == 6


class ProtocolError(ValueError):
    """A message that cannot be encoded or decoded. `reason` is a short stable code (see the
    module documentation), `message` says what exactly was wrong."""

    def __init__(self, reason: str, message: str):
        super().__init__(f"{reason}: {message}")
        self.reason = reason
        self.message = message


@dataclass(frozen=True)
class Limits:
    """What a receiver accepts. Checked before anything is decoded or allocated."""

    max_message_bytes: int = 32 * 1024 * 1024
    max_width: int = 4096
    max_height: int = 4096
    max_json_bytes: int = 1024 * 1024
    size: tuple[int, int] | None = None  # (width, height) the receiver expects (the camera's calibration)
    classes: int | None = None  # label ids must be < classes (the camera's class table); None: not checked


DEFAULT_LIMITS = Limits()


# ------------------------------------------------------------------------------------------
# key expressions

def check_robot(robot: Any) -> str:
    """`robot` if it is a valid robot id, else ProtocolError("bad_robot")."""
    if not isinstance(robot, str) or not ROBOT_PATTERN.fullmatch(robot):
        raise ProtocolError("bad_robot", f"robot id must match {ROBOT_PATTERN.pattern}, got {robot!r:.80}")
    return robot


class KeySpace:
    """The key expressions of one deployment (one prefix)."""

    CHANNELS = ("camera/frame", "camera/info", "pose", "events")

    def __init__(self, prefix: str = DEFAULT_PREFIX):
        chunks = prefix.split("/") if isinstance(prefix, str) else None
        if not chunks or not all(_PREFIX_CHUNK.fullmatch(c) for c in chunks):
            raise ProtocolError("bad_field",
                                f"key prefix must be '/'-separated chunks of [A-Za-z0-9_.-], got {prefix!r}")
        self.prefix = prefix
        self._depth = len(chunks)

    def __repr__(self) -> str:
        return f"KeySpace({self.prefix!r})"

    def __eq__(self, other) -> bool:
        return isinstance(other, KeySpace) and other.prefix == self.prefix

    def __hash__(self) -> int:
        return hash(self.prefix)

    def _key(self, robot: str, channel: str) -> str:
        return f"{self.prefix}/{check_robot(robot)}/{channel}"

    def frame(self, robot: str) -> str:
        return self._key(robot, "camera/frame")

    def info(self, robot: str) -> str:
        return self._key(robot, "camera/info")

    def pose(self, robot: str) -> str:
        return self._key(robot, "pose")

    def events(self, robot: str) -> str:
        return self._key(robot, "events")

    def frames_wildcard(self) -> str:
        return f"{self.prefix}/*/camera/frame"

    def info_wildcard(self) -> str:
        return f"{self.prefix}/*/camera/info"

    def poses_wildcard(self) -> str:
        return f"{self.prefix}/*/pose"

    def events_wildcard(self) -> str:
        return f"{self.prefix}/*/events"

    def parse(self, key: Any) -> tuple[str, str] | None:
        """(robot, channel) of a concrete key of this key space, channel one of `CHANNELS`;
        None for anything else (other prefix, wildcard, invalid robot id)."""
        parts = str(key).split("/")
        d = self._depth
        if len(parts) < d + 2 or "/".join(parts[:d]) != self.prefix:
            return None
        robot, channel = parts[d], "/".join(parts[d + 1:])
        if channel not in self.CHANNELS or not ROBOT_PATTERN.fullmatch(robot):
            return None
        return robot, channel

    def robot_of(self, key: Any) -> str | None:
        """The robot id in a key of this key space (str or zenoh.KeyExpr), or None."""
        p = self.parse(key)
        return p[0] if p else None


# ------------------------------------------------------------------------------------------
# frame message

@dataclass
class WireFrame:
    """A decoded frame message. `frame.index` is `seq`; `size` is the message size in bytes."""

    robot: str
    seq: int
    frame: Frame
    kind: str  # "rgbd" | "stereo" | "mono"
    color_encoding: str  # "raw" | "png" | "jpeg"
    depth_encoding: str  # "none" | "raw" | "png" (of the depth or the right image)
    size: int
    label_encoding: str = "none"  # "none" | "raw" | "png": the label image (frame.extras["labels"])
    version: int = 1  # the message's version (2 when it has a label image)


def frame_kind(frame: Frame) -> str:
    """What a frame is on the wire: stereo if it has a right image, rgbd if it has depth, else mono."""
    if frame.right is not None:
        return "stereo"
    if frame.depth is not None:
        return "rgbd"
    return "mono"


def quantize_depth(depth: np.ndarray, depth_scale: float) -> np.ndarray:
    """Metres (float, 0 / NaN / <= 0 invalid) -> uint16 depth_scale units, invalid 0, valid
    clipped to 1..65535."""
    d = np.asarray(depth, dtype=np.float32)
    with np.errstate(invalid="ignore", over="ignore"):
        q = np.rint(d * np.float32(depth_scale))
        valid = np.isfinite(q) & (d > 0)
    out = np.zeros(d.shape, np.uint16)
    out[valid] = np.clip(q[valid], 1, 65535).astype(np.uint16)
    return out


def dequantize_depth(q: np.ndarray, depth_scale: float) -> np.ndarray:
    """uint16 depth_scale units -> float32 metres (0 stays 0)."""
    return q.astype(np.float32) / np.float32(depth_scale)


def peek_seq(payload: Any) -> int | None:
    """The seq field of a frame message whose fixed header is there (magic and length checked
    only), else None: for reporting a refused frame by its seq."""
    try:
        data = memoryview(payload)
        if data.nbytes >= FIXED_HEADER_BYTES and bytes(data[:4]) == MAGIC:
            return int(struct.unpack_from("<Q", data, 10)[0])
    except (TypeError, ValueError, struct.error):
        pass
    return None


def _check_stamp(stamp: Any) -> float:
    if isinstance(stamp, bool) or not isinstance(stamp, (int, float, np.integer, np.floating)):
        raise ProtocolError("bad_stamp", f"stamp must be a number, got {type(stamp).__name__}")
    s = float(stamp)
    if not math.isfinite(s) or s < 0:
        raise ProtocolError("bad_stamp", f"stamp must be finite and >= 0, got {s!r}")
    return s


def _check_seq(seq: Any) -> int:
    if isinstance(seq, bool) or not isinstance(seq, (int, np.integer)) or not 0 <= int(seq) <= _U64_MAX:
        raise ProtocolError("bad_seq", f"seq must be an integer in 0..2**64-1, got {seq!r:.40}")
    return int(seq)


def _imencode(ext: str, image: np.ndarray, params: list[int]) -> bytes:
    import cv2

    ok, buf = cv2.imencode(ext, image, params)
    if not ok:  # pragma: no cover - OpenCV refuses only unsupported dtypes we exclude earlier
        raise ProtocolError("bad_frame", f"OpenCV could not encode a {image.shape} {image.dtype} image as {ext}")
    return buf.tobytes()


def label_image(labels: Any, h: int, w: int) -> np.ndarray:
    """`labels` as the H×W uint8 / uint16 class-id image that travels: uint8 and uint16 as
    they are; other integer arrays as uint8 when every id is < 256, else uint16.
    ProtocolError("bad_frame") for the wrong shape, a non-integer dtype or ids outside 0..65535."""
    if not isinstance(labels, np.ndarray) or labels.shape != (h, w):
        raise ProtocolError("bad_frame", f"labels must be a {h}×{w} array of class ids, got "
                                         f"{getattr(labels, 'shape', type(labels).__name__)}")
    if labels.dtype in (np.uint8, np.uint16):
        return np.ascontiguousarray(labels)
    if not np.issubdtype(labels.dtype, np.integer) or labels.dtype == np.bool_:
        raise ProtocolError("bad_frame", f"labels must be integer class ids, got dtype {labels.dtype}")
    lo, hi = (int(labels.min()), int(labels.max())) if labels.size else (0, 0)
    if lo < 0 or hi >= MAX_CLASSES:
        raise ProtocolError("bad_frame", f"label ids must be in 0..{MAX_CLASSES - 1}, got {lo}..{hi}")
    return np.ascontiguousarray(labels, dtype=np.uint8 if hi < 256 else np.uint16)


def encode_frame(frame: Frame, robot: str, seq: int, *, depth_scale: float = 1000.0, color: str = "jpeg",
                 depth: str = "png", jpeg_quality: int = 90, png_compression: int = 1,
                 kind: str | None = None, labels: str = "none") -> bytes:
    """One frame message (see the module documentation).

    `color` encodes the (left) image: "jpeg" (lossy, `jpeg_quality`), "png" or "raw".
    `depth` encodes the second image (rgbd depth in `depth_scale` units per metre, or the
    stereo right image, converted to grey): "png" or "raw". `kind` defaults to
    `frame_kind(frame)`; "mono" sends only the image of any frame, "rgbd" needs depth and
    "stereo" a right image. `labels` "png" or "raw" also sends `frame.extras["labels"]` (the
    per-pixel class ids, `label_image`) as a version 2 message; "none" (the default) sends a
    version 1 message without them, whatever the frame's extras hold. Raises ProtocolError
    (reasons bad_robot, bad_seq, bad_stamp, bad_frame, bad_header) for what cannot be sent.
    """
    check_robot(robot)
    seq = _check_seq(seq)
    stamp = _check_stamp(frame.stamp)
    kind = frame_kind(frame) if kind is None else kind
    if kind not in KINDS:
        raise ProtocolError("bad_kind", f"kind must be one of {', '.join(KINDS)}, got {kind!r}")
    if color not in COLOR_ENCODINGS:
        raise ProtocolError("bad_header", f"colour encoding must be jpeg, png or raw, got {color!r}")
    if labels not in LABEL_ENCODINGS:
        raise ProtocolError("bad_header", f"label encoding must be none, png or raw, got {labels!r}")
    second_name = "none" if kind == "mono" else depth
    if second_name not in ("none", "raw", "png") or (kind != "mono" and second_name == "none"):
        raise ProtocolError("bad_header", f"depth / right encoding must be png or raw, got {depth!r}")
    scale = float(np.float32(depth_scale)) if isinstance(depth_scale, (int, float, np.number)) else float("nan")
    if not (math.isfinite(scale) and MIN_DEPTH_SCALE <= scale <= MAX_DEPTH_SCALE):
        raise ProtocolError("bad_header", f"depth_scale must be in {MIN_DEPTH_SCALE:g}..{MAX_DEPTH_SCALE:g}, "
                                          f"got {depth_scale!r}")

    image = frame.image
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or not (
            image.ndim == 2 or (image.ndim == 3 and image.shape[2] in (1, 3))):
        raise ProtocolError("bad_frame", "image must be H×W or H×W×3 uint8")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    h, w = image.shape[:2]
    channels = 1 if image.ndim == 2 else 3
    if not (1 <= w <= 65535 and 1 <= h <= 65535):
        raise ProtocolError("bad_frame", f"image size {w}×{h} does not fit the protocol (1..65535)")
    image = np.ascontiguousarray(image)

    if color == "raw":
        p1 = image.tobytes()
    elif color == "png":
        import cv2

        p1 = _imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, int(png_compression)])
    else:
        import cv2

        p1 = _imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])

    p2 = b""
    if kind == "rgbd":
        if frame.depth is None:
            raise ProtocolError("bad_frame", "an rgbd frame needs depth")
        d = np.asarray(frame.depth)
        if d.shape != (h, w) or not (np.issubdtype(d.dtype, np.floating) or np.issubdtype(d.dtype, np.integer)):
            raise ProtocolError("bad_frame", f"depth must be a {h}×{w} array of metres, got {d.shape} {d.dtype}")
        second = quantize_depth(d, scale)
    elif kind == "stereo":
        if frame.right is None:
            raise ProtocolError("bad_frame", "a stereo frame needs a right image")
        r = frame.right
        if not isinstance(r, np.ndarray) or r.dtype != np.uint8 or r.shape[:2] != (h, w) or not (
                r.ndim == 2 or (r.ndim == 3 and r.shape[2] in (1, 3))):
            raise ProtocolError("bad_frame", f"right image must be a {h}×{w} uint8 image")
        if r.ndim == 3:
            import cv2

            r = r[:, :, 0] if r.shape[2] == 1 else cv2.cvtColor(r, cv2.COLOR_BGR2GRAY)
        second = np.ascontiguousarray(r)
    if kind != "mono":
        if second_name == "raw":
            p2 = second.astype("<u2").tobytes() if kind == "rgbd" else second.tobytes()
        else:
            import cv2

            params = [cv2.IMWRITE_PNG_COMPRESSION, int(png_compression)]
            if kind == "rgbd":  # Z_RLE: 1.5x faster than the default on noisy sensor depth, and smaller
                params += [cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE]
            p2 = _imencode(".png", second, params)

    flags, sensors = _sensor_fields(frame, kind)
    rb = robot.encode("utf-8")
    header_len = FIXED_HEADER_BYTES + len(rb) + _LENGTHS.size + len(sensors)
    if labels == "none":  # version 1: byte for byte what writers sent before labels existed
        head = _FIXED.pack(MAGIC, 1, header_len, flags, seq, stamp, KINDS[kind],
                           COLOR_ENCODINGS[color], SECOND_ENCODINGS[second_name], w, h, channels, scale, len(rb))
        return b"".join((head, rb, _LENGTHS.pack(len(p1), len(p2)), sensors, p1, p2))
    if "labels" not in frame.extras:
        raise ProtocolError("bad_frame", f"{frame.source or 'frame'}: no labels to send (frame.extras['labels'])")
    lab = label_image(frame.extras["labels"], h, w)
    if labels == "raw":
        p3 = lab.astype("<u2").tobytes() if lab.dtype == np.uint16 else lab.tobytes()
    else:
        import cv2

        p3 = _imencode(".png", lab, [cv2.IMWRITE_PNG_COMPRESSION, int(png_compression)])
    header_len += _LABEL_FIELDS.size
    head = _FIXED.pack(MAGIC, 2, header_len, flags, seq, stamp, KINDS[kind],
                       COLOR_ENCODINGS[color], SECOND_ENCODINGS[second_name], w, h, channels, scale, len(rb))
    return b"".join((head, rb, _LENGTHS.pack(len(p1), len(p2)),
                     _LABEL_FIELDS.pack(LABEL_ENCODINGS[labels], lab.itemsize, len(p3)), sensors, p1, p2, p3))


def _sensor_fields(frame: Frame, kind: str) -> tuple[int, bytes]:
    """(flags, the sensor fields' bytes) of a frame's ``extras["depth_stamp"]`` (rgbd only)
    and ``extras["accel"]``; (0, b"") for a frame without them."""
    flags, out = 0, []
    ds = frame.extras.get("depth_stamp")
    if ds is not None and kind == "rgbd":
        try:
            ds = float(ds)
        except (TypeError, ValueError):
            raise ProtocolError("bad_stamp", f"depth_stamp {ds!r} is not a number") from None
        if not (math.isfinite(ds) and ds >= 0):
            raise ProtocolError("bad_stamp", f"depth_stamp {ds!r}")
        flags |= FLAG_DEPTH_STAMP
        out.append(_DEPTH_STAMP.pack(ds))
    a = frame.extras.get("accel")
    if a is not None:
        try:
            v = np.asarray(a, np.float64).reshape(3)
        except (TypeError, ValueError):
            raise ProtocolError("bad_frame", f"accel must be 3 numbers, got {a!r}") from None
        if not (np.all(np.isfinite(v)) and float(np.linalg.norm(v)) <= MAX_ACCEL):
            raise ProtocolError("bad_frame", f"accel {v.tolist()} is not an accelerometer reading")
        flags |= FLAG_ACCEL
        out.append(_ACCEL.pack(*v.tolist()))
    return flags, b"".join(out)


def png_header(data: memoryview, what: str) -> tuple[int, int, int, int]:
    """(width, height, bit depth, colour type) from a PNG's IHDR, without decoding."""
    if len(data) < 33 or bytes(data[:8]) != PNG_SIGNATURE or bytes(data[12:16]) != b"IHDR":
        raise ProtocolError("decode_failed", f"{what}: not a PNG")
    w, h, bits, ctype = struct.unpack_from(">IIBB", data, 16)
    return w, h, bits, ctype


def jpeg_header(data: memoryview, what: str) -> tuple[int, int, int]:
    """(width, height, components) from a JPEG's SOF segment, without decoding."""
    n = len(data)
    if n < 4 or data[0] != 0xFF or data[1] != 0xD8:
        raise ProtocolError("decode_failed", f"{what}: not a JPEG")
    i = 2
    while i + 1 < n:
        if data[i] != 0xFF:
            raise ProtocolError("decode_failed", f"{what}: corrupt JPEG marker at byte {i}")
        m = data[i + 1]
        if m == 0xFF:  # fill byte
            i += 1
            continue
        if m == 0x01 or 0xD0 <= m <= 0xD7:  # stand-alone markers
            i += 2
            continue
        if m in (0xD9, 0xDA):  # end of image / start of scan before any frame header
            break
        if i + 4 > n:
            break
        length = (data[i + 2] << 8) | data[i + 3]
        if length < 2:
            break
        if m in _JPEG_SOF:
            if i + 10 > n:
                break
            h = (data[i + 5] << 8) | data[i + 6]
            w = (data[i + 7] << 8) | data[i + 8]
            return w, h, data[i + 9]
        i += 2 + length
    raise ProtocolError("decode_failed", f"{what}: JPEG without a frame header")


def imdecode(data: memoryview, what: str, w: int, h: int, channels: int, dtype) -> np.ndarray:
    import cv2

    try:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    except Exception as e:  # cv2.error and anything else the codec throws
        raise ProtocolError("decode_failed", f"{what}: {type(e).__name__}: {str(e).strip()[:200]}") from None
    if img is None:
        raise ProtocolError("decode_failed", f"{what}: the codec could not decode it")
    if img.dtype != dtype:
        raise ProtocolError("decode_failed", f"{what}: decoded to {img.dtype}, expected {np.dtype(dtype)}")
    want = (h, w) if channels == 1 else (h, w, channels)
    if img.shape != want:
        raise ProtocolError("size_mismatch", f"{what}: decoded shape {img.shape}, header says {want}")
    return img


def _decode_image(data: memoryview, encoding: str, what: str, w: int, h: int, channels: int,
                  bits: int) -> np.ndarray:
    """One payload to an array of the header's shape; dimensions checked before decoding."""
    dtype = np.uint16 if bits == 16 else np.uint8
    if encoding == "raw":  # length already checked
        a = np.frombuffer(data, "<u2" if bits == 16 else np.uint8)
        a = a.reshape((h, w) if channels == 1 else (h, w, channels))
        return a.astype(dtype, copy=True)
    if encoding == "png":
        pw, ph, pbits, ctype = png_header(data, what)
        if (pw, ph) != (w, h):
            raise ProtocolError("size_mismatch", f"{what}: PNG is {pw}×{ph}, header says {w}×{h}")
        want_ctype = 0 if channels == 1 else 2
        if pbits != bits or ctype != want_ctype:
            raise ProtocolError("decode_failed", f"{what}: PNG is {pbits}-bit colour type {ctype}, "
                                                 f"expected {bits}-bit colour type {want_ctype}")
        return imdecode(data, what, w, h, channels, dtype)
    # jpeg
    jw, jh, comps = jpeg_header(data, what)
    if (jw, jh) != (w, h):
        raise ProtocolError("size_mismatch", f"{what}: JPEG is {jw}×{jh}, header says {w}×{h}")
    if comps != channels:
        raise ProtocolError("decode_failed", f"{what}: JPEG has {comps} components, header says {channels} channels")
    return imdecode(data, what, w, h, channels, dtype)


def decode_frame(payload: Any, limits: Limits = DEFAULT_LIMITS,
                 label_names: tuple[str, ...] | None = None) -> WireFrame:
    """A frame message back to a `WireFrame`; every malformed input raises ProtocolError (see
    the module documentation for the order of the checks and the reason codes). A label image
    comes as ``frame.extras["labels"]`` (H×W uint8 / uint16), and then `label_names` (the
    camera info's class table, if it had one) as ``frame.extras["label_names"]``."""
    try:
        data = memoryview(payload).cast("B")
    except (TypeError, ValueError):
        raise ProtocolError("bad_type", f"expected bytes, got {type(payload).__name__}") from None
    n = len(data)
    if n > limits.max_message_bytes:
        raise ProtocolError("too_large", f"{n} bytes > limit {limits.max_message_bytes}")
    if n < 4:
        raise ProtocolError("truncated", f"{n} bytes, no magic")
    if bytes(data[:4]) != MAGIC:
        raise ProtocolError("bad_magic", f"starts with {bytes(data[:4])!r}, expected {MAGIC!r}")
    if n < 6:
        raise ProtocolError("truncated", f"{n} bytes, no version")
    version = data[4] | (data[5] << 8)
    if version not in FRAME_VERSIONS:
        raise ProtocolError("bad_version", f"version {version}, this reader speaks "
                                           f"{', '.join(map(str, FRAME_VERSIONS))}")
    if n < FIXED_HEADER_BYTES:
        raise ProtocolError("truncated", f"{n} bytes < fixed header {FIXED_HEADER_BYTES}")
    (_, _, header_len, flags, seq, stamp, kind, cenc, senc, w, h, channels, scale,
     rlen) = _FIXED.unpack_from(data, 0)
    fields_end = FIXED_HEADER_BYTES + rlen + _LENGTHS.size + (_LABEL_FIELDS.size if version >= 2 else 0)
    min_header = (fields_end + (_DEPTH_STAMP.size if flags & FLAG_DEPTH_STAMP else 0)
                  + (_ACCEL.size if flags & FLAG_ACCEL else 0))
    if not min_header <= header_len <= MAX_HEADER_BYTES:
        raise ProtocolError("bad_header", f"header_len {header_len} outside {min_header}..{MAX_HEADER_BYTES}")
    if n < header_len:
        raise ProtocolError("truncated", f"{n} bytes < header_len {header_len}")
    try:
        robot = bytes(data[FIXED_HEADER_BYTES:FIXED_HEADER_BYTES + rlen]).decode("utf-8")
    except UnicodeDecodeError:
        raise ProtocolError("bad_robot", "robot id is not utf-8") from None
    check_robot(robot)
    clen, slen = _LENGTHS.unpack_from(data, FIXED_HEADER_BYTES + rlen)
    lenc = lbytes = llen = 0
    if version >= 2:
        lenc, lbytes, llen = _LABEL_FIELDS.unpack_from(data, FIXED_HEADER_BYTES + rlen + _LENGTHS.size)
    total = header_len + clen + slen + llen
    if total > n:
        raise ProtocolError("truncated", f"{n} bytes < header {header_len} + payloads {clen} + {slen} + {llen}")
    if total < n:
        raise ProtocolError("bad_length", f"{n} bytes > header {header_len} + payloads {clen} + {slen} + {llen}")
    if kind not in _KIND_NAMES:
        raise ProtocolError("bad_header", f"unknown kind {kind}")
    if cenc not in _COLOR_NAMES:
        raise ProtocolError("bad_header", f"unknown colour encoding {cenc}")
    if senc not in _SECOND_NAMES:
        raise ProtocolError("bad_header", f"unknown depth/right encoding {senc}")
    if channels not in (1, 3):
        raise ProtocolError("bad_header", f"channels {channels}, expected 1 or 3")
    if lenc not in _LABEL_NAMES:
        raise ProtocolError("bad_header", f"unknown label encoding {lenc}")
    if (lenc == 0 and (lbytes or llen)) or (lenc != 0 and lbytes not in (1, 2)):
        raise ProtocolError("bad_header", f"label image of {lbytes} bytes per pixel ({llen} bytes) with label "
                                          f"encoding {_LABEL_NAMES[lenc]} (expected 1 = uint8 or 2 = uint16)")
    kname = _KIND_NAMES[kind]
    if (kname == "mono") != (senc == 0):
        raise ProtocolError("bad_header", f"{kname} frame with depth/right encoding {_SECOND_NAMES[senc]}")
    if not math.isfinite(scale) or scale < 0 or (kname == "rgbd" and not MIN_DEPTH_SCALE <= scale <= MAX_DEPTH_SCALE):
        raise ProtocolError("bad_header", f"depth_scale {scale!r}")
    if not (1 <= w <= limits.max_width and 1 <= h <= limits.max_height):
        raise ProtocolError("bad_size", f"image {w}×{h} outside 1..{limits.max_width}×1..{limits.max_height}")
    if limits.size is not None and (w, h) != tuple(limits.size):
        raise ProtocolError("size_mismatch", f"image {w}×{h}, the camera's calibration says "
                                             f"{limits.size[0]}×{limits.size[1]}")
    if not math.isfinite(stamp) or stamp < 0:
        raise ProtocolError("bad_stamp", f"stamp {stamp!r}")
    sensors: dict[str, Any] = {}
    at = fields_end
    if flags & FLAG_DEPTH_STAMP:
        (depth_stamp,) = _DEPTH_STAMP.unpack_from(data, at)
        at += _DEPTH_STAMP.size
        if kname != "rgbd":
            raise ProtocolError("bad_header", f"a depth stamp in a {kname} frame")
        if not math.isfinite(depth_stamp) or depth_stamp < 0:
            raise ProtocolError("bad_stamp", f"depth_stamp {depth_stamp!r}")
        sensors["depth_stamp"] = float(depth_stamp)
    if flags & FLAG_ACCEL:
        accel = np.array(_ACCEL.unpack_from(data, at), np.float64)
        if not (np.all(np.isfinite(accel)) and float(np.linalg.norm(accel)) <= MAX_ACCEL):
            raise ProtocolError("bad_header", f"accel {accel.tolist()} is not an accelerometer reading")
        sensors["accel"] = accel
    second_bytes_per_pixel = 2 if kname == "rgbd" else 1
    if cenc == 0 and clen != w * h * channels:
        raise ProtocolError("bad_size", f"raw image is {clen} bytes, expected {w}×{h}×{channels}")
    if cenc != 0 and clen == 0:
        raise ProtocolError("bad_size", "empty compressed image")
    if senc == 1 and slen != w * h * second_bytes_per_pixel:
        raise ProtocolError("bad_size", f"raw {'depth' if kname == 'rgbd' else 'right image'} is {slen} bytes, "
                                        f"expected {w}×{h}×{second_bytes_per_pixel}")
    if senc == 2 and slen == 0:
        raise ProtocolError("bad_size", "empty compressed depth/right image")
    if senc == 0 and slen != 0:
        raise ProtocolError("bad_header", f"{slen} bytes of second payload without an encoding")
    if lenc == 1 and llen != w * h * lbytes:
        raise ProtocolError("bad_size", f"raw label image is {llen} bytes, expected {w}×{h}×{lbytes}")
    if lenc == 2 and llen == 0:
        raise ProtocolError("bad_size", "empty compressed label image")

    p1 = data[header_len:header_len + clen]
    p2 = data[header_len + clen:header_len + clen + slen]
    p3 = data[header_len + clen + slen:total]
    image = _decode_image(p1, _COLOR_NAMES[cenc], "image", w, h, channels, 8)
    depth = right = None
    if kname == "rgbd":
        depth = dequantize_depth(_decode_image(p2, _SECOND_NAMES[senc], "depth", w, h, 1, 16), scale)
    elif kname == "stereo":
        right = _decode_image(p2, _SECOND_NAMES[senc], "right image", w, h, 1, 8)
    frame = Frame(index=seq, stamp=stamp, image=image, depth=depth, right=right, source=f"{robot}#{seq}",
                  extras=sensors)
    if lenc:
        labels = _decode_image(p3, _LABEL_NAMES[lenc], "labels", w, h, 1, 8 * lbytes)
        if limits.classes is not None and labels.size and int(labels.max()) >= limits.classes:
            raise ProtocolError("bad_labels", f"label id {int(labels.max())} >= {limits.classes}, the number of "
                                              f"classes in the camera's class table")
        frame.extras["labels"] = labels
        if label_names is not None:
            frame.extras["label_names"] = tuple(label_names)
    return WireFrame(robot, seq, frame, kname, _COLOR_NAMES[cenc], _SECOND_NAMES[senc], n, _LABEL_NAMES[lenc],
                     version)


# ------------------------------------------------------------------------------------------
# JSON messages

def _json_default(o):
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, np.bool_):
        return bool(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"{type(o).__name__} is not JSON serialisable")


def _dump(obj: dict) -> bytes:
    try:
        return json.dumps(obj, default=_json_default, allow_nan=False, separators=(",", ":")).encode("utf-8")
    except (TypeError, ValueError) as e:
        raise ProtocolError("bad_json", f"cannot serialise: {e}") from None


def _load(data: Any, limits: Limits, what: str) -> dict:
    try:
        raw = bytes(memoryview(data).cast("B"))
    except (TypeError, ValueError):
        if isinstance(data, str):
            raw = data.encode("utf-8", "surrogatepass")
        else:
            raise ProtocolError("bad_type", f"{what}: expected bytes, got {type(data).__name__}") from None
    if len(raw) > limits.max_json_bytes:
        raise ProtocolError("too_large", f"{what}: {len(raw)} bytes > limit {limits.max_json_bytes}")

    def no_constants(name):  # NaN / Infinity are not JSON
        raise ValueError(f"{name} is not allowed")

    try:
        obj = json.loads(raw.decode("utf-8"), parse_constant=no_constants)
    except (UnicodeDecodeError, ValueError, RecursionError) as e:
        raise ProtocolError("bad_json", f"{what}: {type(e).__name__}: {str(e)[:200]}") from None
    if not isinstance(obj, dict):
        raise ProtocolError("bad_json", f"{what}: expected a JSON object, got {type(obj).__name__}")
    if obj.get("version") != JSON_VERSION or isinstance(obj.get("version"), bool):
        raise ProtocolError("bad_version", f"{what}: version {obj.get('version')!r:.40}, expected {JSON_VERSION}")
    check_robot(obj.get("robot"))
    return obj


def _number(obj: dict, key: str, what: str, *, positive: bool = False, nonneg: bool = False) -> float:
    v = obj.get(key)
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ProtocolError("bad_json", f"{what}: {key} must be a number, got {v!r:.40}")
    v = float(v)
    if not math.isfinite(v) or (positive and v <= 0) or (nonneg and v < 0):
        cond = " > 0" if positive else " >= 0" if nonneg else ""
        raise ProtocolError("bad_field", f"{what}: {key} must be finite{cond}, got {v!r}")
    return v


def _integer(obj: dict, key: str, what: str, lo: int, hi: int, *, reason: str = "bad_field") -> int:
    v = obj.get(key)
    if isinstance(v, bool) or not isinstance(v, int):
        raise ProtocolError("bad_json", f"{what}: {key} must be an integer, got {v!r:.40}")
    if not lo <= v <= hi:
        raise ProtocolError(reason, f"{what}: {key} must be in {lo}..{hi}, got {v}")
    return v


@dataclass(frozen=True)
class CameraInfo:
    robot: str
    kind: str  # "rgbd" | "stereo" | "mono"
    calibration: Calibration
    classes: tuple[str, ...] | None = None  # the class table of its label images; None: DEFAULT_CLASSES
    localize: bool = False  # the robot asks for localization only (nothing of it written to the map)

    @property
    def class_count(self) -> int:
        """How many class ids its label images may use (ids are < this)."""
        return len(self.classes if self.classes is not None else DEFAULT_CLASSES)


def check_classes(classes: Any, what: str = "camera info") -> tuple[str, ...]:
    """A class table as a tuple of names: 1..MAX_CLASSES distinct non-empty strings of at most
    MAX_CLASS_NAME printable characters (ProtocolError "bad_json" / "bad_field" otherwise)."""
    if isinstance(classes, (str, bytes)) or not isinstance(classes, (list, tuple)):
        raise ProtocolError("bad_json", f"{what}: classes must be a list of names, got {type(classes).__name__}")
    if not 1 <= len(classes) <= MAX_CLASSES:
        raise ProtocolError("bad_field", f"{what}: classes must have 1..{MAX_CLASSES} names, got {len(classes)}")
    for i, c in enumerate(classes):
        if not isinstance(c, str):
            raise ProtocolError("bad_json", f"{what}: class {i} must be a string, got {c!r:.40}")
        if not 1 <= len(c) <= MAX_CLASS_NAME or not c.isprintable():
            raise ProtocolError("bad_field", f"{what}: class {i} must be 1..{MAX_CLASS_NAME} printable "
                                             f"characters, got {c!r:.80}")
    if len(set(classes)) != len(classes):
        dup = next(c for i, c in enumerate(classes) if c in classes[:i])
        raise ProtocolError("bad_field", f"{what}: class name {dup!r:.80} appears twice")
    return tuple(classes)


def _calibration_fields(calibration: Calibration, kind: str) -> dict:
    c = calibration.camera
    return {"fx": float(c.fx), "fy": float(c.fy), "cx": float(c.cx), "cy": float(c.cy), "width": int(c.width),
            "height": int(c.height), "baseline": None if calibration.baseline is None else float(calibration.baseline),
            "depth_scale": float(calibration.depth_scale),
            **({"distortion": [float(v) for v in c.distortion]} if c.distortion else {})}


def _check_info(obj: dict, what: str = "camera info") -> CameraInfo:
    robot = obj["robot"]
    kind = obj.get("kind")
    if kind not in KINDS:
        raise ProtocolError("bad_kind", f"{what}: kind must be one of {', '.join(KINDS)}, got {kind!r:.40}")
    fx = _number(obj, "fx", what, positive=True)
    fy = _number(obj, "fy", what, positive=True)
    cx = _number(obj, "cx", what)
    cy = _number(obj, "cy", what)
    width = _integer(obj, "width", what, 1, 65535)
    height = _integer(obj, "height", what, 1, 65535)
    baseline = None if obj.get("baseline") is None else _number(obj, "baseline", what, positive=True)
    depth_scale = _number(obj, "depth_scale", what, positive=True)
    if (kind == "stereo") != (baseline is not None):
        raise ProtocolError("bad_field", f"{what}: a {kind} camera must {'' if kind == 'stereo' else 'not '}"
                                         f"have a baseline, got {baseline!r}")
    distortion = obj.get("distortion")
    if distortion is None:
        distortion = ()
    elif (not isinstance(distortion, list) or len(distortion) not in (4, 5, 8)
          or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                     for v in distortion)):
        raise ProtocolError("bad_field", f"{what}: distortion must be a list of 4, 5 or 8 finite numbers "
                                         f"(k1 k2 p1 p2 [k3 [k4 k5 k6]]), got {distortion!r:.80}")
    if baseline is not None and any(distortion):
        raise ProtocolError("bad_field", f"{what}: a stereo camera sends rectified images, without distortion")
    cal = Calibration(PinholeCamera(fx, fy, cx, cy, width, height, tuple(distortion)), baseline, depth_scale)
    classes = obj.get("classes")
    localize = obj.get("localize", False)
    if localize is None:
        localize = False
    if not isinstance(localize, bool):
        raise ProtocolError("bad_field", f"{what}: localize must be true or false, got {localize!r:.40}")
    return CameraInfo(robot, kind, cal, None if classes is None else check_classes(classes, what), localize)


def encode_info(robot: str, calibration: Calibration, kind: str | None = None,
                classes: tuple[str, ...] | list[str] | None = None, localize: bool = False) -> bytes:
    """The camera info message; `kind` defaults to `calibration.kind` ("stereo" with a
    baseline, else "rgbd"); pass "mono" for a camera without depth. `classes`: the class table
    (names indexed by class id) of the label images the camera sends; None leaves the field out
    (the default table, `DEFAULT_CLASSES`). `localize`: ask for localization only (the field is
    sent only when true)."""
    kind = calibration.kind if kind is None else kind
    obj = {"version": JSON_VERSION, "robot": check_robot(robot), "kind": kind,
           **_calibration_fields(calibration, kind)}
    if classes is not None:
        obj["classes"] = list(check_classes(classes))
    if localize:
        obj["localize"] = True
    _check_info(json.loads(_dump(obj)))
    return _dump(obj)


def decode_info_message(data: Any, limits: Limits = DEFAULT_LIMITS) -> CameraInfo:
    """The camera info message as `CameraInfo(robot, kind, calibration, classes)`."""
    return _check_info(_load(data, limits, "camera info"))


def decode_info(data: Any, limits: Limits = DEFAULT_LIMITS) -> tuple[str, Calibration]:
    """(robot, Calibration) of a camera info message; ProtocolError if malformed. (The camera
    kind, which distinguishes mono from rgbd, is in `decode_info_message`.)"""
    info = decode_info_message(data, limits)
    return info.robot, info.calibration


@dataclass
class PoseMessage:
    robot: str
    seq: int
    stamp: float
    status: str
    pose: np.ndarray | None  # 4×4 camera-to-world, or None when not tracked
    keyframe: bool
    segment: int
    node_id: int | None
    queue_depth: int | None = None  # frames of this robot waiting in the service when it was sent
    dropped: int | None = None  # frames of this robot the service dropped so far (queue full)
    map: int | None = None  # the map id whose frame the pose is in; None: a frame no map names (or unknown)
    has_map: bool = False  # the message said which frame (`map`; absent from an older service's)


def _check_pose_matrix(pose: Any, what: str) -> np.ndarray | None:
    if pose is None:
        return None
    try:
        m = np.array(pose, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        raise ProtocolError("bad_json", f"{what}: pose must be a 4×4 matrix of numbers") from None
    if m.shape != (4, 4):
        raise ProtocolError("bad_field", f"{what}: pose must be 4×4, got shape {m.shape}")
    if not np.all(np.isfinite(m)):
        raise ProtocolError("bad_field", f"{what}: pose has non-finite entries")
    if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
        raise ProtocolError("bad_field", f"{what}: pose last row must be 0 0 0 1, got {m[3].tolist()}")
    return m


def _check_status(status: Any, what: str) -> str:
    if not isinstance(status, str) or not _STATUS_PATTERN.fullmatch(status):
        raise ProtocolError("bad_field", f"{what}: status must match {_STATUS_PATTERN.pattern}, got {status!r:.40}")
    return status


def encode_pose(robot: str, seq: int, stamp: float, status: str, pose: np.ndarray | None, keyframe: bool = False,
                segment: int = 0, node_id: int | None = None, queue_depth: int | None = None,
                dropped: int | None = None, map: Any = ...) -> bytes:
    """The pose message for frame `seq` of `robot` (see the module documentation). `map`: the map
    id whose frame the pose is in, None for a frame no map names; left out when not given."""
    what = "pose"
    obj = {"version": JSON_VERSION, "robot": check_robot(robot), "seq": _check_seq(seq),
           "stamp": _check_stamp(stamp), "status": _check_status(status, what)}
    m = _check_pose_matrix(pose, what)
    obj["pose"] = None if m is None else m.tolist()
    obj["keyframe"] = bool(keyframe)
    if isinstance(segment, bool) or not isinstance(segment, (int, np.integer)) or not 0 <= int(segment) < 2**31:
        raise ProtocolError("bad_field", f"{what}: segment must be an integer >= 0, got {segment!r:.40}")
    obj["segment"] = int(segment)
    if node_id is not None and (isinstance(node_id, bool) or not isinstance(node_id, (int, np.integer))
                                or not 0 <= int(node_id) <= _U64_MAX):
        raise ProtocolError("bad_field", f"{what}: node_id must be None or an integer >= 0, got {node_id!r:.40}")
    obj["node_id"] = None if node_id is None else int(node_id)
    for name, v in (("queue_depth", queue_depth), ("dropped", dropped)):
        if v is not None:
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 0 <= int(v) <= _U64_MAX:
                raise ProtocolError("bad_field", f"{what}: {name} must be None or an integer >= 0, got {v!r:.40}")
            obj[name] = int(v)
    if map is not ...:
        if map is not None and (isinstance(map, bool) or not isinstance(map, (int, np.integer))
                                or not 0 <= int(map) <= _U64_MAX):
            raise ProtocolError("bad_field", f"{what}: map must be None or an integer >= 0, got {map!r:.40}")
        obj["map"] = None if map is None else int(map)
    return _dump(obj)


def decode_pose(data: Any, limits: Limits = DEFAULT_LIMITS) -> PoseMessage:
    what = "pose"
    obj = _load(data, limits, what)
    seq = _integer(obj, "seq", what, 0, _U64_MAX, reason="bad_seq")
    stamp = obj.get("stamp")
    if isinstance(stamp, bool) or not isinstance(stamp, (int, float)):
        raise ProtocolError("bad_json", f"{what}: stamp must be a number, got {stamp!r:.40}")
    stamp = _check_stamp(stamp)
    status = _check_status(obj.get("status"), what)
    pose = _check_pose_matrix(obj.get("pose"), what)
    if not isinstance(obj.get("keyframe"), bool):
        raise ProtocolError("bad_json", f"{what}: keyframe must be true or false")
    segment = _integer(obj, "segment", what, 0, 2**31 - 1)
    node_id, queue_depth, dropped, map_id = (None if obj.get(k) is None else _integer(obj, k, what, 0, _U64_MAX)
                                             for k in ("node_id", "queue_depth", "dropped", "map"))
    return PoseMessage(obj["robot"], seq, stamp, status, pose, obj["keyframe"], segment, node_id, queue_depth,
                       dropped, map_id, "map" in obj)


@dataclass
class EventMessage:
    """A decoded event. Also reads like a flat dict: ``e["robot"]``, ``e["kind"]``, then the
    data keys (``e["node_id"]``), ``e.get(key, default)``, ``key in e``."""

    robot: str
    kind: str  # one of EVENT_KINDS
    data: dict = field(default_factory=dict)

    def __getitem__(self, key: str):
        if key == "robot":
            return self.robot
        if key == "kind":
            return self.kind
        return self.data[key]

    def get(self, key: str, default=None):
        try:
            return self[key]
        except KeyError:
            return default

    def __contains__(self, key: str) -> bool:
        return key in ("robot", "kind") or key in self.data

    def as_dict(self) -> dict:
        """{"robot", "kind", **data} (data keys named robot / kind would be shadowed)."""
        return {**self.data, "robot": self.robot, "kind": self.kind}


def encode_event(robot: str, kind: str, /, **data) -> bytes:
    """An event message; `data` is any JSON-serialisable keyword data (numpy allowed). `robot`
    and `kind` are positional-only, so data keys of those names cannot collide with them."""
    if kind not in EVENT_KINDS:
        raise ProtocolError("bad_kind", f"event kind must be one of {', '.join(EVENT_KINDS)}, got {kind!r:.40}")
    return _dump({"version": JSON_VERSION, "robot": check_robot(robot), "kind": kind, "data": data})


def decode_event(data: Any, limits: Limits = DEFAULT_LIMITS) -> EventMessage:
    what = "event"
    obj = _load(data, limits, what)
    kind = obj.get("kind")
    if kind not in EVENT_KINDS:
        raise ProtocolError("bad_kind", f"{what}: kind must be one of {', '.join(EVENT_KINDS)}, got {kind!r:.40}")
    payload = obj.get("data", {})
    if not isinstance(payload, dict):
        raise ProtocolError("bad_json", f"{what}: data must be a JSON object")
    return EventMessage(obj["robot"], kind, payload)


__all__ = [
    "PROTOCOL_VERSION", "FRAME_VERSIONS", "JSON_VERSION", "MAGIC", "DEFAULT_PREFIX", "KINDS", "COLOR_ENCODINGS",
    "SECOND_ENCODINGS", "LABEL_ENCODINGS", "DEFAULT_CLASSES", "MAX_CLASSES", "MAX_CLASS_NAME", "check_classes",
    "label_image", "EVENT_KINDS",
    "ROBOT_PATTERN", "FIXED_HEADER_BYTES", "MAX_HEADER_BYTES", "ProtocolError", "Limits", "DEFAULT_LIMITS",
    "KeySpace", "check_robot", "WireFrame", "frame_kind", "quantize_depth", "dequantize_depth", "encode_frame",
    "decode_frame", "peek_seq", "CameraInfo", "encode_info", "decode_info", "decode_info_message", "PoseMessage",
    "encode_pose", "decode_pose", "EventMessage", "encode_event", "decode_event",
]
