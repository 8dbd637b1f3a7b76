"""Records and validation of the long-term memory: what goes in and comes out of the
database and how it is encoded. Owns the errors (`StoreError`, `UnknownIdError`),
`LinkType` and its names (`LINK_NAMES`, `link_name`), the record dataclasses, the array /
JSON / calibration encodings, the checks every write makes before touching the database,
and the row decoders of the read side.
The underscore helpers are the storage package's own (its other modules use them); nothing
outside `storage` should.

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
from enum import IntEnum

import numpy as np

from mnemoslam.client.kernel.frames import Calibration, PinholeCamera


class StoreError(Exception):
    """The database cannot do what was asked: missing or foreign file, newer schema,
    unknown id, constraint violation, locked or full disk. The message says which."""


class UnknownIdError(StoreError, KeyError):
    """A node or session id that is not in the database."""

    __str__ = Exception.__str__  # KeyError would quote the message


class LinkType(IntEnum):
    """RTAB-Map's Link.type values. Outside the database a type goes by its `label`
    (`LINK_NAMES`): REST, metrics, events, the viewer and the evaluation reports all use it."""

    NEIGHBOR = 0  # odometry between consecutive nodes
    GLOBAL_CLOSURE = 1  # appearance-based loop closure
    LOCAL_SPACE = 2  # proximity by space
    LOCAL_TIME = 3  # proximity by time: along the own path
    USER = 4  # user-added
    VIRTUAL = 5
    NEIGHBOR_MERGED = 6  # odometry across a node removed from the graph
    POSE_PRIOR = 7
    LANDMARK = 8
    MERGED = 10  # rehearsal: T_survivor_merged, from the node a keyframe was merged into (not RTAB-Map's)

    @property
    def label(self) -> str:
        """The type's public name (`LINK_NAMES`)."""
        return LINK_NAMES[self]

    @classmethod
    def from_label(cls, label: str) -> LinkType:
        """The type named `label` (`LINK_NAMES`); ValueError for an unknown name."""
        for t, name in LINK_NAMES.items():
            if name == label:
                return t
        raise ValueError(f"unknown link type {label!r} (one of {', '.join(LINK_NAMES.values())})")


# The one table of link-type names, one name per type: REST (graph links, database
# links_by_type), metrics (loop_closures_total{link}), the `loop_closed` event's `link`, the
# viewer and the evaluation reports (links.csv / links.json) all name a type by it.
LINK_NAMES: dict[LinkType, str] = {
    LinkType.NEIGHBOR: "odometry",  # between consecutive keyframes
    LinkType.GLOBAL_CLOSURE: "loop",  # loop closure by appearance
    LinkType.LOCAL_SPACE: "proximity",  # proximity by space
    LinkType.LOCAL_TIME: "path",  # proximity by time, along the own path
    LinkType.USER: "user",
    LinkType.VIRTUAL: "virtual",
    LinkType.NEIGHBOR_MERGED: "odometry_merged",
    LinkType.POSE_PRIOR: "pose_prior",
    LinkType.LANDMARK: "landmark",
    LinkType.MERGED: "merged",  # rehearsal's survivor -> merged keyframe
}
assert set(LINK_NAMES) == set(LinkType) and len(set(LINK_NAMES.values())) == len(LINK_NAMES)


def link_name(t: int) -> str:
    """The public name of link type `t` (`LINK_NAMES`); a type not in `LinkType` by its number."""
    try:
        return LINK_NAMES[LinkType(t)]
    except ValueError:
        return str(int(t))


# -- records --------------------------------------------------------------------------------


@dataclass
class SessionRecord:
    id: int
    robot: str
    map_id: int
    started_at: float  # wall time, seconds since the epoch
    ended_at: float | None
    calibration: Calibration
    config: dict | None
    # "stopped" (normal end), "idle", "restarted" (a camera restart), "crashed" (found open at
    # start-up), None while running
    end_reason: str | None = None

    def to_dict(self) -> dict:
        d = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        d["calibration"] = _calibration_to_dict(self.calibration)
        return d


@dataclass
class NodeRecord:
    id: int
    session_id: int
    robot: str
    stamp: float
    pose: np.ndarray  # 4×4 float64 camera-to-world
    weight: int
    label: str | None
    merged_into: int | None = None  # the node rehearsal merged this keyframe into (None: a map node)

    @property
    def position(self) -> np.ndarray:
        return self.pose[:3, 3]


@dataclass
class LinkRecord:
    from_id: int
    to_id: int
    type: LinkType
    transform: np.ndarray  # 4×4 float64 T_from_to
    information: np.ndarray  # 6×6 float64


