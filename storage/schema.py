"""The long-term memory's SQLite schema and its migrations.

The stored schema version is `PRAGMA user_version` (0 = empty file), mirrored in
`admin.schema_version` for people reading the file with other tools. `MIGRATIONS[i]` takes
a database from version i to i + 1; `MapStore` applies the missing ones in order, each in
its own `BEGIN IMMEDIATE` transaction together with the version bump, so a crash during a
migration leaves the previous version intact. To change the schema, append a function —
never edit one that has shipped.

Table and column names follow RTAB-Map's schema where it has an equivalent (Node, Link,
Feature, Word, Data, Statistics, Admin); see storage/codec.py for the encodings.
"""
from __future__ import annotations

import sqlite3
from typing import Callable

import sqlite_utils
from sqlite_utils.db import ForeignKey

Migration = Callable[[sqlite_utils.Database], None]


def has_rtree(conn: sqlite3.Connection) -> bool:
    """Whether this SQLite build has the R*Tree module (ENABLE_RTREE)."""
    return any(r[0] == "ENABLE_RTREE" for r in conn.execute("PRAGMA compile_options"))


def _create(db: sqlite_utils.Database, name: str, columns: dict, *, autoincrement: str | None = None, **kw) -> None:
    # sqlite-utils' create() has no public AUTOINCREMENT switch; its SQL builder does
    # (pinned sqlite-utils 4.2.1).
    db.execute(db.create_table_sql(name, columns, _autoincrement=autoincrement, **kw))


def _fk(table: str, column: str, other: str, other_column: str = "id", on_delete: str = "CASCADE") -> ForeignKey:
    return ForeignKey(table, column, other, other_column, on_delete=on_delete)


def m001_initial(db: sqlite_utils.Database) -> None:
    """v1: sessions, nodes (+ spatial index), links, features, words, images, statistics, admin."""
    _create(db, "admin", {"key": str, "value": str}, pk="key")
    _create(
        db, "sessions",
        {"id": int, "robot": str, "map_id": int, "started_at": float, "calibration": str,
         "config": str, "ended_at": float},
        pk="id", not_null=["robot", "map_id", "started_at", "calibration"],
    )
    # AUTOINCREMENT: node ids are global across sessions and never reused, even after a node
    # is deleted (RTAB-Map's ids are monotonic too; caches of a memory manager rely on it).
    _create(
        db, "nodes",
        {"id": int, "session_id": int, "robot": str, "stamp": float, "pose": bytes,
         "x": float, "y": float, "z": float, "weight": int, "label": str, "time_enter": float},
        pk="id", autoincrement="id",
        not_null=["session_id", "robot", "stamp", "pose", "x", "y", "z", "weight", "time_enter"],
        defaults={"weight": 0},
        foreign_keys=[_fk("nodes", "session_id", "sessions", on_delete="NO ACTION")],
    )
    db.table("nodes").create_index(["session_id", "stamp"], index_name="idx_nodes_session")
    db.table("nodes").create_index(["robot"], index_name="idx_nodes_robot")
    # Labels are unique like RTAB-Map's Node.label (goals are set by label); NULLs don't clash.
    db.table("nodes").create_index(["label"], index_name="idx_nodes_label", unique=True)
    if has_rtree(db.conn):
        # R*Tree of the node positions (degenerate boxes), kept in sync by triggers. Its
        # coordinates are float32 rounded outwards, so queries re-check the exact x, y, z.
        db.execute("CREATE VIRTUAL TABLE nodes_rtree USING rtree(id, min_x, max_x, min_y, max_y, min_z, max_z)")
        db.execute("""CREATE TRIGGER nodes_rtree_insert AFTER INSERT ON nodes BEGIN
            INSERT INTO nodes_rtree VALUES (new.id, new.x, new.x, new.y, new.y, new.z, new.z); END""")
        db.execute("""CREATE TRIGGER nodes_rtree_update AFTER UPDATE OF x, y, z ON nodes BEGIN
            UPDATE nodes_rtree SET min_x = new.x, max_x = new.x, min_y = new.y, max_y = new.y,
                min_z = new.z, max_z = new.z WHERE id = new.id; END""")
        db.execute("""CREATE TRIGGER nodes_rtree_delete AFTER DELETE ON nodes BEGIN
            DELETE FROM nodes_rtree WHERE id = old.id; END""")
    else:
        db.table("nodes").create_index(["x", "y", "z"], index_name="idx_nodes_xyz")
    _create(
        db, "links",
        {"from_id": int, "to_id": int, "type": int, "transform": bytes, "information": bytes},
        pk=("from_id", "to_id", "type"), not_null=["from_id", "to_id", "type", "transform", "information"],
        foreign_keys=[_fk("links", "from_id", "nodes"), _fk("links", "to_id", "nodes")],
    )
    db.table("links").create_index(["to_id"], index_name="idx_links_to")
    _create(
        db, "features",
        {"node_id": int, "count": int, "keypoints": bytes, "descriptors": bytes, "points": bytes,
         "word_ids": bytes},
        pk="node_id", not_null=["count", "keypoints", "descriptors", "points"],
        foreign_keys=[_fk("features", "node_id", "nodes")],
    )
    _create(db, "words", {"id": int, "descriptor": bytes, "time_enter": float}, pk="id",
            not_null=["descriptor"])
    _create(
        db, "images", {"node_id": int, "color": bytes, "depth": bytes}, pk="node_id",
        foreign_keys=[_fk("images", "node_id", "nodes")],
    )
    _create(
        db, "statistics", {"node_id": int, "data": str}, pk="node_id", not_null=["data"],
        foreign_keys=[_fk("statistics", "node_id", "nodes")],
    )


