"""Encodings and checks of the long-term memory, the storage package's own (its parts use
them; nothing outside `storage` needs them): arrays as little-endian blobs (`pack`,
`unpack`), JSON text (`to_json`), the validation every write does before touching the file
(`as_int`, `as_rigid`, `prepare_keyframe`, `prepare_object`, ...) and the row decoders of the
read side (`node_from_row`, ...) with the columns they read.

Encodings:

- poses: 4×4 float64 camera-to-world, row-major, little-endian (128 bytes); the node's
  position is also in the `x, y, z` columns for spatial queries (R*Tree when available).
- links: `transform` = T_from_to 4×4 float64 (pose_to = pose_from @ T), `information` 6×6
  float64; `type` uses RTAB-Map's values (`LinkType`); outside the database a type goes by
  its name in `LINK_NAMES` (the one table of link-type names).
- features: `count` = N, `keypoints` N×2 float32 pixels, `descriptors` N×32 uint8 (ORB),
  `points` N×3 float32 camera frame (NaN rows = no depth), `word_ids` N int32 or NULL
  (-1 = no word).
- words: `descriptor` 32 bytes (ORB, 256 bits) of each visual word; a node's word ids and
  the words created for it are written in one transaction (`save_node_words`), so every
  word id ≥ 0 in `features.word_ids` is in `words` (until the word is deleted).
- images: JPEG colour, PNG-16 depth in millimetres (both optional).
- JSON text for session calibration / config and per-node statistics.
- sessions: `ended_at` (wall time) and `end_reason` once ended: "stopped" for a normal
  end, "idle" (the robot sent nothing for service.idle_timeout), "restarted" (its camera
  restarted: stamps back by more than service.restart_gap), "crashed" for one the service
  found still open when it started again.
- objects (v4): `histogram` K float32 (posterior over the source's class table),
  `centroid` 3 float64 in the anchor node's camera frame, `extent` 3 float64 (m, map axes),
  `keyframes` int64 ids of the observing keyframes (the most recent `MAX_OBJECT_KEYFRAMES`).
- statistics: the map update's (service.mapping.mapper) last write for a keyframe, after its words,
  links and poses: a node without a statistics row has not been through the map update.
"""
from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from .records import (
    MAX_OBJECT_KEYFRAMES,
    KeyframeRecord,
    LinkRecord,
    LinkType,
    NodeRecord,
    ObjectRecord,
    SessionRecord,
    StoreError,
    calibration_from_dict,
)

# -- array encoding -------------------------------------------------------------------------


def pack(arr: np.ndarray, dtype) -> bytes:
    """Raw little-endian bytes of `arr` as `dtype` (C order)."""
    return np.ascontiguousarray(arr, dtype=np.dtype(dtype).newbyteorder("<")).tobytes()


def unpack(blob: bytes, dtype, shape: tuple[int, ...]) -> np.ndarray:
    """The array `pack` wrote: a writable, native-order copy of shape `shape`."""
    le = np.dtype(dtype).newbyteorder("<")
    n = int(np.prod(shape)) * le.itemsize
    if blob is None or len(blob) != n:
        got = "NULL" if blob is None else f"{len(blob)} bytes"
        raise StoreError(f"corrupt blob: expected {n} bytes for {shape} {np.dtype(dtype).name}, got {got}")
    return np.frombuffer(blob, le).reshape(shape).astype(np.dtype(dtype), copy=True)


# -- validation (all before any write) ------------------------------------------------------


def as_int(v, what: str) -> int:
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)):
        raise ValueError(f"{what} must be an integer, got {type(v).__name__}")
    return int(v)


def as_float(v, what: str) -> float:
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.integer, np.floating)):
        raise ValueError(f"{what} must be a number, got {type(v).__name__}")
    f = float(v)
    if not math.isfinite(f):
        raise ValueError(f"{what} must be finite, got {f}")
    return f


