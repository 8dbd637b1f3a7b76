"""ROS 2 messages as CDR bytes, without a ROS install: the camera topics a robot publishes
(sensor_msgs/Image, sensor_msgs/CompressedImage incl. compressedDepth, sensor_msgs/CameraInfo)
to our `Frame` / `Calibration`, and our poses to geometry_msgs/PoseStamped.

The CDR (de)serializer is `rosbags`' type store (ROS 2 Humble message definitions; the
messages used here are the same in every ROS 2 distribution). Payloads are what DDS and
zenoh-bridge-ros2dds / rmw_zenoh carry: a 4-byte encapsulation header (CDR little- or
big-endian) and the message.

Decoding follows the conventions of `mnemoslam.client.kernel.frames` and `mnemoslam.client.kernel.protocol`:

- colour comes out H×W×3 uint8 **BGR** or H×W uint8 grey. `Image` encodings: ``bgr8``,
  ``rgb8``, ``bgra8``, ``rgba8``, ``mono8`` (and ``8UC1`` / ``8UC3`` as mono8 / bgr8).
  `CompressedImage`: JPEG (1 or 3 components) or 8-bit PNG (grey, colour, colour + alpha),
  taken as BGR like image_transport's ``compressed`` plugin writes them (it converts to bgr8
  before encoding).
- depth comes out H×W float32 **metres**, 0 = no measurement. `Image` encodings ``16UC1`` /
  ``mono16`` (millimetres, REP 118) and ``32FC1`` (metres; NaN, inf and <= 0 become 0).
  compressedDepth (format ``"16UC1; compressedDepth png"`` or ``"32FC1; compressedDepth
  png"``): image_transport's 12-byte header (int32 format, float32 depthQuantA, depthQuantB)
  then a 16-bit grey PNG: millimetres for 16UC1, quantized inverse depth for 32FC1 (``depth =
  A / (q - B)``, q = 0 none). The RVL codec is not supported (``bad_encoding``).
  Millimetres become ``q / 1000`` exactly as `protocol.dequantize_depth` makes them, so a
  16UC1 stream maps as a native stream at depth_scale 1000.
- PNG / JPEG dimensions and bit depth are read from their headers and checked before
  decoding, as the native protocol does.

Every malformed input raises `mnemoslam.client.kernel.protocol.ProtocolError` with a stable reason:
``bad_cdr`` (not a CDR message of the expected type), ``too_large``, ``bad_encoding``
(an encoding / format this module does not convert), ``bad_size`` (data shorter than
step × height, step shorter than a row, sizes out of the limits), ``size_mismatch`` (not the
size of the camera's calibration), ``decode_failed`` (corrupt PNG / JPEG), ``bad_stamp``
(negative), ``bad_info`` (a CameraInfo we cannot use).
"""
from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np

from .kernel.frames import Calibration, PinholeCamera
from .kernel.protocol import (
    PNG_SIGNATURE,
    ProtocolError,
    dequantize_depth,
    imdecode,
    jpeg_header,
    png_header,
    quantize_depth,
)

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
DEPTH_SCALE = 1000.0  # ROS depth images in 16UC1 are millimetres (REP 118)
COLOR_ENCODINGS = ("bgr8", "rgb8", "bgra8", "rgba8", "mono8", "8UC1", "8UC3")
DEPTH_ENCODINGS = ("16UC1", "mono16", "32FC1")
_COMPRESSED_DEPTH_HEADER = struct.Struct("<iff")  # image_transport's ConfigHeader: format, depthQuantA, depthQuantB
_NS = 1_000_000_000


@lru_cache(maxsize=1)
def typestore():
    """rosbags' type store of the ROS 2 Humble messages (built once, ~0.1 s)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)


# ------------------------------------------------------------------------------------------
# CDR

def deserialize(payload: Any, typename: str, max_bytes: int | None = None):
    """CDR bytes to a rosbags message object of `typename` (ProtocolError ``bad_cdr`` /
    ``too_large``). Array fields are numpy views into `payload`."""
    try:
        data = memoryview(payload).cast("B")
    except (TypeError, ValueError):
        raise ProtocolError("bad_cdr", f"expected bytes, got {type(payload).__name__}") from None
    if max_bytes is not None and len(data) > max_bytes:
        raise ProtocolError("too_large", f"{len(data)} bytes > limit {max_bytes}")
    if len(data) < 4 or data[0] != 0 or data[1] not in (0, 1):
        raise ProtocolError("bad_cdr", f"{typename}: no CDR encapsulation header")
    try:
        return typestore().deserialize_cdr(data, typename)
    except Exception as e:  # rosbags' SerdeError, and whatever a crafted length makes numpy raise
        raise ProtocolError("bad_cdr", f"{typename}: {type(e).__name__}: {str(e)[:200]}") from None


def serialize(message, typename: str) -> bytes:
    """A rosbags message object to CDR bytes (little-endian, with the encapsulation header)."""
    return bytes(typestore().serialize_cdr(message, typename))


def stamp_ns(msg) -> int:
    """The message's header stamp in integer nanoseconds (ProtocolError ``bad_stamp`` if negative)."""
    t = msg.header.stamp
    ns = int(t.sec) * _NS + int(t.nanosec)
    if ns < 0 or not 0 <= int(t.nanosec) < _NS:
        raise ProtocolError("bad_stamp", f"header stamp {t.sec} s {t.nanosec} ns")
    return ns


