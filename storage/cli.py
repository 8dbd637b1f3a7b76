"""`mnemoslam db info|export DB`: printable text for the command line (wired in service/cli.py)."""
from __future__ import annotations

import datetime as _dt
from pathlib import Path

from .connectivity import MapIndex
from .records import StoreError
from .store import MapStore


def _open(path: str | Path) -> MapStore:
    p = Path(path)
    if not p.exists():
        raise StoreError(f"no database at {p}")
    return MapStore(p, create=False)


def _mb(n: int) -> str:
    return f"{n / 1e6:.2f} MB"


def _when(t: float | None) -> str:
    return "-" if t is None else _dt.datetime.fromtimestamp(t).strftime("%Y-%m-%d %H:%M:%S")


def db_info(path: str | Path) -> str:
    """Schema version, sessions (id, robot, map id, nodes, first/last stamp, start, end and
    how it ended), counts, file size and integrity of the database at `path` (which must exist)."""
    with _open(path) as store:
        st = store.stats()
        per_session = store.session_stats()
        sessions = store.sessions()
        integrity = store.integrity_check()
        index = MapIndex()
        index.refresh(store)
        joins = {s.id: index.join(s.id) for s in sessions}
    lines = [
        f"database  {Path(path)}",
        f"schema    v{st['schema_version']}",
        f"size      {_mb(st['file_bytes'])} ({_mb(st['wal_bytes'])} in the WAL)",
        f"sessions  {st['sessions']}",
    ]
    if sessions:
        lines.append(f"  {'id':>4}  {'robot':<16} {'map':>4} {'in map':>6} {'nodes':>7}  {'first stamp':>17}  "
                     f"{'last stamp':>17}  {'started':<19}  ended")
        for s in sessions:
            ps = per_session.get(s.id, {})
            n, first, last = ps.get("nodes", 0), ps.get("first_stamp"), ps.get("last_stamp")
            f = "-" if first is None else f"{first:.6f}"
            la = "-" if last is None else f"{last:.6f}"
            how = f" ({s.end_reason})" if s.end_reason else ""
            j = joins.get(s.id)
            now = "-" if j is None or j.first_node is None else str(j.map)
            joined = (f"; joined map {j.map} at keyframe {j.node} (stamp {j.stamp:.3f})"
                      if j is not None and j.joined else "")
            lines.append(f"  {s.id:>4}  {s.robot:<16} {s.map_id:>4} {now:>6} {n:>7}  {f:>17}  {la:>17}  "
                         f"{_when(s.started_at):<19}  {_when(s.ended_at)}{how}{joined}")
    by_type = ", ".join(f"{k} {v}" for k, v in st["links_by_type"].items())
    lines += [
        f"nodes     {st['nodes']}",
        f"links     {st['links']}" + (f" ({by_type})" if by_type else ""),
        f"features  {st['features']} ({st['keypoints']} keypoints)",
        f"words     {st['words']}",
        f"images    {st['images']}",
        f"integrity {integrity}",
    ]
    return "\n".join(lines)


def db_export(path: str | Path, out_dir: str | Path, session: int | None = None) -> str:
    """Export trajectories (TUM) and graph.json of the database at `path` into `out_dir`."""
    with _open(path) as store:
        if session is not None and store.session(session) is None:
            raise StoreError(f"{path}: no session {session}")
        written = store.export(out_dir, session)
    return "\n".join(f"wrote {p}" for p in written)
