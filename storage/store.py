"""`MapStore`: the SQLite long-term memory (LTM) of the map.

One file holds every session of every robot (RTAB-Map's multi-session database). Encodings:

- poses: 4×4 float64 camera-to-world, row-major, little-endian (128 bytes); the node's
  position is also in the `x, y, z` columns for spatial queries (R*Tree when available).
- links: `transform` = T_from_to 4×4 float64 (pose_to = pose_from @ T), `information` 6×6
  float64; `type` uses RTAB-Map's values (`LinkType`).
- features: `count` = N, `keypoints` N×2 float32 pixels, `descriptors` N×32 uint8 (ORB),
  `points` N×3 float32 camera frame (NaN rows = no depth), `word_ids` N int32 or NULL
  (-1 = no word).
- words: `descriptor` 32 bytes (ORB, 256 bits) of each visual word; a node's word ids and
  the words created for it are written in one transaction (`save_node_words`), so every
  word id ≥ 0 in `features.word_ids` is in `words` (until the word is deleted).
- images: JPEG colour, PNG-16 depth in millimetres (both optional).
- JSON text for session calibration / config and per-node statistics.
- sessions: `ended_at` (wall time) and `end_reason` once ended: "stopped" for a normal
  end, "crashed" for one the service found still open when it started again.
- statistics: the map update's (service.mapping) last write for a keyframe, after its words,
  links and poses: a node without a statistics row has not been through the map update.

Durability: WAL journal with synchronous=NORMAL. A transaction is durable against a
process crash (kill -9) once COMMIT returns; `add_keyframe` returns only after COMMIT, so
a reported node id is always in the file. (A power loss may drop the last few commits but
never corrupts the file.)

Threads: every method may be called from any thread. Writes go through one connection
behind a lock, each in one `BEGIN IMMEDIATE` transaction; reads use a pool of separate
connections, so in WAL mode they never wait for a writer and see the last committed state.
WAL checkpoints (copying the WAL into the database file, with its fsyncs) run in a
background thread instead of inside a commit, which keeps add_keyframe's p99 near its
median; when writes outpace it, it briefly holds the writer off so the WAL stays bounded
(~16 MB). Other processes may open the same file (e.g. `mnemoslam db info` while the
service runs): writers then queue on SQLite's lock for up to `busy_timeout` seconds.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import math
import sqlite3
import threading
import time
from collections.abc import Iterable, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from enum import IntEnum
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import sqlite_utils

from client.frames import Calibration, PinholeCamera
from client.trajectory import Trajectory, format_tum

from . import schema

log = logging.getLogger("mnemoslam.storage")


class StoreError(Exception):
    """The database cannot do what was asked: missing or foreign file, newer schema,
    unknown id, constraint violation, locked or full disk. The message says which."""


class UnknownIdError(StoreError, KeyError):
    """A node or session id that is not in the database."""

    __str__ = Exception.__str__  # KeyError would quote the message


class LinkType(IntEnum):
    """RTAB-Map's Link.type values."""

    NEIGHBOR = 0  # odometry between consecutive nodes
    GLOBAL_CLOSURE = 1  # appearance-based loop closure
    LOCAL_SPACE = 2  # proximity by space
    LOCAL_TIME = 3  # proximity by time
    USER = 4  # user-added
    VIRTUAL = 5
    NEIGHBOR_MERGED = 6
    POSE_PRIOR = 7
    LANDMARK = 8
    MERGED = 10  # rehearsal: T_survivor_merged, from the node a keyframe was merged into (not RTAB-Map's)


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
    end_reason: str | None = None  # "stopped" (normal end), "crashed" (found open at start-up), None while running

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


def _link_name(t: int) -> str:
    try:
        return LinkType(t).name.lower()
    except ValueError:
        return str(t)


def _end_reason(reason) -> str:
    if not isinstance(reason, str) or not reason.strip():
        raise ValueError(f"end reason must be a non-empty string, got {reason!r}")
    return reason


def _session(row) -> SessionRecord:
    return SessionRecord(row[0], row[1], row[2], row[3], row[4], _calibration_from_dict(json.loads(row[5])),
                         None if row[6] is None else json.loads(row[6]), row[7])


_SESSION_COLUMNS = "id, robot, map_id, started_at, ended_at, calibration, config, end_reason"

#: Link types the map update (service.mapping.Mapper) writes; each goes *to* the keyframe being updated.
MAP_UPDATE_LINKS = (LinkType.GLOBAL_CLOSURE, LinkType.LOCAL_SPACE, LinkType.LOCAL_TIME)


# -- the store ------------------------------------------------------------------------------