def seconds(ns: int) -> float:
    """Integer nanoseconds to float seconds (one correctly rounded division: ns / 1e9)."""
    return ns / 1e9


def _header(ns: int, frame_id: str):
    ts = typestore()
    sec, nsec = divmod(int(ns), _NS)
    return ts.types["std_msgs/msg/Header"](stamp=ts.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec),
                                           frame_id=frame_id)


# ------------------------------------------------------------------------------------------
# images -> arrays

def _check_size(w: int, h: int, what: str, size: tuple[int, int] | None, max_side: int) -> None:
    if not (1 <= w <= max_side and 1 <= h <= max_side):
        raise ProtocolError("bad_size", f"{what}: {w}×{h} outside 1..{max_side}")
    if size is not None and (w, h) != tuple(size):
        raise ProtocolError("size_mismatch", f"{what}: {w}×{h}, the camera's calibration says {size[0]}×{size[1]}")


def _rows(msg, what: str, bytes_per_pixel: int, dtype: str) -> np.ndarray:
    """The image's pixels as an H×W(×C) view of `dtype` (C = bytes_per_pixel / itemsize),
    rows `step` bytes apart."""
    w, h, step = int(msg.width), int(msg.height), int(msg.step)
    data = msg.data
    if step < w * bytes_per_pixel:
        raise ProtocolError("bad_size", f"{what}: step {step} < width {w} × {bytes_per_pixel} bytes")
    if len(data) < step * h:
        raise ProtocolError("bad_size", f"{what}: {len(data)} bytes < step {step} × height {h}")
    rows = np.asarray(data[:step * h], np.uint8).reshape(h, step)[:, :w * bytes_per_pixel]
    dt = np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<")
    channels = bytes_per_pixel // dt.itemsize
    px = np.ascontiguousarray(rows).view(dt)  # (a copy only when rows are padded)
    return px.reshape(h, w, channels) if channels > 1 else px.reshape(h, w)


def image_color(msg, size: tuple[int, int] | None = None, max_side: int = 65535) -> np.ndarray:
    """A sensor_msgs/Image of a colour encoding to BGR H×W×3 / grey H×W uint8 (a new array)."""
    import cv2

    enc = str(msg.encoding)
    _check_size(int(msg.width), int(msg.height), "image", size, max_side)
    if enc in ("mono8", "8UC1"):
        return _rows(msg, "image", 1, "u1").copy()
    if enc in ("bgr8", "8UC3"):
        return _rows(msg, "image", 3, "u1").copy()
    if enc == "rgb8":
        return cv2.cvtColor(_rows(msg, "image", 3, "u1"), cv2.COLOR_RGB2BGR)
    if enc == "bgra8":
        return cv2.cvtColor(_rows(msg, "image", 4, "u1"), cv2.COLOR_BGRA2BGR)
    if enc == "rgba8":
        return cv2.cvtColor(_rows(msg, "image", 4, "u1"), cv2.COLOR_RGBA2BGR)
    raise ProtocolError("bad_encoding", f"image encoding {enc!r:.40}; colour images take {', '.join(COLOR_ENCODINGS)}")


def _metres(d: np.ndarray) -> np.ndarray:
    """float metres with every non-measurement (NaN, inf, <= 0) as 0, float32."""
    d = d.astype(np.float32)  # (native byte order, a new array)
    with np.errstate(invalid="ignore"):
        d[~(np.isfinite(d) & (d > 0))] = 0.0
    return d


def image_depth(msg, size: tuple[int, int] | None = None, max_side: int = 65535) -> np.ndarray:
    """A sensor_msgs/Image of a depth encoding to H×W float32 metres (0 = none)."""
    enc = str(msg.encoding)
    _check_size(int(msg.width), int(msg.height), "depth", size, max_side)
    if enc in ("16UC1", "mono16"):
        return dequantize_depth(_rows(msg, "depth", 2, "u2"), DEPTH_SCALE)
    if enc == "32FC1":
        return _metres(_rows(msg, "depth", 4, "f4"))
    raise ProtocolError("bad_encoding", f"depth encoding {enc!r:.40}; depth images take {', '.join(DEPTH_ENCODINGS)}")


