"""The keyframes' local occupancy grids (schema v7, issue 25): `Grids` saves and reads them
and gives the map grid what it needs in one query each (every node's pose, session and
whether it has a grid). A grid is made once, where the keyframe is written
(service/memory/keyframes.py), and kept with the node like RTAB-Map's `Data` cells, so a
keyframe in long-term memory still counts and nothing is recomputed at start-up. The grid's
encoding is service.grid.local's; here it is a record of plain values."""
from __future__ import annotations

import json
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from .codec import as_int, as_rigid
from .connection import Part
from .records import UnknownIdError


@dataclass
class LocalGridRecord:
    """One row of `local_grids` (see storage.schema.m007_local_grids)."""

    node_id: int
    cell_size: float
    transform: np.ndarray  # 4×4 camera ← grid frame
    origin_x: int
    origin_y: int
    cells: bytes  # PNG, uint8 0 unknown / 1 free / 2 occupied
    up_source: str = "config"
    floor_points: int = 0


_COLUMNS = "node_id, cell_size, transform, origin_x, origin_y, cells, up_source, floor_points"


def _record(row) -> LocalGridRecord:
    return LocalGridRecord(row[0], float(row[1]), np.frombuffer(row[2], "<f8").reshape(4, 4).astype(np.float64),
                           int(row[3]), int(row[4]), bytes(row[5]), row[6], int(row[7]))


class Grids(Part):
    """Local grids of the keyframes (the `MapStore` methods of those)."""

    def save_local_grids(self, grids: Iterable[LocalGridRecord]) -> int:
        """Insert or replace local grids, in one transaction; returns how many. A grid of an
        unknown node writes nothing (UnknownIdError)."""
        rows = []
        for g in grids:
            cs = float(g.cell_size)
            if not (cs > 0 and np.isfinite(cs)):
                raise ValueError(f"cell_size must be > 0, got {g.cell_size!r}")
            T = np.ascontiguousarray(as_rigid(g.transform, "local grid transform"), "<f8")
            rows.append((as_int(g.node_id, "node id"), cs, T.tobytes(), as_int(g.origin_x, "origin_x"),
                         as_int(g.origin_y, "origin_y"), bytes(g.cells), str(g.up_source),
                         as_int(g.floor_points, "floor_points")))
        if not rows:
            return 0
        with self.db.write("save_local_grids") as c:
            known = {r[0] for r in c.execute("SELECT id FROM nodes WHERE id IN (SELECT value FROM json_each(?))",
                                             (json.dumps([r[0] for r in rows]),))}
            missing = sorted({r[0] for r in rows} - known)
            if missing:
                raise UnknownIdError(f"save_local_grids: no node {', '.join(map(str, missing[:10]))}; nothing saved")
            c.executemany(f"INSERT OR REPLACE INTO local_grids ({_COLUMNS}) VALUES (?, ?, ?, ?, ?, ?, ?, ?)", rows)
        return len(rows)

    def local_grids(self, node_ids: Iterable[int]) -> dict[int, LocalGridRecord]:
        """{node id: its local grid} of those that have one."""
        js = json.dumps([as_int(i, "node id") for i in node_ids])
        with self.db.read() as c:
            rows = c.execute(f"SELECT {_COLUMNS} FROM local_grids WHERE node_id IN (SELECT value FROM json_each(?))",
                             (js,)).fetchall()
        return {r[0]: _record(r) for r in rows}

    def count_local_grids(self) -> int:
        with self.db.read() as c:
            return c.execute("SELECT COUNT(*) FROM local_grids").fetchone()[0]

    def grid_nodes(self, has_grid: bool = True) -> dict[str, np.ndarray]:
        """Every node as columns, by id: `id` (N,) int64, `session_id` (N,) int64, `pose`
        (N, 4, 4) float64 (its current graph pose) and, with `has_grid`, `has_grid` (N,) bool.
        One query (~20 ms at 20k nodes)."""
        sql = ("SELECT n.id, n.session_id, n.pose, g.node_id IS NOT NULL FROM nodes n "
               "LEFT JOIN local_grids g ON g.node_id = n.id ORDER BY n.id") if has_grid else \
            "SELECT id, session_id, pose FROM nodes ORDER BY id"
        with self.db.read(snapshot=True) as c:
            rows = c.execute(sql).fetchall()
        n = len(rows)
        cols = list(zip(*rows)) if rows else [()] * 4
        out = {"id": np.array(cols[0], np.int64).reshape(n), "session_id": np.array(cols[1], np.int64).reshape(n),
               "pose": np.frombuffer(b"".join(cols[2]), "<f8").reshape(n, 4, 4).astype(np.float64)}
        if has_grid:
            out["has_grid"] = np.array(cols[3], bool).reshape(n)
        return out

    def nodes_without_grid(self, node_ids: Iterable[int] | None = None) -> list[int]:
        """Nodes (of `node_ids`) with stored depth but no local grid: made from their images."""
        sql = ("SELECT n.id FROM nodes n JOIN images i ON i.node_id = n.id WHERE i.depth IS NOT NULL "
               "AND NOT EXISTS (SELECT 1 FROM local_grids g WHERE g.node_id = n.id)")
        params: tuple = ()
        if node_ids is not None:
            sql += " AND n.id IN (SELECT value FROM json_each(?))"
            params = (json.dumps([as_int(i, "node id") for i in node_ids]),)
        with self.db.read() as c:
            return [r[0] for r in c.execute(sql + " ORDER BY n.id", params)]
