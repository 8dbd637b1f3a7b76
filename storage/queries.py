"""The read side of the map: `Queries` gets nodes (by id, label, session, robot, bbox),
their features, images and statistics, links, trajectories, the keyframes without a map
update, counts and file sizes, an integrity check, and exports trajectories (TUM) and the
graph (JSON). Row decoders are `storage.codec`'s; read connections are
`storage.connection`'s."""
from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from mnemoslam.client.kernel.trajectory import Trajectory, format_tum

from .codec import (
    NODE_COLUMNS,
    SESSION_COLUMNS,
    as_bbox,
    as_int,
    jsonable,
    link_from_row,
    node_from_row,
    session_from_row,
    unpack,
)
from .connection import Part
from .records import LinkRecord, NodeRecord, UnknownIdError, link_name


class Queries(Part):
    """Reads of nodes, links, trajectories and statistics, and the export (the `MapStore`
    methods of those)."""

    # -- reads ------------------------------------------------------------------------------
    def get_node(self, node_id: int) -> NodeRecord | None:
        with self.db.read() as c:
            row = c.execute(f"SELECT {NODE_COLUMNS} FROM nodes n WHERE n.id = ?",
                            (as_int(node_id, "node_id"),)).fetchone()
        return None if row is None else node_from_row(row)

    def node_by_label(self, label: str) -> NodeRecord | None:
        with self.db.read() as c:
            row = c.execute(f"SELECT {NODE_COLUMNS} FROM nodes n WHERE n.label = ?", (label,)).fetchone()
        return None if row is None else node_from_row(row)

    def load_features(self, node_id: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
        """(keypoints N×2 float32, descriptors N×32 uint8, points N×3 float32, word_ids N int32 | None),
        bit-exact as written. Raises UnknownIdError for an unknown node."""
        nid = as_int(node_id, "node_id")
        with self.db.read() as c:
            row = c.execute("SELECT count, keypoints, descriptors, points, word_ids FROM features WHERE node_id = ?",
                            (nid,)).fetchone()
        if row is None:
            raise UnknownIdError(f"no features for node {nid}")
        n = row[0]
        return (unpack(row[1], np.float32, (n, 2)), unpack(row[2], np.uint8, (n, 32)),
                unpack(row[3], np.float32, (n, 3)), None if row[4] is None else unpack(row[4], np.int32, (n,)))

    def get_nodes(self, node_ids: Iterable[int]) -> list[NodeRecord]:
        """The given nodes (unknown ids left out), ordered by id: one query."""
        ids = json.dumps(sorted({as_int(i, "node id") for i in node_ids}))
        with self.db.read() as c:
            rows = c.execute(f"SELECT {NODE_COLUMNS} FROM nodes n WHERE n.id IN (SELECT value FROM json_each(?)) "
                             "ORDER BY n.id", (ids,)).fetchall()
        return [node_from_row(r) for r in rows]

    def node_ids(self, ended: bool | None = None, merged: bool | None = False) -> np.ndarray:
        """Ids (int64, ascending: in time) of the nodes, ids only, one query: `ended` True =
        of sessions that have ended (a map reopened by a new session: its previous map),
        False = of open sessions, None = all; `merged` as for `nodes` (default: the map's
        nodes, not the keyframes merged into them)."""
        where, params = self._node_filter(None, None, None, merged)
        if ended is not None:
            where += (" AND " if where else " WHERE ") + \
                f"n.session_id IN (SELECT id FROM sessions WHERE ended_at IS {'NOT ' if ended else ''}NULL)"
        with self.db.read() as c:
            rows = c.execute(f"SELECT n.id FROM nodes n{where} ORDER BY n.id", params).fetchall()
        return np.fromiter((r[0] for r in rows), np.int64, len(rows))

    def load_features_many(self, node_ids: Iterable[int]) -> dict[int, tuple[np.ndarray, np.ndarray, np.ndarray,
                                                                             np.ndarray | None]]:
        """`load_features` of many nodes in one query: {node id: (keypoints, descriptors, points,
        word_ids | None)} in ascending id order; nodes without features are left out."""
        ids = json.dumps(sorted({as_int(i, "node id") for i in node_ids}))
        with self.db.read(snapshot=True) as c:
            rows = c.execute("SELECT node_id, count, keypoints, descriptors, points, word_ids FROM features "
                             "WHERE node_id IN (SELECT value FROM json_each(?)) ORDER BY node_id", (ids,)).fetchall()
        return {r[0]: (unpack(r[2], np.float32, (r[1], 2)), unpack(r[3], np.uint8, (r[1], 32)),
                       unpack(r[4], np.float32, (r[1], 3)), None if r[5] is None else unpack(r[5], np.int32, (r[1],)))
                for r in rows}

    def link_pairs(self, types: Iterable[int] | None = None) -> np.ndarray:
        """(from, to) of every link (of `types`), (L, 2) int64, one query, ids only; a merged
        keyframe's end is its survivor's (links that then join a node to itself are left out):
        the graph adjacency of the map's nodes."""
        where, params = "", []
        if types is not None:
            where = " WHERE l.type IN (SELECT value FROM json_each(?))"
            params.append(json.dumps([as_int(t, "link type") for t in types]))
        sql = ("SELECT COALESCE(a.merged_into, l.from_id), COALESCE(b.merged_into, l.to_id) FROM links l "
               "JOIN nodes a ON a.id = l.from_id JOIN nodes b ON b.id = l.to_id" + where)
        with self.db.read() as c:
            rows = c.execute(sql, params).fetchall()
        pairs = np.array(rows, np.int64).reshape(-1, 2)
        return pairs[pairs[:, 0] != pairs[:, 1]]

    def links_after(self, rowid: int = 0) -> tuple[int, np.ndarray]:
        """The links stored after row `rowid` (a rewritten link gets a new row): (the newest
        row, (L, 2) int64 (from, to) in row order), ids as stored. For an incremental view of
        which nodes the links join (`storage.connectivity`)."""
        with self.db.read() as c:
            rows = c.execute("SELECT rowid, from_id, to_id FROM links WHERE rowid > ? ORDER BY rowid",
                             (as_int(rowid, "rowid"),)).fetchall()
        if not rows:
            return int(rowid), np.zeros((0, 2), np.int64)
        a = np.array(rows, np.int64)
        return int(a[-1, 0]), a[:, 1:]

    def link_rows(self, rowid: int = 0) -> tuple[int, np.ndarray]:
        """As `links_after`, with each link's type: (the newest row, (L, 3) int64 (from, to,
        type) in row order). For which map each keyframe and session is in (`storage.connectivity`)."""
        with self.db.read() as c:
            rows = c.execute("SELECT rowid, from_id, to_id, type FROM links WHERE rowid > ? ORDER BY rowid",
                             (as_int(rowid, "rowid"),)).fetchall()
        if not rows:
            return int(rowid), np.zeros((0, 3), np.int64)
        a = np.array(rows, np.int64)
        return int(a[-1, 0]), a[:, 1:]

    def node_sessions(self, after_id: int = 0) -> dict[str, np.ndarray]:
        """The nodes with id > `after_id` by id (merged ones too), without decoding poses:
        {"id", "session_id" (int64), "stamp", "time_enter" (float64, wall time written)}."""
        with self.db.read() as c:
            rows = c.execute("SELECT id, session_id, stamp, time_enter FROM nodes WHERE id > ? ORDER BY id",
                             (as_int(after_id, "after_id"),)).fetchall()
        a = np.array(rows, np.float64).reshape(-1, 4)
        return {"id": a[:, 0].astype(np.int64), "session_id": a[:, 1].astype(np.int64), "stamp": a[:, 2],
                "time_enter": a[:, 3]}

    def load_images(self, node_id: int) -> tuple[bytes | None, bytes | None]:
        """(JPEG colour, PNG-16 millimetre depth) as stored; (None, None) when not kept."""
        nid = as_int(node_id, "node_id")
        with self.db.read() as c:
            row = c.execute("SELECT n.id, i.color, i.depth FROM nodes n LEFT JOIN images i ON i.node_id = n.id "
                            "WHERE n.id = ?", (nid,)).fetchone()
        if row is None:
            raise UnknownIdError(f"no node {nid}")
        return row[1], row[2]

    def statistics(self, node_id: int) -> dict | None:
        with self.db.read() as c:
            row = c.execute("SELECT data FROM statistics WHERE node_id = ?", (as_int(node_id, "node_id"),)).fetchone()
        return None if row is None else json.loads(row[0])

    def map_updates(self, session_id: int, after_node: int = 0) -> list[tuple]:
        """The map updates of a session's keyframes (their statistics rows), of nodes after
        `after_node`, in node order: (node id, update ms = the sum of its steps' `timings_ms`,
        STM, WM, LTM sizes and vocabulary words after it; None where the row lacks it). Only
        these fields are read (SQLite's JSON functions), not the whole statistics."""
        sql = ("SELECT s.node_id, (SELECT SUM(value) FROM json_each(s.data, '$.timings_ms')), "
               "json_extract(s.data, '$.memory.stm'), json_extract(s.data, '$.memory.wm'), "
               "json_extract(s.data, '$.memory.ltm'), json_extract(s.data, '$.memory.words') "
               "FROM statistics s JOIN nodes n ON n.id = s.node_id "
               "WHERE n.session_id = ? AND s.node_id > ? ORDER BY s.node_id")
        with self.db.read() as c:
            return [tuple(r) for r in c.execute(sql, (as_int(session_id, "session_id"),
                                                      as_int(after_node, "after_node")))]

    def unmapped_nodes(self, session_ids: Iterable[int] | None = None,
                       end_reason: str | None = None) -> dict[int, list[int]]:
        """{session id: [node ids ascending]} of the keyframes that have no map update yet: no
        `statistics` row, which the map update (service.mapping.mapper.Mapper) writes last, after the
        keyframe's words, links and poses. Only sessions in `session_ids` and/or that ended
        with `end_reason`, when given; sessions without such keyframes are left out."""
        where, params = [], []
        if session_ids is not None:
            where.append("n.session_id IN (SELECT value FROM json_each(?))")
            params.append(json.dumps([as_int(i, "session id") for i in session_ids]))
        if end_reason is not None:
            where.append("n.session_id IN (SELECT id FROM sessions WHERE end_reason = ?)")
            params.append(str(end_reason))
        sql = ("SELECT n.session_id, n.id FROM nodes n LEFT JOIN statistics s ON s.node_id = n.id "
               "WHERE s.node_id IS NULL" + "".join(f" AND {w}" for w in where) + " ORDER BY n.session_id, n.id")
        out: dict[int, list[int]] = {}
        with self.db.read() as c:
            for sid, nid in c.execute(sql, params):
                out.setdefault(sid, []).append(nid)
        return out

    # -- the live viewer (service.viewer) -----------------------------------------------------
    def node_positions(self, session_id: int, after_id: int = 0) -> np.ndarray:
        """(N, 4) float64 rows (id, x, y, z) of the session's map nodes (not merged into another)
        with id > `after_id`, by id: the viewer's trajectory without decoding poses."""
        with self.db.read() as c:
            rows = c.execute("SELECT id, x, y, z FROM nodes WHERE session_id = ? AND id > ? AND merged_into IS NULL "
                             "ORDER BY id",
                             (as_int(session_id, "session_id"), as_int(after_id, "after_id"))).fetchall()
        return np.array(rows, dtype=np.float64).reshape(-1, 4)

    def link_segments(self, types: Iterable[int], session_id: int, limit: int | None = None) -> list[tuple]:
        """Links of the given types ending at a node of `session_id` (as `count_links` counts
        them) with both ends' positions: (from, to, type, x1, y1, z1, x2, y2, z2), the
        newest `limit` (by their end node) in (to, from, type) order."""
        kinds = json.dumps(sorted({as_int(t, "type") for t in types}))
        lim = -1 if limit is None else as_int(limit, "limit")
        sql = ("SELECT * FROM (SELECT l.from_id, l.to_id, l.type, a.x, a.y, a.z, b.x, b.y, b.z "
               "FROM nodes b JOIN links l ON l.to_id = b.id JOIN nodes a ON a.id = l.from_id "
               "WHERE b.session_id = ? AND l.type IN (SELECT value FROM json_each(?)) "
               "ORDER BY l.to_id DESC, l.from_id DESC, l.type DESC LIMIT ?) ORDER BY 2, 1, 3")
        with self.db.read() as c:
            return [tuple(r) for r in c.execute(sql, (as_int(session_id, "session_id"), kinds, lim))]

    def count_links(self, types: Iterable[int], session_id: int | None = None) -> dict[int, int]:
        """{link type: links} of the given types, of those ending at a node of `session_id`
        when given (a loop closure's link ends at the new keyframe)."""
        kinds = sorted({as_int(t, "type") for t in types})
        if not kinds:
            return {}
        marks = ", ".join("?" * len(kinds))
        if session_id is None:
            sql, args = f"SELECT type, COUNT(*) FROM links WHERE type IN ({marks}) GROUP BY type", kinds
        else:
            sql = (f"SELECT l.type, COUNT(*) FROM nodes n JOIN links l ON l.to_id = n.id "
                   f"WHERE n.session_id = ? AND l.type IN ({marks}) GROUP BY l.type")
            args = [as_int(session_id, "session_id"), *kinds]
        with self.db.read() as c:
            out = {t: 0 for t in kinds}
            out.update({t: n for t, n in c.execute(sql, args)})
        return out

    def _node_filter(self, session_id, robot, bbox, merged=None) -> tuple[str, list]:
        where: list[str] = []
        params: list[int | float | str] = []
        if merged is not None:
            where.append("n.merged_into IS NOT NULL" if merged else "n.merged_into IS NULL")
        if session_id is not None:
            where.append("n.session_id = ?")
            params.append(as_int(session_id, "session_id"))
        if robot is not None:
            where.append("n.robot = ?")
            params.append(str(robot))
        if bbox is not None:
            lo, hi = as_bbox(bbox)
            if self.db.rtree and merged is not True:  # (the R*Tree holds the map's nodes, not merged keyframes)
                rtree = ("n.id IN (SELECT id FROM nodes_rtree WHERE max_x >= ? AND min_x <= ? "
                         "AND max_y >= ? AND min_y <= ? AND max_z >= ? AND min_z <= ?)")
                where.append(rtree if merged is False else f"({rtree} OR n.merged_into IS NOT NULL)")
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
        lim = -1 if limit is None else as_int(limit, "limit")
        off = as_int(offset, "offset")
        if lim < -1 or off < 0:
            raise ValueError(f"limit and offset must be >= 0, got {limit}, {offset}")
        with self.db.read() as c:
            rows = c.execute(f"SELECT {NODE_COLUMNS} FROM nodes n{where} ORDER BY n.id LIMIT ? OFFSET ?",
                             params + [lim, off]).fetchall()
        return [node_from_row(r) for r in rows]

    def count_nodes(self, session_id: int | None = None, robot: str | None = None, bbox=None,
                    merged: bool | None = None) -> int:
        where, params = self._node_filter(session_id, robot, bbox, merged)
        with self.db.read() as c:
            return c.execute(f"SELECT COUNT(*) FROM nodes n{where}", params).fetchone()[0]

    def links(self, session_id: int | None = None, node_ids: Iterable[int] | None = None,
              type: int | None = None) -> list[LinkRecord]:
        """Links ordered by (from, to, type): touching a node of `session_id`, touching one
        of `node_ids`, of link `type` — every given filter applies."""
        with self.db.read() as c:
            return self._links(c, session_id, node_ids, type)

    def _links(self, c, session_id=None, node_ids=None, type=None, both_in_session=False) -> list[LinkRecord]:
        where: list[str] = []
        params: list[int | str] = []
        if session_id is not None:
            sub = "(SELECT id FROM nodes WHERE session_id = ?)"
            where.append(f"(from_id IN {sub} {'AND' if both_in_session else 'OR'} to_id IN {sub})")
            params += [as_int(session_id, "session_id")] * 2
        if node_ids is not None:
            ids = json.dumps([as_int(i, "node id") for i in node_ids])
            where.append("(from_id IN (SELECT value FROM json_each(?)) OR to_id IN (SELECT value FROM json_each(?)))")
            params += [ids, ids]
        if type is not None:
            where.append("type = ?")
            params.append(as_int(type, "link type"))
        sql = "SELECT from_id, to_id, type, transform, information FROM links"
        if where:
            sql += " WHERE " + " AND ".join(where)
        rows = c.execute(sql + " ORDER BY from_id, to_id, type", params).fetchall()
        return [link_from_row(r) for r in rows]

    def trajectory(self, session_id: int) -> Trajectory:
        """The session's node poses ordered by stamp (then id)."""
        with self.db.read(snapshot=True) as c:
            return self._trajectory(c, as_int(session_id, "session_id"))

    def _trajectory(self, c, sid: int) -> Trajectory:
        if c.execute("SELECT 1 FROM sessions WHERE id = ?", (sid,)).fetchone() is None:
            raise UnknownIdError(f"no session {sid}")
        rows = c.execute("SELECT stamp, pose FROM nodes WHERE session_id = ? ORDER BY stamp, id", (sid,)).fetchall()
        poses = np.array([unpack(r[1], np.float64, (4, 4)) for r in rows]).reshape(-1, 4, 4)
        return Trajectory(np.array([r[0] for r in rows], dtype=np.float64), poses)

    def file_bytes(self) -> tuple[int, int]:
        """(database file, WAL file) sizes in bytes."""
        def size(p: Path) -> int:
            try:
                return p.stat().st_size
            except OSError:
                return 0
        path = self.db.path
        return size(path), size(path.with_name(path.name + "-wal"))

    def stats(self) -> dict:
        """Counts (one consistent snapshot) and file sizes; JSON-encodable."""
        with self.db.read(snapshot=True) as c:
            one = lambda sql: c.execute(sql).fetchone()[0]  # noqa: E731
            by_type = {link_name(t): n
                       for t, n in c.execute("SELECT type, COUNT(*) FROM links GROUP BY type ORDER BY type")}
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

    def integrity_check(self) -> str:
        """'ok', or SQLite's integrity / foreign-key problems, one per line."""
        with self.db.read() as c:
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
        with self.db.read(snapshot=True) as c:
            if session_id is not None:
                sid = as_int(session_id, "session_id")
                trajs = {sid: self._trajectory(c, sid)}
                names = {sid: "trajectory.tum"}
                rows = c.execute(f"SELECT {SESSION_COLUMNS} FROM sessions WHERE id = ?", (sid,)).fetchall()
                nodes = c.execute("SELECT id, session_id, stamp, pose, weight, label FROM nodes "
                                  "WHERE session_id = ? ORDER BY id", (sid,)).fetchall()
                links = self._links(c, session_id=sid, both_in_session=True)
            else:
                rows = c.execute(f"SELECT {SESSION_COLUMNS} FROM sessions ORDER BY id").fetchall()
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
            "sessions": [session_from_row(r).to_dict() for r in rows],
            "nodes": [{"id": r[0], "session": r[1], "stamp": r[2],
                       "pose": unpack(r[3], np.float64, (4, 4)).reshape(-1).tolist(),
                       "weight": r[4], "label": r[5]} for r in nodes],
            "links": [{"from": lk.from_id, "to": lk.to_id, "type": int(lk.type),
                       "transform": lk.transform.reshape(-1).tolist(),
                       "information": lk.information.reshape(-1).tolist()} for lk in links],
        }
        p = out / "graph.json"
        p.write_text(json.dumps(jsonable(graph, "graph"), indent=1))
        written.append(p)
        return written