def as_matrix(m, shape: tuple[int, int], what: str) -> np.ndarray:
    a = np.asarray(m)
    if a.dtype.kind not in "fiu":
        raise ValueError(f"{what} must be a real {shape[0]}×{shape[1]} matrix, got dtype {a.dtype}")
    if a.shape != shape:
        raise ValueError(f"{what} must be {shape[0]}×{shape[1]}, got shape {a.shape}")
    a = a.astype(np.float64)
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{what} has non-finite values")
    return a


def as_rigid(m, what: str) -> np.ndarray:
    a = as_matrix(m, (4, 4), what)
    if np.abs(a[3] - (0.0, 0.0, 0.0, 1.0)).max() > 1e-6:
        raise ValueError(f"{what} is not a homogeneous transform (last row {a[3].tolist()})")
    return a


def as_features(a, what: str, dtype, cols: int | None) -> np.ndarray:
    if not isinstance(a, np.ndarray):
        raise ValueError(f"{what} must be a numpy array, got {type(a).__name__}")
    if a.dtype != np.dtype(dtype):
        raise ValueError(f"{what} must be {np.dtype(dtype).name}, got {a.dtype}")
    want = (cols is None and a.ndim == 1) or (cols is not None and a.ndim == 2 and a.shape[1] == cols)
    if not want:
        shape = "(N,)" if cols is None else f"(N, {cols})"
        raise ValueError(f"{what} must have shape {shape}, got {a.shape}")
    return a


_MAX_WORD_ID = 2**31 - 1  # features.word_ids holds int32


def as_word_ids(a, what: str, lowest: int) -> np.ndarray:
    """A 1-D integer array (or sequence) of word ids in [lowest, 2^31 - 1], as int64."""
    a = np.asarray(a)
    if a.ndim != 1:
        raise ValueError(f"{what} must have shape (N,), got {a.shape}")
    if a.size == 0:
        return np.zeros(0, np.int64)
    if a.dtype.kind not in "iu":
        raise ValueError(f"{what} must be integers, got {a.dtype}")
    lo, hi = int(a.min()), int(a.max())
    if lo < lowest or hi > _MAX_WORD_ID:
        raise ValueError(f"{what} must be in [{lowest}, {_MAX_WORD_ID}], got values in [{lo}, {hi}]")
    return a.astype(np.int64)

_JPEG_MAGIC = b"\xff\xd8\xff"
_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def as_image(b, what: str, magic: bytes, kind: str) -> bytes | None:
    if b is None:
        return None
    if not isinstance(b, (bytes, bytearray, memoryview)):
        raise ValueError(f"{what} must be {kind} bytes, got {type(b).__name__}")
    b = bytes(b)
    if not b.startswith(magic):
        raise ValueError(f"{what} is not {kind} data (starts with {b[:8]!r})")
    return b


def jsonable(obj, what: str):
    """`obj` as plain JSON types: numpy scalars/arrays converted, non-finite floats → null
    (SQLite's JSON functions reject NaN). Anything else is a ValueError naming the key."""
    if obj is None or isinstance(obj, (str, bool)):
        return obj
    if isinstance(obj, np.bool_):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        f = float(obj)
        return f if math.isfinite(f) else None
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist(), what)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return jsonable(dataclasses.asdict(obj), what)
    if isinstance(obj, Mapping):
        out = {}
        for k, v in obj.items():
            if not isinstance(k, (str, int)) or isinstance(k, bool):
                raise ValueError(f"{what}: key {k!r} is not a string")
            out[str(k)] = jsonable(v, f"{what}[{k!r}]")
        return out
    if isinstance(obj, (list, tuple)):
        return [jsonable(v, f"{what}[{i}]") for i, v in enumerate(obj)]
    raise ValueError(f"{what}: {type(obj).__name__} is not JSON-encodable")


def to_json(obj, what: str) -> str | None:
    return None if obj is None else json.dumps(jsonable(obj, what), separators=(",", ":"))


@dataclass
class PreparedKeyframe:
    session_id: int
    stamp: float
    pose: bytes
    xyz: tuple[float, float, float]
    weight: int
    count: int
    keypoints: bytes
    descriptors: bytes
    points: bytes
    word_ids: bytes | None
    color: bytes | None
    depth: bytes | None
    link: tuple[int, bytes, bytes] | None
    statistics: str | None