def m002_session_end_reason(db: sqlite_utils.Database) -> None:
    """v2: `sessions.end_reason`, how a session ended: "stopped" (a normal end), "crashed"
    (found still open when the service started again), NULL while it runs. Sessions that had
    already ended were ended normally (`end_session` was the only way to end one)."""
    db.execute("ALTER TABLE sessions ADD COLUMN end_reason TEXT")
    db.execute("UPDATE sessions SET end_reason = 'stopped' WHERE ended_at IS NOT NULL")


def m003_merged_nodes(db: sqlite_utils.Database) -> None:
    """v3: `nodes.merged_into`, the node a keyframe was merged into by rehearsal (NULL for a
    node of the map). A merged keyframe keeps its row (stamp, pose, the links tracking wrote)
    and gets a `merged` link from its survivor; its features and images are gone."""
    db.execute("ALTER TABLE nodes ADD COLUMN merged_into INTEGER")


def m004_objects(db: sqlite_utils.Database) -> None:
    """v4: `objects`, the 3-D object instances of the semantic map (issue 14). Each is
    anchored to a keyframe (`node_id`): `centroid` is in that node's camera frame, so the
    object moves with the node when the graph is corrected (its world position is the
    node's pose @ centroid, computed on read). `histogram` is the float32 posterior over the
    K classes of the source's class table, `class_id` / `label` / `confidence` its argmax,
    the class name and its probability; `extent` the axis-aligned size in the map frame;
    `keyframes` the int64 ids of the (most recent ≤ 64) keyframes that observed it."""
    _create(
        db, "objects",
        {"id": int, "node_id": int, "class_id": int, "label": str, "confidence": float, "histogram": bytes,
         "centroid": bytes, "extent": bytes, "observations": int, "keyframes": bytes, "updated": float},
        pk="id", autoincrement="id",
        not_null=["node_id", "class_id", "label", "confidence", "histogram", "centroid", "extent",
                  "observations", "keyframes", "updated"],
        foreign_keys=[_fk("objects", "node_id", "nodes")],
    )
    db.table("objects").create_index(["label"], index_name="idx_objects_label")
    db.table("objects").create_index(["node_id"], index_name="idx_objects_node")


def m005_rtree_map_nodes(db: sqlite_utils.Database) -> None:
    """v5: the R*Tree holds the map's nodes only. A keyframe merged by rehearsal leaves it (a
    trigger on `merged_into`), so a spatial query of the map (retrieval near the keyframe, at
    every map update) does not slow down as a patrol merges ever more keyframes at one place;
    queries that include merged keyframes check their exact x, y, z without the R*Tree."""
    if db.execute("SELECT 1 FROM sqlite_master WHERE name = 'nodes_rtree'").fetchone() is None:
        return  # an SQLite without R*Tree: the (x, y, z) index serves every query
    db.execute("DELETE FROM nodes_rtree WHERE id IN (SELECT id FROM nodes WHERE merged_into IS NOT NULL)")
    db.execute("""CREATE TRIGGER nodes_rtree_merged AFTER UPDATE OF merged_into ON nodes
        WHEN new.merged_into IS NOT NULL BEGIN DELETE FROM nodes_rtree WHERE id = new.id; END""")


def m006_segmentations(db: sqlite_utils.Database) -> None:
    """v6: `segmentations`, which keyframes the semantic map has taken (issue 24): one row per
    node the semantic worker has dealt with, `source` ("camera" labels or "model"), `status`
    ("fused": its labels are in the objects; "skipped": nothing to segment (no depth, no
    image, no model for an unlabelled keyframe)), `at` (UNIX time). A keyframe without a row
    is not segmented yet: the worker back-fills it from its stored images, and coverage is
    the share of the map's nodes with a "fused" row."""
    _create(db, "segmentations", {"node_id": int, "source": str, "status": str, "at": float}, pk="node_id",
            not_null=["source", "status", "at"], foreign_keys=[_fk("segmentations", "node_id", "nodes")])


def m007_local_grids(db: sqlite_utils.Database) -> None:
    """v7: `local_grids`, each keyframe's local occupancy grid made from its depth (issue 25;
    RTAB-Map keeps ground/obstacle/empty cells in its `Data` table): `cell_size` (m),
    `transform` (float64 4×4, camera ← grid frame: z up, origin on the floor under the
    camera), `origin_x`/`origin_y` (cell index of the image's first cell), `cells` (PNG of a
    uint8 image: 0 unknown, 1 free, 2 occupied; row = y), `up_source` (where the up direction
    came from: config, session, floor, accelerometer) and `floor_points` (depth points of the
    fitted floor, 0 when none). Keyframes of older files have no row: the grid is made from
    their stored depth when a map grid first needs it."""
    _create(db, "local_grids",
            {"node_id": int, "cell_size": float, "transform": bytes, "origin_x": int, "origin_y": int,
             "cells": bytes, "up_source": str, "floor_points": int},
            pk="node_id", not_null=["cell_size", "transform", "origin_x", "origin_y", "cells", "up_source",
                                    "floor_points"],
            foreign_keys=[_fk("local_grids", "node_id", "nodes")])


#: Applied in order: MIGRATIONS[i] upgrades schema version i to i + 1.
MIGRATIONS: tuple[Migration, ...] = (m001_initial, m002_session_end_reason, m003_merged_nodes, m004_objects,
                                      m005_rtree_map_nodes, m006_segmentations, m007_local_grids)

#: Tables a v1 database has (for "is this a mnemoslam database" checks).
TABLES = ("admin", "sessions", "nodes", "links", "features", "words", "images", "statistics")
