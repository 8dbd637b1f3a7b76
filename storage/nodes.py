"""Sessions and the write side of the pose graph: `Nodes` begins, ends and lists sessions
(and finds the keyframes a map update has not been through yet), adds keyframes (node,
features, images, odometry link and statistics in one transaction), adds and deletes
links, moves poses, names nodes and replaces their statistics. Encodings and checks are
`storage.records`'; transactions are `storage.connection`'s."""
from __future__ import annotations

import dataclasses
import json
import sqlite3
import time
from collections.abc import Iterable, Mapping

import numpy as np

from mnemoslam.client.kernel.frames import Calibration

from .connection import Connection
from .records import (
    _SESSION_COLUMNS,
    KeyframeRecord,
    LinkType,
    SessionRecord,
    StoreError,
    UnknownIdError,
    _as_int,
    _calibration_to_dict,
    _end_reason,
    _matrix,
    _pack,
    _prepare_keyframe,
    _rigid,
    _session,
    _to_json,
)


class Nodes(Connection):
    """Sessions, keyframes, links, poses, labels and statistics (the `MapStore` methods of
    those)."""

    # -- sessions ---------------------------------------------------------------------------
    def begin_session(self, robot: str, calibration: Calibration, config: dict | None = None) -> int:
        """Start a session (a new map id, RTAB-Map's multi-session) and return its id."""
        if not isinstance(robot, str) or not robot.strip():
            raise ValueError(f"robot must be a non-empty string, got {robot!r}")
        if not isinstance(calibration, Calibration):
            raise ValueError(f"calibration must be a mnemoslam.client.kernel.frames.Calibration, got {type(calibration).__name__}")
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
                rows = c.execute(f"SELECT {_SESSION_COLUMNS} FROM sessions WHERE id IN ({q}) ORDER BY id",
                                 ids).fetchall()
            else:
                rows = []
        return [_session(r) for r in rows]

    def unmapped_nodes(self, session_ids: Iterable[int] | None = None,
                       end_reason: str | None = None) -> dict[int, list[int]]:
        """{session id: [node ids ascending]} of the keyframes that have no map update yet: no
        `statistics` row, which the map update (service.mapping.mapper.Mapper) writes last, after the
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
            known = ", ".join(f"{x.value} {x.name.lower()}" for x in LinkType)
            raise ValueError(f"unknown link type {type!r} (known: {known})") from e
        T = _pack(_rigid(transform, "transform"), np.float64)
        info = _pack(np.eye(6) if information is None else _matrix(information, (6, 6), "information"), np.float64)
        verb = "INSERT OR REPLACE" if replace else "INSERT"
        with self._write("add_link") as c:
            try:
                c.execute(f"{verb} INTO links (from_id, to_id, type, transform, information) VALUES (?, ?, ?, ?, ?)",
                          (a, b, int(t), T, info))
            except sqlite3.IntegrityError as e:
                if "FOREIGN KEY" in str(e):
                    missing = [i for i in (a, b)
                               if c.execute("SELECT 1 FROM nodes WHERE id = ?", (i,)).fetchone() is None]
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
            c.execute("UPDATE nodes SET weight = weight + (SELECT weight + 1 FROM nodes WHERE id = ?) WHERE id = ?",
                      (a, b))
            c.execute("UPDATE nodes SET merged_into = ? WHERE id = ?", (b, a))
            c.execute("INSERT OR REPLACE INTO links (from_id, to_id, type, transform, information) "
                      "VALUES (?, ?, ?, ?, ?)", (b, a, int(LinkType.MERGED), T, info))
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
                missing = [r[4] for r in rows
                           if c.execute("SELECT 1 FROM nodes WHERE id = ?", (r[4],)).fetchone() is None]
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