class MapStore:
    """The long-term memory in one SQLite file. See the module docstring for the encodings,
    durability and threading guarantees."""

    #: MIGRATIONS[i] upgrades schema version i to i + 1; the current version is their count.
    MIGRATIONS: tuple = schema.MIGRATIONS

    def __init__(self, path: str | Path, *, create: bool = True, busy_timeout: float = 10.0):
        if str(path) in ("", ":memory:") or str(path).startswith("file:"):
            raise ValueError(f"MapStore needs a file path, got {str(path)!r}")
        self.path = Path(path)
        self.busy_timeout = float(busy_timeout)
        if self.path.is_dir():
            raise StoreError(f"{self.path} is a directory, not a database file")
        if not create and not self.path.exists():
            raise StoreError(f"no database at {self.path}")
        if create:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lock = threading.RLock()  # the writer connection
        self._pool_lock = threading.Lock()
        self._idle: list[sqlite3.Connection] = []
        self._closed = False
        self._commits = 0  # since the last checkpoint
        self._checkpoint_wake = threading.Event()
        self._checkpointer: threading.Thread | None = None
        self._writer = self._connect("rwc" if create else "rw")
        try:
            self._configure_writer()
            self.db = sqlite_utils.Database(self._writer, execute_plugins=False)
            self._migrate(create)
            self._rtree = self._writer.execute(
                "SELECT 1 FROM sqlite_master WHERE name = 'nodes_rtree'").fetchone() is not None
            if self._rtree and not schema.has_rtree(self._writer):
                raise StoreError(f"{self.path} uses an R*Tree index but this SQLite build has no R*Tree module")
        except BaseException:
            self._closed = True
            self._writer.close()
            raise
        if self._wal:
            self._checkpointer = threading.Thread(target=self._checkpoint_loop, daemon=True,
                                                  name=f"mnemoslam-checkpoint-{self.path.name}")
            self._checkpointer.start()

    # -- connections ------------------------------------------------------------------------
    def _connect(self, mode: str) -> sqlite3.Connection:
        uri = self.path.resolve().as_uri() + f"?mode={mode}"
        try:
            conn = sqlite3.connect(uri, uri=True, timeout=self.busy_timeout, isolation_level=None,
                                   check_same_thread=False)
        except sqlite3.Error as e:
            raise StoreError(f"cannot open database {self.path}: {e}") from e
        try:
            conn.execute("PRAGMA foreign_keys = ON")
            conn.execute("PRAGMA synchronous = NORMAL")
        except sqlite3.DatabaseError as e:
            conn.close()
            raise StoreError(f"{self.path} is not a SQLite database ({e})") from e
        return conn

    def _configure_writer(self) -> None:
        try:
            mode = self._writer.execute("PRAGMA journal_mode = WAL").fetchone()[0]
            self._writer.execute("PRAGMA journal_size_limit = 67108864")  # truncate the WAL to 64 MB after checkpoints
        except sqlite3.DatabaseError as e:
            raise StoreError(f"{self.path} is not a SQLite database ({e})") from e
        self._wal = mode.lower() == "wal"
        if self._wal:
            # Checkpoints (WAL -> database file, with fsyncs) run in a background thread so a
            # commit never pays for one: p99 of add_keyframe drops from ~7 ms to < 1 ms.
            self._writer.execute("PRAGMA wal_autocheckpoint = 0")
        else:
            log.warning("%s: journal_mode is %s, not WAL (file system without shared memory?): "
                        "readers will wait for writers", self.path, mode)

    _CHECKPOINT_COMMITS = 32  # wake the checkpointer after this many commits
    _CHECKPOINT_PERIOD = 2.0  # seconds; and at least this often when there were commits
    _WAL_PAGES = 4096  # WAL size (pages, 16 MB at 4 kB) past which a checkpoint briefly holds the writer

    def _checkpoint_loop(self) -> None:
        try:
            conn = self._connect("rw")
        except StoreError as e:  # pragma: no cover - the writer opened the same file
            log.warning("checkpointer not started: %s; falling back to automatic checkpoints", e)
            with self._lock:
                if not self._closed:
                    self._writer.execute("PRAGMA wal_autocheckpoint = 1000")
            return
        try:
            while True:
                self._checkpoint_wake.wait(self._CHECKPOINT_PERIOD)
                self._checkpoint_wake.clear()
                if self._closed:
                    return
                if self._commits == 0:
                    continue
                self._commits = 0
                try:
                    # PASSIVE: copies what is committed, never waits for (nor blocks) the
                    # writer or readers.
                    (_, wal_pages, _), = conn.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchall()
                    if wal_pages > self._WAL_PAGES:
                        # The WAL restarts from its beginning only when a write starts after a
                        # checkpoint has caught up with it, which never happens under
                        # continuous writes. Catch up without the lock while that shrinks the
                        # tail, then finish the rest with the writer held off, so the WAL
                        # stays bounded.
                        for _ in range(4):
                            (_, now, _), = conn.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchall()
                            tail, wal_pages = now - wal_pages, now
                            if tail < 256:
                                break
                        with self._lock:
                            if self._closed:
                                return
                            conn.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchall()
                except sqlite3.Error as e:
                    log.warning("%s: WAL checkpoint failed: %s", self.path, e)
        finally:
            conn.close()

    def checkpoint(self) -> tuple[int, int]:
        """Copy the whole WAL into the database file now, holding writers off meanwhile, so
        the next write restarts the WAL from its beginning. The background checkpointer
        normally does this; returns (WAL pages, pages checkpointed)."""
        deadline = time.monotonic() + self.busy_timeout
        with self._lock:
            self._check_open()
            try:
                while True:
                    (busy, pages, done), = self._writer.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchall()
                    if not busy or time.monotonic() > deadline:
                        break
                    time.sleep(0.002)  # another checkpoint (the background one) is running
            except sqlite3.Error as e:
                raise StoreError(f"checkpoint of {self.path}: {e}") from e
        if busy:
            raise StoreError(f"checkpoint of {self.path}: another checkpoint kept running for {self.busy_timeout:g} s")
        return pages, done

    def _check_open(self) -> None:
        if self._closed:
            raise StoreError(f"the store {self.path} is closed")

    @contextmanager
    def _write(self, what: str) -> Iterator[sqlite3.Connection]:
        """One write transaction (BEGIN IMMEDIATE … COMMIT) on the writer connection; rolled
        back on any exception. sqlite3 errors come out as StoreError."""
        with self._lock:
            self._check_open()
            conn = self._writer
            try:
                conn.execute("BEGIN IMMEDIATE")
            except sqlite3.Error as e:
                raise StoreError(f"{what}: cannot start a write transaction on {self.path}: {e}") from e
            try:
                yield conn
                conn.execute("COMMIT")
                self._commits += 1
                if self._commits >= self._CHECKPOINT_COMMITS:
                    self._checkpoint_wake.set()
            except BaseException as e:
                if conn.in_transaction:
                    conn.execute("ROLLBACK")
                if isinstance(e, sqlite3.Error):
                    raise StoreError(f"{what}: {e}") from e
                raise

    @contextmanager
    def _read(self, snapshot: bool = False) -> Iterator[sqlite3.Connection]:
        """A pooled read connection; with `snapshot`, all its queries see one committed state."""
        self._check_open()
        with self._pool_lock:
            conn = self._idle.pop() if self._idle else None
        if conn is None:
            conn = self._connect("rw")
            conn.execute("PRAGMA query_only = ON")
        try:
            if snapshot:
                conn.execute("BEGIN")
            yield conn
        except sqlite3.Error as e:
            raise StoreError(f"reading {self.path}: {e}") from e
        finally:
            if conn.in_transaction:
                conn.execute("COMMIT")
            with self._pool_lock:
                if self._closed:
                    conn.close()
                else:
                    self._idle.append(conn)

    def close(self) -> None:
        """Close every connection (idempotent). In-flight reads finish on their own. The
        last connection to close checkpoints the WAL into the database file."""
        with self._lock:
            if self._closed:
                return
            self._closed = True  # from here on no write starts and no read connection is lent
        if self._checkpointer is not None:  # (outside the lock: the checkpointer may want it)
            self._checkpoint_wake.set()
            self._checkpointer.join(10)
        with self._lock:
            with self._pool_lock:
                idle, self._idle = self._idle, []
            for c in idle:
                c.close()
            try:
                self._writer.execute("PRAGMA optimize")
            except sqlite3.Error:
                pass
            self._writer.close()

    @property
    def closed(self) -> bool:
        return self._closed

    def __enter__(self) -> "MapStore":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"MapStore({str(self.path)!r}{', closed' if self._closed else ''})"

    # -- schema -----------------------------------------------------------------------------
    @property
    def current_version(self) -> int:
        """The schema version this code writes (the number of migrations)."""
        return len(self.MIGRATIONS)

    @property
    def schema_version(self) -> int:
        """The schema version stored in the file."""
        with self._read() as c:
            return c.execute("PRAGMA user_version").fetchone()[0]

    def _migrate(self, create: bool) -> None:
        target = self.current_version
        c = self._writer
        try:
            version = c.execute("PRAGMA user_version").fetchone()[0]
            tables = [r[0] for r in c.execute(
                "SELECT name FROM sqlite_master WHERE type = 'table' AND name NOT LIKE 'sqlite_%'")]
        except sqlite3.DatabaseError as e:
            raise StoreError(f"{self.path} is not a SQLite database ({e})") from e
        if version > target:
            raise StoreError(self._newer_message(version))
        if version == 0:
            if tables:
                raise StoreError(f"{self.path} is not a mnemoslam database (it has tables {', '.join(sorted(tables)[:5])} "
                                 "but no mnemoslam schema version)")
            if not create:
                raise StoreError(f"{self.path} is not a mnemoslam database (no schema)")
        while True:
            with self._write("schema migration") as c:
                # Re-read under the write lock: another process may have migrated meanwhile.
                version = c.execute("PRAGMA user_version").fetchone()[0]
                if version > target:
                    raise StoreError(self._newer_message(version))
                if version == target:
                    break
                log.info("%s: migrating schema v%d -> v%d (%s)", self.path, version, version + 1,
                         getattr(self.MIGRATIONS[version], "__name__", "migration"))
                self.MIGRATIONS[version](self.db)
                c.execute(f"PRAGMA user_version = {version + 1}")
                c.execute("INSERT OR REPLACE INTO admin (key, value) VALUES ('schema_version', ?)",
                          (json.dumps(version + 1),))
                if version == 0:
                    c.execute("INSERT OR REPLACE INTO admin (key, value) VALUES ('created_at', ?)",
                              (json.dumps(time.time()),))

    def _newer_message(self, version: int) -> str:
        return (f"{self.path} has schema version {version}, newer than this mnemoslam knows "
                f"(up to {self.current_version}): upgrade mnemoslam to open it")

    def get_info(self, key: str, default: Any = None) -> Any:
        """A value of the `admin` key-value table (JSON-decoded)."""
        with self._read() as c:
            row = c.execute("SELECT value FROM admin WHERE key = ?", (key,)).fetchone()
        return default if row is None or row[0] is None else json.loads(row[0])

    def set_info(self, key: str, value: Any) -> None:
        """Store a JSON-encodable value in the `admin` key-value table."""
        if not isinstance(key, str) or not key:
            raise ValueError("info key must be a non-empty string")
        text = _to_json(value, f"info[{key!r}]")
        with self._write("set_info") as c:
            c.execute("INSERT OR REPLACE INTO admin (key, value) VALUES (?, ?)", (key, text))

    # -- sessions ---------------------------------------------------------------------------
    def begin_session(self, robot: str, calibration: Calibration, config: dict | None = None) -> int:
        """Start a session (a new map id, RTAB-Map's multi-session) and return its id."""
        if not isinstance(robot, str) or not robot.strip():
            raise ValueError(f"robot must be a non-empty string, got {robot!r}")
        if not isinstance(calibration, Calibration):
            raise ValueError(f"calibration must be a client.frames.Calibration, got {type(calibration).__name__}")
        if config is not None and not (isinstance(config, Mapping) or dataclasses.is_dataclass(config)):
            raise ValueError(f"config must be a dict, got {type(config).__name__}")
        calib = _to_json(_calibration_to_dict(calibration), "calibration")
        conf = _to_json(config, "config")
        with self._write("begin_session") as c:
            map_id = c.execute("SELECT COALESCE(MAX(map_id) + 1, 0) FROM sessions").fetchone()[0]
            cur = c.execute(
                "INSERT INTO sessions (robot, map_id, started_at, calibration, config) VALUES (?, ?, ?, ?, ?)",
                (robot, map_id, time.time(), calib, conf))
            return cur.lastrowid

    def end_session(self, session_id: int, reason: str = "stopped") -> None:
        """Mark a session ended, with why ("stopped" = a normal end); its first end time and
        reason are kept. It takes no more keyframes."""
        sid = _as_int(session_id, "session_id")
        why = _end_reason(reason)
        with self._write("end_session") as c:
            cur = c.execute("UPDATE sessions SET ended_at = COALESCE(ended_at, ?), "
                            "end_reason = CASE WHEN ended_at IS NULL THEN ? ELSE end_reason END WHERE id = ?",
                            (time.time(), why, sid))
            if cur.rowcount == 0:
                raise UnknownIdError(f"no session {sid}")

    def end_open_sessions(self, reason: str = "crashed") -> list[SessionRecord]:
        """End every session that has not ended, with `reason`, in one transaction, and return
        them as ended. For the sessions a killed service left open: their end time is their last
        keyframe's (when it was stored), or their start without keyframes."""
        why = _end_reason(reason)
        with self._write("end_open_sessions") as c:
            ids = [r[0] for r in c.execute("SELECT id FROM sessions WHERE ended_at IS NULL ORDER BY id")]
            if ids:
                c.execute("UPDATE sessions SET end_reason = ?, ended_at = COALESCE("
                          "(SELECT MAX(n.time_enter) FROM nodes n WHERE n.session_id = sessions.id), started_at) "
                          "WHERE ended_at IS NULL", (why,))
                q = ",".join("?" * len(ids))
                rows = c.execute(f"SELECT {_SESSION_COLUMNS} FROM sessions WHERE id IN ({q}) ORDER BY id", ids).fetchall()
            else:
                rows = []
        return [_session(r) for r in rows]

    def unmapped_nodes(self, session_ids: Iterable[int] | None = None,
                       end_reason: str | None = None) -> dict[int, list[int]]:
        """{session id: [node ids ascending]} of the keyframes that have no map update yet: no
        `statistics` row, which the map update (service.mapping.Mapper) writes last, after the
        keyframe's words, links and poses. Only sessions in `session_ids` and/or that ended
        with `end_reason`, when given; sessions without such keyframes are left out."""
        where, params = [], []
        if session_ids is not None:
            where.append("n.session_id IN (SELECT value FROM json_each(?))")
            params.append(json.dumps([_as_int(i, "session id") for i in session_ids]))
        if end_reason is not None:
            where.append("n.session_id IN (SELECT id FROM sessions WHERE end_reason = ?)")
            params.append(str(end_reason))
        sql = ("SELECT n.session_id, n.id FROM nodes n LEFT JOIN statistics s ON s.node_id = n.id "
               "WHERE s.node_id IS NULL" + "".join(f" AND {w}" for w in where) + " ORDER BY n.session_id, n.id")
        out: dict[int, list[int]] = {}
        with self._read() as c:
            for sid, nid in c.execute(sql, params):
                out.setdefault(sid, []).append(nid)
        return out

    def sessions(self, robot: str | None = None) -> list[SessionRecord]:
        sql, params = f"SELECT {_SESSION_COLUMNS} FROM sessions", ()
        if robot is not None:
            sql, params = sql + " WHERE robot = ?", (robot,)
        with self._read() as c:
            rows = c.execute(sql + " ORDER BY id", params).fetchall()
        return [_session(r) for r in rows]

    def session(self, session_id: int) -> SessionRecord | None:
        with self._read() as c:
            row = c.execute(f"SELECT {_SESSION_COLUMNS} FROM sessions WHERE id = ?",
                            (_as_int(session_id, "session_id"),)).fetchone()
        return None if row is None else _session(row)

    def calibration(self, session_id: int) -> Calibration:
        s = self.session(session_id)
        if s is None:
            raise UnknownIdError(f"no session {session_id}")
        return s.calibration

    # -- writes -----------------------------------------------------------------------------
    def add_keyframe(self, rec: KeyframeRecord) -> int:
        """Write node + features + images + odometry link + statistics in one transaction
        and return the node id. When this returns the keyframe is committed (durable against
        a process crash); on any error nothing of it is written."""
        k = _prepare_keyframe(rec)
        with self._write("add_keyframe") as c:
            row = c.execute("SELECT robot, ended_at FROM sessions WHERE id = ?", (k.session_id,)).fetchone()
            if row is None:
                raise UnknownIdError(f"no session {k.session_id}")
            if row[1] is not None:
                raise StoreError(f"session {k.session_id} has ended")
            node_id = c.execute(
                "INSERT INTO nodes (session_id, robot, stamp, pose, x, y, z, weight, time_enter) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (k.session_id, row[0], k.stamp, k.pose, *k.xyz, k.weight, time.time())).lastrowid
            c.execute("INSERT INTO features (node_id, count, keypoints, descriptors, points, word_ids) "
                      "VALUES (?, ?, ?, ?, ?, ?)",
                      (node_id, k.count, k.keypoints, k.descriptors, k.points, k.word_ids))
            if k.color is not None or k.depth is not None:
                c.execute("INSERT INTO images (node_id, color, depth) VALUES (?, ?, ?)", (node_id, k.color, k.depth))
            if k.link is not None:
                try:
                    c.execute("INSERT INTO links (from_id, to_id, type, transform, information) VALUES (?, ?, ?, ?, ?)",
                              (k.link[0], node_id, int(LinkType.NEIGHBOR), k.link[1], k.link[2]))
                except sqlite3.IntegrityError as e:
                    if "FOREIGN KEY" in str(e):
                        raise UnknownIdError(f"odometry link from node {k.link[0]}: no such node") from e
                    raise
            if k.statistics is not None:
                c.execute("INSERT INTO statistics (node_id, data) VALUES (?, ?)", (node_id, k.statistics))
        return node_id

    def add_link(self, from_id: int, to_id: int, type: int, transform: np.ndarray,
                 information: np.ndarray | None = None, *, replace: bool = False) -> None:
        """Add a constraint T_from_to (pose_to = pose_from @ T). `information` defaults to
        identity. An existing (from, to, type) link is an error unless `replace`."""
        a, b = _as_int(from_id, "from_id"), _as_int(to_id, "to_id")
        try:
            t = LinkType(_as_int(type, "link type"))
        except ValueError as e:
            raise ValueError(f"unknown link type {type!r} (known: {', '.join(f'{x.value} {x.name.lower()}' for x in LinkType)})") from e
        T = _pack(_rigid(transform, "transform"), np.float64)
        info = _pack(np.eye(6) if information is None else _matrix(information, (6, 6), "information"), np.float64)
        verb = "INSERT OR REPLACE" if replace else "INSERT"
        with self._write("add_link") as c:
            try:
                c.execute(f"{verb} INTO links (from_id, to_id, type, transform, information) VALUES (?, ?, ?, ?, ?)",
                          (a, b, int(t), T, info))
            except sqlite3.IntegrityError as e:
                if "FOREIGN KEY" in str(e):
                    missing = [i for i in (a, b) if c.execute("SELECT 1 FROM nodes WHERE id = ?", (i,)).fetchone() is None]
                    raise UnknownIdError(f"link {a} -> {b}: no node {', '.join(map(str, missing))}") from e
                raise StoreError(f"link {a} -> {b} of type {t.name.lower()} already exists (pass replace=True)") from e

    def merge_node(self, node_id: int, into_id: int, transform: np.ndarray, information: np.ndarray) -> int:
        """Rehearsal: keyframe `node_id` is merged into node `into_id`, which it sees from
        T_into_node (`transform`). In one transaction: the node is marked merged, a `merged`
        link into -> node keeps the transform, the survivor's weight grows by the node's + 1
        (RTAB-Map's), and the node's features and images are deleted (its row, statistics and
        the links tracking wrote stay). Returns the survivor's new weight."""
        a, b = _as_int(node_id, "node_id"), _as_int(into_id, "into_id")
        if a == b:
            raise ValueError(f"node {a} cannot be merged into itself")
        T = _pack(_rigid(transform, "transform"), np.float64)
        info = _pack(_matrix(information, (6, 6), "information"), np.float64)
        with self._write("merge_node") as c:
            rows = dict(c.execute("SELECT id, merged_into FROM nodes WHERE id IN (?, ?)", (a, b)).fetchall())
            missing = [i for i in (a, b) if i not in rows]
            if missing:
                raise UnknownIdError(f"merge {a} into {b}: no node {', '.join(map(str, missing))}")
            if rows[a] is not None or rows[b] is not None:
                raise StoreError(f"merge {a} into {b}: node {a if rows[a] is not None else b} is merged already")
            c.execute("UPDATE nodes SET weight = weight + (SELECT weight + 1 FROM nodes WHERE id = ?) WHERE id = ?", (a, b))
            c.execute("UPDATE nodes SET merged_into = ? WHERE id = ?", (b, a))
            c.execute("INSERT OR REPLACE INTO links (from_id, to_id, type, transform, information) VALUES (?, ?, ?, ?, ?)",
                      (b, a, int(LinkType.MERGED), T, info))
            c.execute("DELETE FROM features WHERE node_id = ?", (a,))
            c.execute("DELETE FROM images WHERE node_id = ?", (a,))
            return c.execute("SELECT weight FROM nodes WHERE id = ?", (b,)).fetchone()[0]

    def delete_links(self, to_ids: Iterable[int], types: Iterable[int]) -> int:
        """Delete the links of the given `types` that end at one of `to_ids`, in one
        transaction (e.g. what an interrupted map update wrote for a keyframe before it is
        redone: see `MAP_UPDATE_LINKS`). Returns the number deleted."""
        ids = json.dumps([_as_int(i, "node id") for i in to_ids])
        kinds = json.dumps([_as_int(t, "link type") for t in types])
        with self._write("delete_links") as c:
            return c.execute("DELETE FROM links WHERE to_id IN (SELECT value FROM json_each(?)) "
                             "AND type IN (SELECT value FROM json_each(?))", (ids, kinds)).rowcount

    def update_poses(self, poses: Mapping[int, np.ndarray]) -> int:
        """Set the pose (blob and x, y, z) of many nodes in one transaction, e.g. after graph
        optimisation. All or nothing: an unknown id rolls everything back. Returns the count."""
        if not isinstance(poses, Mapping):
            raise ValueError(f"update_poses needs {{node_id: 4×4 pose}}, got {type(poses).__name__}")
        rows = []
        for nid, pose in poses.items():
            p = _rigid(pose, f"pose of node {nid}")
            rows.append((_pack(p, np.float64), float(p[0, 3]), float(p[1, 3]), float(p[2, 3]), _as_int(nid, "node id")))
        if not rows:
            return 0
        with self._write("update_poses") as c:
            cur = c.executemany("UPDATE nodes SET pose = ?, x = ?, y = ?, z = ? WHERE id = ?", rows)
            if cur.rowcount != len(rows):
                missing = [r[4] for r in rows if c.execute("SELECT 1 FROM nodes WHERE id = ?", (r[4],)).fetchone() is None]
                raise UnknownIdError(f"update_poses: no node {', '.join(map(str, missing[:10]))}"
                                     f"{' …' if len(missing) > 10 else ''}; nothing updated")
        return len(rows)

    def set_label(self, node_id: int, label: str | None) -> None:
        """Name a node (unique across the database, like RTAB-Map's labels); None clears it."""
        nid = _as_int(node_id, "node_id")
        if label is not None and (not isinstance(label, str) or not label.strip()):
            raise ValueError(f"label must be a non-empty string or None, got {label!r}")
        with self._write("set_label") as c:
            try:
                cur = c.execute("UPDATE nodes SET label = ? WHERE id = ?", (label, nid))
            except sqlite3.IntegrityError as e:
                other = c.execute("SELECT id FROM nodes WHERE label = ?", (label,)).fetchone()
                raise StoreError(f"label {label!r} is already on node {other[0] if other else '?'}") from e
            if cur.rowcount == 0:
                raise UnknownIdError(f"no node {nid}")

    def set_statistics(self, node_id: int, statistics: dict) -> None:
        """Replace a node's statistics (e.g. the loop-closure decision made after it was stored)."""
        nid = _as_int(node_id, "node_id")
        if not isinstance(statistics, Mapping):
            raise ValueError(f"statistics must be a dict, got {type(statistics).__name__}")
        data = _to_json(statistics, "statistics")
        with self._write("set_statistics") as c:
            if c.execute("SELECT 1 FROM nodes WHERE id = ?", (nid,)).fetchone() is None:
                raise UnknownIdError(f"no node {nid}")
            c.execute("INSERT INTO statistics (node_id, data) VALUES (?, ?) "
                      "ON CONFLICT(node_id) DO UPDATE SET data = excluded.data", (nid, data))

    def set_word_ids(self, node_id: int, word_ids: np.ndarray | None) -> None:
        """Attach (or clear) the visual-word id of each feature of a node."""
        nid = _as_int(node_id, "node_id")
        blob = None
        if word_ids is not None:
            blob = _pack(_features_array(word_ids, "word_ids", np.int32, None), np.int32)
        with self._write("set_word_ids") as c:
            row = c.execute("SELECT count FROM features WHERE node_id = ?", (nid,)).fetchone()
            if row is None:
                raise UnknownIdError(f"no node {nid}")
            if word_ids is not None and len(word_ids) != row[0]:
                raise ValueError(f"{len(word_ids)} word_ids for the {row[0]} features of node {nid}")
            c.execute("UPDATE features SET word_ids = ? WHERE node_id = ?", (blob, nid))

    # -- visual words -----------------------------------------------------------------------
    def save_node_words(self, node_id: int, word_ids: np.ndarray, new_word_ids: np.ndarray | None = None,
                        new_descriptors: np.ndarray | None = None) -> None:
        """Attach the visual-word id of each feature of a node (-1 = no word) and store the
        words the vocabulary created for it (`new_word_ids` (M,), `new_descriptors` M×32
        uint8), in one transaction. Every id ≥ 0 in `word_ids` must then be in `words`: a
        node never points at an unsaved word, even after a kill -9. Ids are never reused: a
        word id already stored is a StoreError, and the highest id ever stored is kept
        (admin `next_word_id`) so that pruning the newest words does not free their ids."""
        nid = _as_int(node_id, "node_id")
        wid = _word_ids(word_ids, "word_ids", -1)
        if (new_word_ids is None) != (new_descriptors is None):
            raise ValueError("new_word_ids and new_descriptors go together")
        new = np.zeros(0, np.int64) if new_word_ids is None else _word_ids(new_word_ids, "new_word_ids", 0)
        desc = b""
        if new_descriptors is not None:
            d = _features_array(new_descriptors, "new_descriptors", np.uint8, 32)
            if len(d) != len(new):
                raise ValueError(f"{len(d)} new_descriptors for {len(new)} new_word_ids")
            if len(np.unique(new)) != len(new):
                raise ValueError("new_word_ids has duplicates")
            desc = _pack(d, np.uint8)
        used = np.unique(wid[wid >= 0])
        blob = _pack(wid, np.int32)
        with self._write("save_node_words") as c:
            row = c.execute("SELECT count FROM features WHERE node_id = ?", (nid,)).fetchone()
            if row is None:
                raise UnknownIdError(f"no node {nid}")
            if len(wid) != row[0]:
                raise ValueError(f"{len(wid)} word_ids for the {row[0]} features of node {nid}")
            if len(new):
                ids = json.dumps(new.tolist())
                try:
                    # One statement: word j is bytes 32j..32j+31 of the descriptor blob.
                    c.execute("INSERT INTO words (id, descriptor, time_enter) "
                              "SELECT j.value, substr(?1, 32 * j.key + 1, 32), ?2 FROM json_each(?3) j",
                              (desc, time.time(), ids))
                except sqlite3.IntegrityError as e:
                    dup = [r[0] for r in c.execute(
                        "SELECT id FROM words WHERE id IN (SELECT value FROM json_each(?)) ORDER BY id LIMIT 10", (ids,))]
                    raise StoreError(f"word id(s) {', '.join(map(str, dup))} already stored: word ids are never "
                                     "reused (two vocabularies writing to one map?); nothing written") from e
                c.execute("INSERT INTO admin (key, value) VALUES ('next_word_id', ?1) ON CONFLICT(key) DO UPDATE "
                          "SET value = MAX(CAST(value AS INTEGER), CAST(excluded.value AS INTEGER))",
                          (str(int(new.max()) + 1),))
            if len(used):
                ids = json.dumps(used.tolist())
                found = c.execute("SELECT COUNT(*) FROM words WHERE id IN (SELECT value FROM json_each(?))",
                                  (ids,)).fetchone()[0]
                if found != len(used):
                    have = {r[0] for r in c.execute(
                        "SELECT id FROM words WHERE id IN (SELECT value FROM json_each(?))", (ids,))}
                    missing = [w for w in used.tolist() if w not in have]
                    raise ValueError(f"node {nid} refers to {len(missing)} word(s) not in the map "
                                     f"({', '.join(map(str, missing[:10]))}{' …' if len(missing) > 10 else ''}): "
                                     "pass them as new_word_ids/new_descriptors; nothing written")
            c.execute("UPDATE features SET word_ids = ? WHERE node_id = ?", (blob, nid))

    def count_words(self) -> int:
        with self._read() as c:
            return c.execute("SELECT COUNT(*) FROM words").fetchone()[0]

    def load_words(self, word_ids: Iterable[int] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(ids (W,) int64 ascending, descriptors W×32 uint8) of the given (default: all)
        stored words; unknown ids are left out."""
        with self._read(snapshot=True) as c:
            if word_ids is None:
                return self._words(c)
            ids = np.unique(_word_ids(word_ids, "word_ids", 0))
            return self._words(c, json.dumps(ids.tolist()))

    _WORD_CHUNK = 1 << 18  # words per aggregate query of the loader (8 MB of descriptors)

    def _words(self, c, only: str | None = None) -> tuple[np.ndarray, np.ndarray]:
        # One row per word in SQL, but never per word in Python: each chunk comes back as
        # one concatenated descriptor blob and one JSON array of ids (both aggregates see
        # the rows in the same order, so they line up whatever that order is).
        where = "" if only is None else "AND id IN (SELECT value FROM json_each(?3)) "
        sql = ("SELECT CAST(group_concat(descriptor, x'') AS BLOB), json_group_array(id), "
               "COALESCE(SUM(length(descriptor) != 32), 0) FROM "
               f"(SELECT id, descriptor FROM words WHERE id > ?1 {where}ORDER BY id LIMIT ?2)")
        ids, descs, last = [], [], -1
        while True:
            params = (last, self._WORD_CHUNK) if only is None else (last, self._WORD_CHUNK, only)
            blob, id_json, bad = c.execute(sql, params).fetchone()
            chunk = np.asarray(json.loads(id_json), np.int64)
            if not len(chunk):
                break
            if bad:
                raise StoreError(f"corrupt words table: {bad} descriptor(s) are not 32 bytes")
            ids.append(chunk)
            descs.append(np.frombuffer(blob, np.uint8).reshape(-1, 32))
            last = int(chunk.max())
            if len(chunk) < self._WORD_CHUNK:
                break
        if not ids:
            return np.zeros(0, np.int64), np.zeros((0, 32), np.uint8)
        ids, desc = np.concatenate(ids), np.concatenate(descs)
        if np.any(np.diff(ids) <= 0):
            order = np.argsort(ids, kind="stable")
            ids, desc = ids[order], desc[order]
        return ids, desc

    def load_vocabulary_state(self) -> dict[str, np.ndarray]:
        """Everything `service.vocabulary.Vocabulary.from_state` needs, from one snapshot:
        `word_ids` (W,) ascending and `descriptors` W×32 uint8 from `words`; the inverted
        index rebuilt from the nodes' `features.word_ids` (nodes without word ids are not
        indexed): `post_word`, `post_node`, `post_count` (one row per distinct (node, word),
        words missing from `words` left out), `node_ids` and `node_nfeat` (features with a
        word id ≥ 0); `next_id` (1,) = one past the highest word id ever stored or referenced."""
        with self._read(snapshot=True) as c:
            ids, desc = self._words(c)
            mark = c.execute("SELECT value FROM admin WHERE key = 'next_word_id'").fetchone()
            rows = c.execute("SELECT node_id, count, word_ids FROM features WHERE word_ids IS NOT NULL "
                             "ORDER BY node_id").fetchall()
        nodes = np.fromiter((r[0] for r in rows), np.int64, len(rows))
        counts = np.fromiter((r[1] for r in rows), np.int64, len(rows))
        blobs = [r[2] for r in rows]
        sizes = np.fromiter((len(b) for b in blobs), np.int64, len(blobs))
        bad = np.nonzero(sizes != 4 * counts)[0]
        if len(bad):
            i = int(bad[0])
            raise StoreError(f"corrupt word_ids of node {nodes[i]}: {sizes[i]} bytes for {counts[i]} features")
        w = np.frombuffer(b"".join(blobs), np.dtype("<i4")).astype(np.int64)
        n = np.repeat(nodes, counts)
        quantized = w >= 0
        nfeat = np.bincount(np.repeat(np.arange(len(nodes)), counts)[quantized], minlength=len(nodes))
        next_id = max(int(ids[-1]) + 1 if len(ids) else 0, int(w.max()) + 1 if len(w) else 0,
                      int(mark[0]) if mark is not None else 0)
        present = np.zeros(next_id, bool)
        present[ids] = True
        keep = quantized.copy()
        keep[quantized] = present[w[quantized]]
        key, post_count = np.unique((n[keep] << 32) | w[keep], return_counts=True)
        return {
            "word_ids": ids, "descriptors": desc,
            "post_word": key & 0xFFFFFFFF, "post_node": key >> 32, "post_count": post_count.astype(np.int64),
            "node_ids": nodes, "node_nfeat": nfeat.astype(np.int64),
            "next_id": np.array([next_id], np.int64),
        }

    def delete_words(self, word_ids: Iterable[int]) -> int:
        """Delete words (e.g. ones whose nodes are all gone); unknown ids are ignored. The
        caller makes sure no stored node still refers to them (`prune_words` checks it
        itself). Returns the number deleted."""
        ids = np.unique(_word_ids(word_ids, "word_ids", 0))
        if not len(ids):
            return 0
        with self._write("delete_words") as c:
            return c.execute("DELETE FROM words WHERE id IN (SELECT value FROM json_each(?))",
                             (json.dumps(ids.tolist()),)).rowcount

    def prune_words(self) -> np.ndarray:
        """Delete every word no stored node refers to, in one transaction; returns their ids."""
        with self._write("prune_words") as c:
            (id_json,) = c.execute("SELECT json_group_array(id) FROM words").fetchone()
            ids = np.asarray(json.loads(id_json), np.int64)
            used = [np.frombuffer(r[0], np.dtype("<i4")) for r in
                    c.execute("SELECT word_ids FROM features WHERE word_ids IS NOT NULL")]
            orphans = ids[~np.isin(ids, np.concatenate(used) if used else np.zeros(0, np.int32))]
            if len(orphans):
                c.execute("DELETE FROM words WHERE id IN (SELECT value FROM json_each(?))",
                          (json.dumps(orphans.tolist()),))
        return orphans

    # -- reads ------------------------------------------------------------------------------
    def get_node(self, node_id: int) -> NodeRecord | None:
        with self._read() as c:
            row = c.execute(f"SELECT {_NODE_COLUMNS} FROM nodes n WHERE n.id = ?",
                            (_as_int(node_id, "node_id"),)).fetchone()
        return None if row is None else _node(row)

    def node_by_label(self, label: str) -> NodeRecord | None:
        with self._read() as c:
            row = c.execute(f"SELECT {_NODE_COLUMNS} FROM nodes n WHERE n.label = ?", (label,)).fetchone()
        return None if row is None else _node(row)

    def load_features(self, node_id: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
        """(keypoints N×2 float32, descriptors N×32 uint8, points N×3 float32, word_ids N int32 | None),
        bit-exact as written. Raises UnknownIdError for an unknown node."""
        nid = _as_int(node_id, "node_id")
        with self._read() as c:
            row = c.execute("SELECT count, keypoints, descriptors, points, word_ids FROM features WHERE node_id = ?",
                            (nid,)).fetchone()
        if row is None:
            raise UnknownIdError(f"no features for node {nid}")
        n = row[0]
        return (_unpack(row[1], np.float32, (n, 2)), _unpack(row[2], np.uint8, (n, 32)),
                _unpack(row[3], np.float32, (n, 3)), None if row[4] is None else _unpack(row[4], np.int32, (n,)))

    def load_images(self, node_id: int) -> tuple[bytes | None, bytes | None]:
        """(JPEG colour, PNG-16 millimetre depth) as stored; (None, None) when not kept."""
        nid = _as_int(node_id, "node_id")
        with self._read() as c:
            row = c.execute("SELECT n.id, i.color, i.depth FROM nodes n LEFT JOIN images i ON i.node_id = n.id "
                            "WHERE n.id = ?", (nid,)).fetchone()
        if row is None:
            raise UnknownIdError(f"no node {nid}")
        return row[1], row[2]

    def statistics(self, node_id: int) -> dict | None:
        with self._read() as c:
            row = c.execute("SELECT data FROM statistics WHERE node_id = ?", (_as_int(node_id, "node_id"),)).fetchone()
        return None if row is None else json.loads(row[0])

    def _node_filter(self, session_id, robot, bbox, merged=None) -> tuple[str, list]:
        where, params = [], []
        if merged is not None:
            where.append("n.merged_into IS NOT NULL" if merged else "n.merged_into IS NULL")
        if session_id is not None:
            where.append("n.session_id = ?")
            params.append(_as_int(session_id, "session_id"))
        if robot is not None:
            where.append("n.robot = ?")
            params.append(str(robot))
        if bbox is not None:
            lo, hi = _bbox(bbox)
            if self._rtree:
                where.append("n.id IN (SELECT id FROM nodes_rtree WHERE max_x >= ? AND min_x <= ? "
                             "AND max_y >= ? AND min_y <= ? AND max_z >= ? AND min_z <= ?)")
                params += [lo[0], hi[0], lo[1], hi[1], lo[2], hi[2]]
            where.append("n.x BETWEEN ? AND ? AND n.y BETWEEN ? AND ? AND n.z BETWEEN ? AND ?")
            params += [lo[0], hi[0], lo[1], hi[1], lo[2], hi[2]]
        return (" WHERE " + " AND ".join(where)) if where else "", params

    def nodes(self, session_id: int | None = None, robot: str | None = None, bbox=None,
              limit: int | None = 100, offset: int = 0, merged: bool | None = None) -> list[NodeRecord]:
        """Nodes matching every given filter, ordered by id; `bbox` = ((xmin, ymin, zmin),
        (xmax, ymax, zmax)) on the node positions, bounds included; `limit=None` = all;
        `merged` False = the map's nodes only, True = merged keyframes only, None = both."""
        where, params = self._node_filter(session_id, robot, bbox, merged)
        lim = -1 if limit is None else _as_int(limit, "limit")
        off = _as_int(offset, "offset")
        if lim < -1 or off < 0:
            raise ValueError(f"limit and offset must be >= 0, got {limit}, {offset}")
        with self._read() as c:
            rows = c.execute(f"SELECT {_NODE_COLUMNS} FROM nodes n{where} ORDER BY n.id LIMIT ? OFFSET ?",
                             params + [lim, off]).fetchall()
        return [_node(r) for r in rows]

    def count_nodes(self, session_id: int | None = None, robot: str | None = None, bbox=None,
                    merged: bool | None = None) -> int:
        where, params = self._node_filter(session_id, robot, bbox, merged)
        with self._read() as c:
            return c.execute(f"SELECT COUNT(*) FROM nodes n{where}", params).fetchone()[0]

    def links(self, session_id: int | None = None, node_ids: Iterable[int] | None = None,
              type: int | None = None) -> list[LinkRecord]:
        """Links ordered by (from, to, type): touching a node of `session_id`, touching one
        of `node_ids`, of link `type` — every given filter applies."""
        with self._read() as c:
            return self._links(c, session_id, node_ids, type)

    def _links(self, c, session_id=None, node_ids=None, type=None, both_in_session=False) -> list[LinkRecord]:
        where, params = [], []
        if session_id is not None:
            sub = "(SELECT id FROM nodes WHERE session_id = ?)"
            where.append(f"(from_id IN {sub} {'AND' if both_in_session else 'OR'} to_id IN {sub})")
            params += [_as_int(session_id, "session_id")] * 2
        if node_ids is not None:
            ids = json.dumps([_as_int(i, "node id") for i in node_ids])
            where.append("(from_id IN (SELECT value FROM json_each(?)) OR to_id IN (SELECT value FROM json_each(?)))")
            params += [ids, ids]
        if type is not None:
            where.append("type = ?")
            params.append(_as_int(type, "link type"))
        sql = "SELECT from_id, to_id, type, transform, information FROM links"
        if where:
            sql += " WHERE " + " AND ".join(where)
        rows = c.execute(sql + " ORDER BY from_id, to_id, type", params).fetchall()
        return [_link(r) for r in rows]

    def trajectory(self, session_id: int) -> Trajectory:
        """The session's node poses ordered by stamp (then id)."""
        with self._read(snapshot=True) as c:
            return self._trajectory(c, _as_int(session_id, "session_id"))

    def _trajectory(self, c, sid: int) -> Trajectory:
        if c.execute("SELECT 1 FROM sessions WHERE id = ?", (sid,)).fetchone() is None:
            raise UnknownIdError(f"no session {sid}")
        rows = c.execute("SELECT stamp, pose FROM nodes WHERE session_id = ? ORDER BY stamp, id", (sid,)).fetchall()
        poses = np.array([_unpack(r[1], np.float64, (4, 4)) for r in rows]).reshape(-1, 4, 4)
        return Trajectory(np.array([r[0] for r in rows], dtype=np.float64), poses)

    def file_bytes(self) -> tuple[int, int]:
        """(database file, WAL file) sizes in bytes."""
        def size(p: Path) -> int:
            try:
                return p.stat().st_size
            except OSError:
                return 0
        return size(self.path), size(self.path.with_name(self.path.name + "-wal"))

    def stats(self) -> dict:
        """Counts (one consistent snapshot) and file sizes; JSON-encodable."""
        with self._read(snapshot=True) as c:
            one = lambda sql: c.execute(sql).fetchone()[0]  # noqa: E731
            by_type = {_link_name(t): n for t, n in c.execute("SELECT type, COUNT(*) FROM links GROUP BY type ORDER BY type")}
            out = {
                "schema_version": one("PRAGMA user_version"),
                "sessions": one("SELECT COUNT(*) FROM sessions"),
                "nodes": one("SELECT COUNT(*) FROM nodes"),
                "links": sum(by_type.values()),
                "links_by_type": by_type,
                "features": one("SELECT COUNT(*) FROM features"),
                "keypoints": one("SELECT COALESCE(SUM(count), 0) FROM features"),
                "words": one("SELECT COUNT(*) FROM words"),
                "images": one("SELECT COUNT(*) FROM images"),
                "statistics": one("SELECT COUNT(*) FROM statistics"),
            }
        db, wal = self.file_bytes()
        out.update(file_bytes=db + wal, wal_bytes=wal)
        return out

    def session_stats(self) -> dict[int, dict]:
        """{session id: {nodes, first_stamp, last_stamp}} for every session (one snapshot)."""
        with self._read(snapshot=True) as c:
            out = {r[0]: {"nodes": 0, "first_stamp": None, "last_stamp": None}
                   for r in c.execute("SELECT id FROM sessions ORDER BY id")}
            for sid, n, first, last in c.execute(
                    "SELECT session_id, COUNT(*), MIN(stamp), MAX(stamp) FROM nodes GROUP BY session_id"):
                out[sid] = {"nodes": n, "first_stamp": first, "last_stamp": last}
        return out

    def integrity_check(self) -> str:
        """'ok', or SQLite's integrity / foreign-key problems, one per line."""
        with self._read() as c:
            problems = [r[0] for r in c.execute("PRAGMA integrity_check").fetchall()]
            if problems == ["ok"]:
                problems = []
            problems += [f"foreign key: {r[0]} row {r[1]} -> {r[2]}" for r in c.execute("PRAGMA foreign_key_check")]
        return "\n".join(problems) if problems else "ok"

    # -- export -----------------------------------------------------------------------------
    def export(self, out_dir: str | Path, session_id: int | None = None) -> list[Path]:
        """Write TUM trajectories and graph.json into `out_dir`; return the written paths.

        With `session_id`: `trajectory.tum` of that session and its graph. Without: one
        session → `trajectory.tum`; several → `trajectory_<session id>.tum` each (their
        stamps are on unrelated clocks, so they are not merged); graph.json holds them all.
        graph.json = {sessions: [...], nodes: [{id, session, stamp, pose (16 floats,
        row-major), weight, label}], links: [{from, to, type, transform (16), information (36)}]}.
        """
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        written = []
        with self._read(snapshot=True) as c:
            if session_id is not None:
                sid = _as_int(session_id, "session_id")
                trajs = {sid: self._trajectory(c, sid)}
                names = {sid: "trajectory.tum"}
                rows = c.execute(f"SELECT {_SESSION_COLUMNS} FROM sessions WHERE id = ?", (sid,)).fetchall()
                nodes = c.execute("SELECT id, session_id, stamp, pose, weight, label FROM nodes "
                                  "WHERE session_id = ? ORDER BY id", (sid,)).fetchall()
                links = self._links(c, session_id=sid, both_in_session=True)
            else:
                rows = c.execute(f"SELECT {_SESSION_COLUMNS} FROM sessions ORDER BY id").fetchall()
                trajs = {r[0]: self._trajectory(c, r[0]) for r in rows}
                names = {s: ("trajectory.tum" if len(rows) == 1 else f"trajectory_{s}.tum") for s in trajs}
                nodes = c.execute("SELECT id, session_id, stamp, pose, weight, label FROM nodes ORDER BY id").fetchall()
                links = self._links(c)
        if not trajs:
            (out / "trajectory.tum").write_text("")
            written.append(out / "trajectory.tum")
        for sid, traj in trajs.items():
            p = out / names[sid]
            p.write_text(format_tum(traj))
            written.append(p)
        graph = {
            "sessions": [_session(r).to_dict() for r in rows],
            "nodes": [{"id": r[0], "session": r[1], "stamp": r[2],
                       "pose": _unpack(r[3], np.float64, (4, 4)).reshape(-1).tolist(),
                       "weight": r[4], "label": r[5]} for r in nodes],
            "links": [{"from": l.from_id, "to": l.to_id, "type": int(l.type),
                       "transform": l.transform.reshape(-1).tolist(),
                       "information": l.information.reshape(-1).tolist()} for l in links],
        }
        p = out / "graph.json"
        p.write_text(json.dumps(_jsonable(graph, "graph"), indent=1))
        written.append(p)
        return written