def _codec(data: memoryview, fmt: str) -> str:
    if len(data) >= 8 and bytes(data[:8]) == PNG_SIGNATURE:
        return "png"
    if len(data) >= 2 and data[0] == 0xFF and data[1] == 0xD8:
        return "jpeg"
    raise ProtocolError("decode_failed", f"compressed image ({fmt!r:.60}) is neither PNG nor JPEG")


def compressed_color(msg, size: tuple[int, int] | None = None, max_side: int = 65535) -> np.ndarray:
    """A sensor_msgs/CompressedImage (JPEG / 8-bit PNG) to BGR H×W×3 / grey H×W uint8."""
    import cv2

    fmt = str(msg.format)
    if "compresseddepth" in fmt.lower():
        raise ProtocolError("bad_encoding", f"compressed image format {fmt!r:.60} is depth, on a colour key")
    data = memoryview(np.ascontiguousarray(msg.data, np.uint8)).cast("B")
    if _codec(data, fmt) == "png":
        w, h, bits, ctype = png_header(data, "image")
        _check_size(w, h, "image", size, max_side)
        channels = {0: 1, 2: 3, 6: 4}.get(ctype)
        if bits != 8 or channels is None:
            raise ProtocolError("bad_encoding", f"image: {bits}-bit PNG of colour type {ctype}; colour PNGs are "
                                                f"8-bit grey, RGB or RGBA")
    else:
        w, h, channels = jpeg_header(data, "image")
        _check_size(w, h, "image", size, max_side)
        if channels not in (1, 3):
            raise ProtocolError("bad_encoding", f"image: JPEG with {channels} components")
    img = imdecode(data, "image", w, h, channels, np.uint8)
    return cv2.cvtColor(img, cv2.COLOR_BGRA2BGR) if channels == 4 else img


def compressed_depth(msg, size: tuple[int, int] | None = None, max_side: int = 65535) -> np.ndarray:
    """A compressedDepth sensor_msgs/CompressedImage (PNG) to H×W float32 metres (0 = none)."""
    fmt = str(msg.format)
    original = fmt.split(";")[0].strip()
    low = fmt.lower()
    if "rvl" in low:
        raise ProtocolError("bad_encoding",
                            f"compressed depth format {fmt!r:.60}: the RVL codec is not supported (use png)")
    if original not in DEPTH_ENCODINGS:
        raise ProtocolError("bad_encoding", f"compressed depth format {fmt!r:.60}; expected 16UC1 or 32FC1 "
                                            f"compressedDepth png")
    data = memoryview(np.ascontiguousarray(msg.data, np.uint8)).cast("B")
    quant = None
    if len(data) >= 8 and bytes(data[:8]) == PNG_SIGNATURE:  # (writers without the config header)
        png = data
    elif len(data) >= _COMPRESSED_DEPTH_HEADER.size + 8 and bytes(data[12:20]) == PNG_SIGNATURE:
        _, a, b = _COMPRESSED_DEPTH_HEADER.unpack_from(data, 0)
        quant, png = (a, b), data[_COMPRESSED_DEPTH_HEADER.size:]
    else:
        raise ProtocolError("decode_failed", f"compressed depth ({fmt!r:.60}): no PNG after the 12-byte header")
    w, h, bits, ctype = png_header(png, "depth")
    _check_size(w, h, "depth", size, max_side)
    if bits != 16 or ctype != 0:
        raise ProtocolError("decode_failed", f"depth: {bits}-bit PNG of colour type {ctype}, expected 16-bit grey")
    q = imdecode(png, "depth", w, h, 1, np.uint16)
    if original != "32FC1":
        return dequantize_depth(q, DEPTH_SCALE)
    if quant is None or not all(math.isfinite(v) for v in quant):
        raise ProtocolError("decode_failed", "32FC1 compressed depth without its quantization parameters")
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.float32(quant[0]) / (q.astype(np.float32) - np.float32(quant[1]))
    d[q == 0] = 0.0
    return _metres(d)


def decode_color(msg, size=None, max_side: int = 65535) -> np.ndarray:
    """Colour from an Image or a CompressedImage message object."""
    return compressed_color(msg, size, max_side) if hasattr(msg, "format") else image_color(msg, size, max_side)