def prepare_keyframe(rec: KeyframeRecord) -> PreparedKeyframe:
    if not isinstance(rec, KeyframeRecord):
        raise ValueError(f"add_keyframe needs a KeyframeRecord, got {type(rec).__name__}")
    pose = as_rigid(rec.pose, "pose")
    kp = as_features(rec.keypoints, "keypoints", np.float32, 2)
    desc = as_features(rec.descriptors, "descriptors", np.uint8, 32)
    pts = as_features(rec.points, "points", np.float32, 3)
    n = len(kp)
    if len(desc) != n or len(pts) != n:
        raise ValueError(f"feature counts differ: {n} keypoints, {len(desc)} descriptors, {len(pts)} points")
    wid = None
    if rec.word_ids is not None:
        wid = as_features(rec.word_ids, "word_ids", np.int32, None)
        if len(wid) != n:
            raise ValueError(f"{len(wid)} word_ids for {n} keypoints")
    link = None
    if rec.odom_link is not None:
        if not isinstance(rec.odom_link, (tuple, list)) or len(rec.odom_link) not in (2, 3):
            raise ValueError("odom_link must be (from_id, transform 4×4, information 6×6 | None)")
        from_id = as_int(rec.odom_link[0], "odom_link from_id")
        T = as_rigid(rec.odom_link[1], "odom_link transform")
        info = rec.odom_link[2] if len(rec.odom_link) == 3 else None
        info = np.eye(6) if info is None else as_matrix(info, (6, 6), "odom_link information")
        link = (from_id, pack(T, np.float64), pack(info, np.float64))
    if rec.statistics is not None and not isinstance(rec.statistics, Mapping):
        raise ValueError(f"statistics must be a dict, got {type(rec.statistics).__name__}")
    return PreparedKeyframe(
        session_id=as_int(rec.session_id, "session_id"),
        stamp=as_float(rec.stamp, "stamp"),
        pose=pack(pose, np.float64),
        xyz=(float(pose[0, 3]), float(pose[1, 3]), float(pose[2, 3])),
        weight=as_int(rec.weight, "weight"),
        count=n,
        keypoints=pack(kp, np.float32),
        descriptors=pack(desc, np.uint8),
        points=pack(pts, np.float32),
        word_ids=None if wid is None else pack(wid, np.int32),
        color=as_image(rec.image_jpeg, "image_jpeg", _JPEG_MAGIC, "JPEG"),
        depth=as_image(rec.depth_png, "depth_png", _PNG_MAGIC, "PNG"),
        link=link,
        statistics=to_json(rec.statistics, "statistics"),
    )


def as_bbox(bbox) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    try:
        lo, hi = bbox
        lo = tuple(as_float(v, "bbox") for v in lo)
        hi = tuple(as_float(v, "bbox") for v in hi)
    except (TypeError, ValueError) as e:
        raise ValueError(f"bbox must be ((xmin, ymin, zmin), (xmax, ymax, zmax)) of finite numbers: {e}") from None
    if len(lo) != 3 or len(hi) != 3:
        raise ValueError("bbox must be ((xmin, ymin, zmin), (xmax, ymax, zmax))")
    if any(a > b for a, b in zip(lo, hi)):
        raise ValueError(f"bbox min {lo} exceeds max {hi}")
    return lo, hi


NODE_COLUMNS = "n.id, n.session_id, n.robot, n.stamp, n.pose, n.weight, n.label, n.merged_into"


def node_from_row(row) -> NodeRecord:
    return NodeRecord(row[0], row[1], row[2], row[3], unpack(row[4], np.float64, (4, 4)), row[5], row[6], row[7])


def link_from_row(row) -> LinkRecord:
    t = row[2]
    try:
        t = LinkType(t)
    except ValueError:
        pass
    return LinkRecord(row[0], row[1], t, unpack(row[3], np.float64, (4, 4)), unpack(row[4], np.float64, (6, 6)))