@dataclass
class KeyframeRecord:
    """Everything `add_keyframe` writes for one keyframe, in one transaction."""

    session_id: int
    stamp: float
    pose: np.ndarray  # 4×4 camera-to-world
    keypoints: np.ndarray  # (N, 2) float32
    descriptors: np.ndarray  # (N, 32) uint8
    points: np.ndarray  # (N, 3) float32, NaN rows = no depth
    weight: int = 0
    image_jpeg: bytes | None = None
    depth_png: bytes | None = None  # PNG-16, millimetres
    odom_link: tuple | None = None  # (from_id, T_from_to 4×4, information 6×6 | None)
    statistics: dict | None = None
    word_ids: np.ndarray | None = None  # (N,) int32, visual words of the features


@dataclass
class ObjectRecord:
    """A 3-D object of the semantic map (table `objects`). `centroid` is in the anchor
    node's camera frame; `position` (world, = anchor pose @ centroid) is filled by the
    reads and ignored by writes. `id` None = a new object (`save_objects` inserts it)."""

    id: int | None
    node_id: int  # anchor keyframe
    class_id: int  # argmax of `histogram`
    label: str  # the class's name
    confidence: float  # histogram[class_id]
    histogram: np.ndarray  # (K,) float32 posterior over the classes
    centroid: np.ndarray  # (3,) float64, anchor node's camera frame
    extent: np.ndarray  # (3,) float64 axis-aligned size in the map frame (m)
    observations: int  # keyframes that observed it
    keyframes: np.ndarray  # (≤ 64,) int64 ids of the most recent observing keyframes
    position: np.ndarray | None = None  # (3,) world position, read side only


#: How many observing keyframe ids an object keeps (the most recent).
MAX_OBJECT_KEYFRAMES = 64


# -- array encoding -------------------------------------------------------------------------


def _pack(arr: np.ndarray, dtype) -> bytes:
    """Raw little-endian bytes of `arr` as `dtype` (C order)."""
    return np.ascontiguousarray(arr, dtype=np.dtype(dtype).newbyteorder("<")).tobytes()


def _unpack(blob: bytes, dtype, shape: tuple[int, ...]) -> np.ndarray:
    """The array `_pack` wrote: a writable, native-order copy of shape `shape`."""
    le = np.dtype(dtype).newbyteorder("<")
    n = int(np.prod(shape)) * le.itemsize
    if blob is None or len(blob) != n:
        got = "NULL" if blob is None else f"{len(blob)} bytes"
        raise StoreError(f"corrupt blob: expected {n} bytes for {shape} {np.dtype(dtype).name}, got {got}")
    return np.frombuffer(blob, le).reshape(shape).astype(np.dtype(dtype), copy=True)


# -- validation (all before any write) ------------------------------------------------------


def _as_int(v, what: str) -> int:
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)):
        raise ValueError(f"{what} must be an integer, got {type(v).__name__}")
    return int(v)


def _as_float(v, what: str) -> float:
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.integer, np.floating)):
        raise ValueError(f"{what} must be a number, got {type(v).__name__}")
    f = float(v)
    if not math.isfinite(f):
        raise ValueError(f"{what} must be finite, got {f}")
    return f


def _matrix(m, shape: tuple[int, int], what: str) -> np.ndarray:
    a = np.asarray(m)
    if a.dtype.kind not in "fiu":
        raise ValueError(f"{what} must be a real {shape[0]}×{shape[1]} matrix, got dtype {a.dtype}")
    if a.shape != shape:
        raise ValueError(f"{what} must be {shape[0]}×{shape[1]}, got shape {a.shape}")
    a = a.astype(np.float64)
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{what} has non-finite values")
    return a


def _rigid(m, what: str) -> np.ndarray:
    a = _matrix(m, (4, 4), what)
    if np.abs(a[3] - (0.0, 0.0, 0.0, 1.0)).max() > 1e-6:
        raise ValueError(f"{what} is not a homogeneous transform (last row {a[3].tolist()})")
    return a


def _features_array(a, what: str, dtype, cols: int | None) -> np.ndarray:
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


def _word_ids(a, what: str, lowest: int) -> np.ndarray:
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


def _image_bytes(b, what: str, magic: bytes, kind: str) -> bytes | None:
    if b is None:
        return None
    if not isinstance(b, (bytes, bytearray, memoryview)):
        raise ValueError(f"{what} must be {kind} bytes, got {type(b).__name__}")
    b = bytes(b)
    if not b.startswith(magic):
        raise ValueError(f"{what} is not {kind} data (starts with {b[:8]!r})")
    return b