def decode_depth(msg, size=None, max_side: int = 65535) -> np.ndarray:
    """Depth metres from an Image or a compressedDepth CompressedImage message object."""
    return compressed_depth(msg, size, max_side) if hasattr(msg, "format") else image_depth(msg, size, max_side)


# ------------------------------------------------------------------------------------------
# CameraInfo -> Calibration

def calibration(msg, intrinsics: str = "k", max_side: int = 65535) -> Calibration:
    """The pinhole calibration of a sensor_msgs/CameraInfo: K and the lens distortion D
    (``intrinsics="k"``: the raw images, depth registered to them; plumb_bob or
    rational_polynomial D, other models only when D is zero) or the left 3×3 of P (``"p"``:
    the rectified images of image_rect topics, no distortion). Depth scale 1000 (16UC1
    millimetres; 32FC1 depth is metres anyway). ProtocolError ``bad_info`` for a size or
    intrinsics we cannot use, binning or a region of interest."""
    w, h = int(msg.width), int(msg.height)
    if not (1 <= w <= max_side and 1 <= h <= max_side):
        raise ProtocolError("bad_info", f"camera info size {w}×{h} outside 1..{max_side}")
    if int(msg.binning_x) > 1 or int(msg.binning_y) > 1:
        raise ProtocolError("bad_info", f"camera info binning {msg.binning_x}×{msg.binning_y} is not supported")
    roi = msg.roi
    if int(roi.width) not in (0, w) or int(roi.height) not in (0, h) or int(roi.x_offset) or int(roi.y_offset):
        raise ProtocolError("bad_info", "camera info with a region of interest is not supported")
    m = np.asarray(msg.k if intrinsics == "k" else msg.p, np.float64)
    if m.size != (9 if intrinsics == "k" else 12):
        raise ProtocolError("bad_info", f"camera info {intrinsics.upper()} has {m.size} values")
    m = m.reshape(3, -1)
    fx, fy, cx, cy = float(m[0, 0]), float(m[1, 1]), float(m[0, 2]), float(m[1, 2])
    if not all(math.isfinite(v) for v in (fx, fy, cx, cy)) or fx <= 0 or fy <= 0:
        raise ProtocolError("bad_info", f"camera info {intrinsics.upper()}: fx {fx}, fy {fy}, cx {cx}, cy {cy}")
    distortion: tuple[float, ...] = ()
    d = np.asarray(msg.d, np.float64).reshape(-1)
    if intrinsics == "k" and d.size and np.any(d != 0):
        model = str(msg.distortion_model)
        if model not in ("plumb_bob", "rational_polynomial") or d.size not in (4, 5, 8) \
                or not np.all(np.isfinite(d)):
            raise ProtocolError("bad_info", f"camera info distortion {model!r} with {d.size} coefficients is not "
                                            "supported (plumb_bob, rational_polynomial; or use the rectified images)")
        distortion = tuple(float(v) for v in d)
    return Calibration(PinholeCamera(fx, fy, cx, cy, w, h, distortion), None, DEPTH_SCALE)


# ------------------------------------------------------------------------------------------
# writers (the service's pose; cameras and tests)