def as_end_reason(reason) -> str:
    if not isinstance(reason, str) or not reason.strip():
        raise ValueError(f"end reason must be a non-empty string, got {reason!r}")
    return reason


def session_from_row(row) -> SessionRecord:
    return SessionRecord(row[0], row[1], row[2], row[3], row[4], calibration_from_dict(json.loads(row[5])),
                         None if row[6] is None else json.loads(row[6]), row[7])


SESSION_COLUMNS = "id, robot, map_id, started_at, ended_at, calibration, config, end_reason"

# -- objects (v4) ---------------------------------------------------------------------------


def as_vector(v, n: int | None, what: str, dtype=np.float64) -> np.ndarray:
    a = np.asarray(v)
    if a.dtype.kind not in "fiu":
        raise ValueError(f"{what} must be real numbers, got dtype {a.dtype}")
    if a.ndim != 1 or (n is not None and a.shape[0] != n):
        raise ValueError(f"{what} must have shape ({n if n is not None else 'K'},), got {a.shape}")
    a = a.astype(dtype)
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{what} has non-finite values")
    return a


def prepare_object(o: ObjectRecord) -> tuple:
    """Checked, encoded columns of an object: (id | None, node_id, class_id, label, confidence,
    histogram, centroid, extent, observations, keyframes). ValueError names what is wrong."""
    if not isinstance(o, ObjectRecord):
        raise ValueError(f"expected an ObjectRecord, got {type(o).__name__}")
    oid = None if o.id is None else as_int(o.id, "object id")
    node = as_int(o.node_id, "object node_id")
    hist = as_vector(o.histogram, None, "object histogram", np.float32)
    if hist.shape[0] < 1 or (hist < 0).any():
        raise ValueError("object histogram must be non-empty and non-negative")
    cls = as_int(o.class_id, "object class_id")
    if not 0 <= cls < hist.shape[0]:
        raise ValueError(f"object class_id {cls} is outside the histogram's {hist.shape[0]} classes")
    if not isinstance(o.label, str) or not o.label.strip():
        raise ValueError(f"object label must be a non-empty string, got {o.label!r}")
    conf = as_float(o.confidence, "object confidence")
    if not 0.0 <= conf <= 1.0:
        raise ValueError(f"object confidence must be in [0, 1], got {conf}")
    centroid = as_vector(o.centroid, 3, "object centroid")
    extent = as_vector(o.extent, 3, "object extent")
    if (extent < 0).any():
        raise ValueError(f"object extent must be non-negative, got {extent.tolist()}")
    obs = as_int(o.observations, "object observations")
    if obs < 0:
        raise ValueError(f"object observations must be ≥ 0, got {obs}")
    kf = np.asarray([] if o.keyframes is None else o.keyframes)
    if kf.ndim != 1 or (kf.size and kf.dtype.kind not in "iu"):
        raise ValueError(f"object keyframes must be a 1-D array of node ids, got shape {kf.shape} {kf.dtype}")
    kf = kf.astype(np.int64)[-MAX_OBJECT_KEYFRAMES:]
    return (oid, node, cls, o.label, conf, pack(hist, np.float32), pack(centroid, np.float64),
            pack(extent, np.float64), obs, pack(kf, np.int64))


OBJECT_COLUMNS = ("o.id, o.node_id, o.class_id, o.label, o.confidence, o.histogram, o.centroid, o.extent, "
                   "o.observations, o.keyframes, n.pose")


def object_from_row(row) -> ObjectRecord:
    hist = unpack(row[5], np.float32, (len(row[5]) // 4,))
    centroid = unpack(row[6], np.float64, (3,))
    pose = unpack(row[10], np.float64, (4, 4))
    return ObjectRecord(row[0], row[1], row[2], row[3], row[4], hist, centroid, unpack(row[7], np.float64, (3,)),
                        row[8], unpack(row[9], np.int64, (len(row[9]) // 8,)), pose[:3, :3] @ centroid + pose[:3, 3])
