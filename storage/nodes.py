"""The write side of the pose graph (tables `nodes`, `links`, `features`, `images`,
`statistics`): `Nodes` adds keyframes (node, features, images, odometry link and statistics
in one transaction), adds and deletes links, merges a keyframe into a node (rehearsal),
moves poses, names nodes and replaces their statistics. Encodings and checks are
`storage.codec`'s; transactions are `storage.connection`'s."""
from __future__ import annotations

import json
import sqlite3
import time
from collections.abc import Iterable, Mapping

import numpy as np

from .codec import as_int, as_matrix, as_rigid, pack, prepare_keyframe, to_json
from .connection import Part
from .records import KeyframeRecord, LinkType, StoreError, UnknownIdError


class Nodes(Part):
    """Keyframes, links, poses, labels and statistics: the writes (the `MapStore` methods of
    those)."""

    # -- writes -----------------------------------------------------------------------------
    def add_keyframe(self, rec: KeyframeRecord) -> int:
        """Write node + features + images + odometry link + statistics in one transaction
        and return the node id. When this returns the keyframe is committed (durable against
        a process crash); on any error nothing of it is written."""
        k = prepare_keyframe(rec)
        with self.db.write("add_keyframe") as c:
            row = c.execute("SELECT robot, ended_at FROM sessions WHERE id = ?", (k.session_id,)).fetchone()
            if row is None:
                raise UnknownIdError(f"no session {k.session_id}")
            if row[1] is not None:
                raise StoreError(f"session {k.session_id} has ended")
            node_id = c.execute(
                "INSERT INTO nodes (session_id, robot, stamp, pose, x, y, z, weight, time_enter) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (k.session_id, row[0], k.stamp, k.pose, *k.xyz, k.weight, time.time())).lastrowid
            assert node_id is not None  # (set by every INSERT into a rowid table)
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
        self.add_links([(from_id, to_id, type, transform, information)], replace=replace)

    def add_links(self, links: Iterable[tuple], *, replace: bool = False) -> None:
        """Add constraints (from_id, to_id, type, T_from_to, information or None), as `add_link`
        does each, in ONE transaction: all of them or, on any error, none (a map joined
        through two links never holds one of them alone, whatever kills the process)."""
        rows = []
        for from_id, to_id, type, transform, information in links:
            a, b = as_int(from_id, "from_id"), as_int(to_id, "to_id")
            try:
                t = LinkType(as_int(type, "link type"))
            except ValueError as e:
                known = ", ".join(f"{x.value} {x.name.lower()}" for x in LinkType)
                raise ValueError(f"unknown link type {type!r} (known: {known})") from e
            T = pack(as_rigid(transform, "transform"), np.float64)
            info = pack(np.eye(6) if information is None else as_matrix(information, (6, 6), "information"),
                        np.float64)
            rows.append((a, b, t, T, info))
        sql = ("INSERT OR REPLACE" if replace else "INSERT") + \
            " INTO links (from_id, to_id, type, transform, information) VALUES (?, ?, ?, ?, ?)"
        with self.db.write("add_link" if len(rows) == 1 else "add_links") as c:
            for a, b, t, T, info in rows:
                try:
                    c.execute(sql, (a, b, int(t), T, info))
                except sqlite3.IntegrityError as e:
                    if "FOREIGN KEY" in str(e):
                        missing = [i for i in (a, b)
                                   if c.execute("SELECT 1 FROM nodes WHERE id = ?", (i,)).fetchone() is None]
                        raise UnknownIdError(f"link {a} -> {b}: no node {', '.join(map(str, missing))}") from e
                    raise StoreError(f"link {a} -> {b} of type {t.name.lower()} already exists "
                                     f"(pass replace=True)") from e

    def merge_node(self, node_id: int, into_id: int, transform: np.ndarray, information: np.ndarray) -> int:
        """Rehearsal: keyframe `node_id` is merged into node `into_id`, which it sees from
        T_into_node (`transform`). In one transaction: the node is marked merged, a `merged`
        link into -> node keeps the transform, the survivor's weight grows by the node's + 1
        (RTAB-Map's), and the node's features and images are deleted (its row, statistics and
        the links tracking wrote stay). Returns the survivor's new weight."""
        a, b = as_int(node_id, "node_id"), as_int(into_id, "into_id")
        if a == b:
            raise ValueError(f"node {a} cannot be merged into itself")
        T = pack(as_rigid(transform, "transform"), np.float64)
        info = pack(as_matrix(information, (6, 6), "information"), np.float64)
        with self.db.write("merge_node") as c:
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
        ids = json.dumps([as_int(i, "node id") for i in to_ids])
        kinds = json.dumps([as_int(t, "link type") for t in types])
        with self.db.write("delete_links") as c:
            return c.execute("DELETE FROM links WHERE to_id IN (SELECT value FROM json_each(?)) "
                             "AND type IN (SELECT value FROM json_each(?))", (ids, kinds)).rowcount

    def update_poses(self, poses: Mapping[int, np.ndarray]) -> int:
        """Set the pose (blob and x, y, z) of many nodes in one transaction, e.g. after graph
        optimisation. All or nothing: an unknown id rolls everything back. Returns the count."""
        if not isinstance(poses, Mapping):
            raise ValueError(f"update_poses needs {{node_id: 4×4 pose}}, got {type(poses).__name__}")
        rows = []
        for nid, pose in poses.items():
            p = as_rigid(pose, f"pose of node {nid}")
            rows.append((pack(p, np.float64), float(p[0, 3]), float(p[1, 3]), float(p[2, 3]), as_int(nid, "node id")))
        if not rows:
            return 0
        with self.db.write("update_poses") as c:
            cur = c.executemany("UPDATE nodes SET pose = ?, x = ?, y = ?, z = ? WHERE id = ?", rows)
            if cur.rowcount != len(rows):
                missing = [r[4] for r in rows
                           if c.execute("SELECT 1 FROM nodes WHERE id = ?", (r[4],)).fetchone() is None]
                raise UnknownIdError(f"update_poses: no node {', '.join(map(str, missing[:10]))}"
                                     f"{' …' if len(missing) > 10 else ''}; nothing updated")
        return len(rows)

    def set_label(self, node_id: int, label: str | None) -> None:
        """Name a node (unique across the database, like RTAB-Map's labels); None clears it."""
        nid = as_int(node_id, "node_id")
        if label is not None and (not isinstance(label, str) or not label.strip()):
            raise ValueError(f"label must be a non-empty string or None, got {label!r}")
        with self.db.write("set_label") as c:
            try:
                cur = c.execute("UPDATE nodes SET label = ? WHERE id = ?", (label, nid))
            except sqlite3.IntegrityError as e:
                other = c.execute("SELECT id FROM nodes WHERE label = ?", (label,)).fetchone()
                raise StoreError(f"label {label!r} is already on node {other[0] if other else '?'}") from e
            if cur.rowcount == 0:
                raise UnknownIdError(f"no node {nid}")

    def set_statistics(self, node_id: int, statistics: dict) -> None:
        """Replace a node's statistics (e.g. the loop-closure decision made after it was stored)."""
        nid = as_int(node_id, "node_id")
        if not isinstance(statistics, Mapping):
            raise ValueError(f"statistics must be a dict, got {type(statistics).__name__}")
        data = to_json(statistics, "statistics")
        with self.db.write("set_statistics") as c:
            if c.execute("SELECT 1 FROM nodes WHERE id = ?", (nid,)).fetchone() is None:
                raise UnknownIdError(f"no node {nid}")
            c.execute("INSERT INTO statistics (node_id, data) VALUES (?, ?) "
                      "ON CONFLICT(node_id) DO UPDATE SET data = excluded.data", (nid, data))