def quaternion(R: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w) unit quaternion of a rotation matrix, w >= 0 (Shepperd's method)."""
    R = np.asarray(R, np.float64)
    t = R[0, 0] + R[1, 1] + R[2, 2]
    if t > 0:
        s = 2.0 * math.sqrt(1.0 + t)
        q = ((R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s)
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = (0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s)
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = ((R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s)
    else:
        s = 2.0 * math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = ((R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s, (R[1, 0] - R[0, 1]) / s)
    q = np.array(q)
    q /= np.linalg.norm(q)
    if q[3] < 0:
        q = -q
    return tuple(float(v) for v in q)


def rotation(q) -> np.ndarray:
    """The rotation matrix of an (x, y, z, w) quaternion."""
    x, y, z, w = (float(v) for v in q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def encode_pose_stamped(pose: np.ndarray, ns: int, frame_id: str = "map") -> bytes:
    """A 4×4 camera-to-world pose as CDR geometry_msgs/PoseStamped stamped `ns` nanoseconds."""
    ts = typestore()
    T = ts.types
    x, y, z = (float(v) for v in np.asarray(pose)[:3, 3])
    qx, qy, qz, qw = quaternion(np.asarray(pose)[:3, :3])
    msg = T[POSE_STAMPED](header=_header(ns, frame_id), pose=T["geometry_msgs/msg/Pose"](
        position=T["geometry_msgs/msg/Point"](x=x, y=y, z=z),
        orientation=T["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw)))
    return serialize(msg, POSE_STAMPED)


@dataclass(frozen=True)
class PoseStamped:
    ns: int  # header stamp, nanoseconds
    frame_id: str
    pose: np.ndarray  # 4×4


def decode_pose_stamped(payload: Any) -> PoseStamped:
    msg = deserialize(payload, POSE_STAMPED)
    p, o = msg.pose.position, msg.pose.orientation
    T = np.eye(4)
    T[:3, :3] = rotation((o.x, o.y, o.z, o.w))
    T[:3, 3] = (p.x, p.y, p.z)
    return PoseStamped(stamp_ns(msg), str(msg.header.frame_id), T)


def encode_image(array: np.ndarray, encoding: str, ns: int, frame_id: str = "camera") -> bytes:
    """An array as CDR sensor_msgs/Image: colour BGR / grey uint8 as `encoding` (bgr8, rgb8,
    mono8), depth as 16UC1 (float metres are quantized to millimetres, `protocol.
    quantize_depth`; uint16 is taken as millimetres) or 32FC1 (float32 metres)."""
    import cv2

    a = np.asarray(array)
    if encoding == "rgb8":
        a = cv2.cvtColor(a, cv2.COLOR_BGR2RGB)
    elif encoding == "16UC1" and a.dtype != np.uint16:
        a = quantize_depth(a, DEPTH_SCALE)
    elif encoding == "32FC1":
        a = a.astype(np.float32)
    a = np.ascontiguousarray(a)
    h, w = a.shape[:2]
    ts = typestore()
    msg = ts.types[IMAGE](header=_header(ns, frame_id), height=h, width=w, encoding=encoding, is_bigendian=0,
                          step=a.strides[0], data=a.view(np.uint8).reshape(-1))
    return serialize(msg, IMAGE)


def encode_compressed(array: np.ndarray, ns: int, codec: str = "png", frame_id: str = "camera") -> bytes:
    """A BGR / grey uint8 image as CDR sensor_msgs/CompressedImage, as image_transport's
    ``compressed`` plugin sends it (format ``"bgr8; png compressed bgr8"``)."""
    import cv2

    a = np.asarray(array)
    enc = "mono8" if a.ndim == 2 else "bgr8"
    ok, buf = cv2.imencode(".png" if codec == "png" else ".jpg", a)
    if not ok:
        raise ValueError(f"OpenCV could not encode a {a.shape} {a.dtype} image as {codec}")
    ts = typestore()
    msg = ts.types[COMPRESSED](header=_header(ns, frame_id), format=f"{enc}; {codec} compressed {enc}",
                               data=buf.reshape(-1))
    return serialize(msg, COMPRESSED)


def encode_compressed_depth(depth: np.ndarray, ns: int, frame_id: str = "camera") -> bytes:
    """Depth (float metres, or uint16 millimetres) as CDR compressedDepth CompressedImage
    (format ``"16UC1; compressedDepth png"``: the 12-byte config header, then PNG-16 millimetres)."""
    import cv2

    d = np.asarray(depth)
    q = d if d.dtype == np.uint16 else quantize_depth(d, DEPTH_SCALE)
    ok, buf = cv2.imencode(".png", q)
    if not ok:
        raise ValueError("OpenCV could not encode the depth as PNG")
    data = np.frombuffer(_COMPRESSED_DEPTH_HEADER.pack(0, 0.0, 0.0) + buf.tobytes(), np.uint8)
    ts = typestore()
    msg = ts.types[COMPRESSED](header=_header(ns, frame_id), format="16UC1; compressedDepth png", data=data)
    return serialize(msg, COMPRESSED)


def encode_camera_info(calib: Calibration, ns: int, frame_id: str = "camera") -> bytes:
    """A calibration as CDR sensor_msgs/CameraInfo (K, P, and D: plumb_bob with the camera's
    distortion, zeros when it has none; rational_polynomial for 8 coefficients)."""
    c = calib.camera
    ts = typestore()
    T = ts.types
    k = np.array([c.fx, 0.0, c.cx, 0.0, c.fy, c.cy, 0.0, 0.0, 1.0])
    p = np.array([c.fx, 0.0, c.cx, 0.0, 0.0, c.fy, c.cy, 0.0, 0.0, 0.0, 1.0, 0.0])
    d = np.zeros(5) if not c.distortion else np.array(c.distortion, np.float64)
    model = "rational_polynomial" if len(d) == 8 else "plumb_bob"
    msg = T[CAMERA_INFO](header=_header(ns, frame_id), height=c.height, width=c.width, distortion_model=model,
                         d=d, k=k, r=np.eye(3).reshape(-1), p=p, binning_x=0, binning_y=0,
                         roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                                    do_rectify=False))
    return serialize(msg, CAMERA_INFO)