def _jsonable(obj, what: str):
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
        return _jsonable(obj.tolist(), what)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return _jsonable(dataclasses.asdict(obj), what)
    if isinstance(obj, Mapping):
        out = {}
        for k, v in obj.items():
            if not isinstance(k, (str, int)) or isinstance(k, bool):
                raise ValueError(f"{what}: key {k!r} is not a string")
            out[str(k)] = _jsonable(v, f"{what}[{k!r}]")
        return out
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v, f"{what}[{i}]") for i, v in enumerate(obj)]
    raise ValueError(f"{what}: {type(obj).__name__} is not JSON-encodable")


def _to_json(obj, what: str) -> str | None:
    return None if obj is None else json.dumps(_jsonable(obj, what), separators=(",", ":"))


def _calibration_to_dict(c: Calibration) -> dict:
    cam = c.camera
    return {"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy, "width": cam.width,
            "height": cam.height, "baseline": c.baseline, "depth_scale": c.depth_scale}


def _calibration_from_dict(d: dict) -> Calibration:
    cam = PinholeCamera(float(d["fx"]), float(d["fy"]), float(d["cx"]), float(d["cy"]),
                        int(d["width"]), int(d["height"]))
    return Calibration(cam, None if d.get("baseline") is None else float(d["baseline"]),
                       float(d.get("depth_scale", 1000.0)))


@dataclass
class _PreparedKeyframe:
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


def _prepare_keyframe(rec: KeyframeRecord) -> _PreparedKeyframe:
    if not isinstance(rec, KeyframeRecord):
        raise ValueError(f"add_keyframe needs a KeyframeRecord, got {type(rec).__name__}")
    pose = _rigid(rec.pose, "pose")
    kp = _features_array(rec.keypoints, "keypoints", np.float32, 2)
    desc = _features_array(rec.descriptors, "descriptors", np.uint8, 32)
    pts = _features_array(rec.points, "points", np.float32, 3)
    n = len(kp)
    if len(desc) != n or len(pts) != n:
        raise ValueError(f"feature counts differ: {n} keypoints, {len(desc)} descriptors, {len(pts)} points")
    wid = None
    if rec.word_ids is not None:
        wid = _features_array(rec.word_ids, "word_ids", np.int32, None)
        if len(wid) != n:
            raise ValueError(f"{len(wid)} word_ids for {n} keypoints")
    link = None
    if rec.odom_link is not None:
        if not isinstance(rec.odom_link, (tuple, list)) or len(rec.odom_link) not in (2, 3):
            raise ValueError("odom_link must be (from_id, transform 4×4, information 6×6 | None)")
        from_id = _as_int(rec.odom_link[0], "odom_link from_id")
        T = _rigid(rec.odom_link[1], "odom_link transform")
        info = rec.odom_link[2] if len(rec.odom_link) == 3 else None
        info = np.eye(6) if info is None else _matrix(info, (6, 6), "odom_link information")
        link = (from_id, _pack(T, np.float64), _pack(info, np.float64))
    if rec.statistics is not None and not isinstance(rec.statistics, Mapping):
        raise ValueError(f"statistics must be a dict, got {type(rec.statistics).__name__}")
    return _PreparedKeyframe(
        session_id=_as_int(rec.session_id, "session_id"),
        stamp=_as_float(rec.stamp, "stamp"),
        pose=_pack(pose, np.float64),
        xyz=(float(pose[0, 3]), float(pose[1, 3]), float(pose[2, 3])),
        weight=_as_int(rec.weight, "weight"),
        count=n,
        keypoints=_pack(kp, np.float32),
        descriptors=_pack(desc, np.uint8),
        points=_pack(pts, np.float32),
        word_ids=None if wid is None else _pack(wid, np.int32),
        color=_image_bytes(rec.image_jpeg, "image_jpeg", _JPEG_MAGIC, "JPEG"),
        depth=_image_bytes(rec.depth_png, "depth_png", _PNG_MAGIC, "PNG"),
        link=link,
        statistics=_to_json(rec.statistics, "statistics"),
    )


def _bbox(bbox) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    try:
        lo, hi = bbox
        lo = tuple(_as_float(v, "bbox") for v in lo)
        hi = tuple(_as_float(v, "bbox") for v in hi)
    except (TypeError, ValueError) as e:
        raise ValueError(f"bbox must be ((xmin, ymin, zmin), (xmax, ymax, zmax)) of finite numbers: {e}") from None
    if len(lo) != 3 or len(hi) != 3:
        raise ValueError("bbox must be ((xmin, ymin, zmin), (xmax, ymax, zmax))")
    if any(a > b for a, b in zip(lo, hi)):
        raise ValueError(f"bbox min {lo} exceeds max {hi}")
    return lo, hi


_NODE_COLUMNS = "n.id, n.session_id, n.robot, n.stamp, n.pose, n.weight, n.label, n.merged_into"


def _node(row) -> NodeRecord:
    return NodeRecord(row[0], row[1], row[2], row[3], _unpack(row[4], np.float64, (4, 4)), row[5], row[6], row[7])


def _link(row) -> LinkRecord:
    t = row[2]
    try:
        t = LinkType(t)
    except ValueError:
        pass
    return LinkRecord(row[0], row[1], t, _unpack(row[3], np.float64, (4, 4)), _unpack(row[4], np.float64, (6, 6)))


def _end_reason(reason) -> str:
    if not isinstance(reason, str) or not reason.strip():
        raise ValueError(f"end reason must be a non-empty string, got {reason!r}")
    return reason


def _session(row) -> SessionRecord:
    return SessionRecord(row[0], row[1], row[2], row[3], row[4], _calibration_from_dict(json.loads(row[5])),
                         None if row[6] is None else json.loads(row[6]), row[7])


_SESSION_COLUMNS = "id, robot, map_id, started_at, ended_at, calibration, config, end_reason"

#: Link types the map update (service.mapping.mapper.Mapper) writes; each goes *to* the keyframe being updated.
MAP_UPDATE_LINKS = (LinkType.GLOBAL_CLOSURE, LinkType.LOCAL_SPACE, LinkType.LOCAL_TIME)


# -- objects (v4) ---------------------------------------------------------------------------


def _vector(v, n: int | None, what: str, dtype=np.float64) -> np.ndarray:
    a = np.asarray(v)
    if a.dtype.kind not in "fiu":
        raise ValueError(f"{what} must be real numbers, got dtype {a.dtype}")
    if a.ndim != 1 or (n is not None and a.shape[0] != n):
        raise ValueError(f"{what} must have shape ({n if n is not None else 'K'},), got {a.shape}")
    a = a.astype(dtype)
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{what} has non-finite values")
    return a


def _prepare_object(o: ObjectRecord) -> tuple:
    """Checked, encoded columns of an object: (id | None, node_id, class_id, label, confidence,
    histogram, centroid, extent, observations, keyframes). ValueError names what is wrong."""
    if not isinstance(o, ObjectRecord):
        raise ValueError(f"expected an ObjectRecord, got {type(o).__name__}")
    oid = None if o.id is None else _as_int(o.id, "object id")
    node = _as_int(o.node_id, "object node_id")
    hist = _vector(o.histogram, None, "object histogram", np.float32)
    if hist.shape[0] < 1 or (hist < 0).any():
        raise ValueError("object histogram must be non-empty and non-negative")
    cls = _as_int(o.class_id, "object class_id")
    if not 0 <= cls < hist.shape[0]:
        raise ValueError(f"object class_id {cls} is outside the histogram's {hist.shape[0]} classes")
    if not isinstance(o.label, str) or not o.label.strip():
        raise ValueError(f"object label must be a non-empty string, got {o.label!r}")
    conf = _as_float(o.confidence, "object confidence")
    if not 0.0 <= conf <= 1.0:
        raise ValueError(f"object confidence must be in [0, 1], got {conf}")
    centroid = _vector(o.centroid, 3, "object centroid")
    extent = _vector(o.extent, 3, "object extent")
    if (extent < 0).any():
        raise ValueError(f"object extent must be non-negative, got {extent.tolist()}")
    obs = _as_int(o.observations, "object observations")
    if obs < 0:
        raise ValueError(f"object observations must be ≥ 0, got {obs}")
    kf = np.asarray([] if o.keyframes is None else o.keyframes)
    if kf.ndim != 1 or (kf.size and kf.dtype.kind not in "iu"):
        raise ValueError(f"object keyframes must be a 1-D array of node ids, got shape {kf.shape} {kf.dtype}")
    kf = kf.astype(np.int64)[-MAX_OBJECT_KEYFRAMES:]
    return (oid, node, cls, o.label, conf, _pack(hist, np.float32), _pack(centroid, np.float64),
            _pack(extent, np.float64), obs, _pack(kf, np.int64))


_OBJECT_COLUMNS = ("o.id, o.node_id, o.class_id, o.label, o.confidence, o.histogram, o.centroid, o.extent, "
                   "o.observations, o.keyframes, n.pose")


def _object(row) -> ObjectRecord:
    hist = _unpack(row[5], np.float32, (len(row[5]) // 4,))
    centroid = _unpack(row[6], np.float64, (3,))
    pose = _unpack(row[10], np.float64, (4, 4))
    return ObjectRecord(row[0], row[1], row[2], row[3], row[4], hist, centroid, _unpack(row[7], np.float64, (3,)),
                        row[8], _unpack(row[9], np.int64, (len(row[9]) // 8,)), pose[:3, :3] @ centroid + pose[:3, 3])
