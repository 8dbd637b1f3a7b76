"""Sessions (table `sessions`): `Sessions` begins and ends them (a new map id each,
RTAB-Map's multi-session), ends those a killed service left open, and lists them with their
calibration and node counts. Encodings and checks are `storage.codec`'s; transactions are
`storage.connection`'s."""
from __future__ import annotations

import dataclasses
import time
from collections.abc import Mapping

from mnemoslam.client.kernel.frames import Calibration

from .codec import SESSION_COLUMNS, as_end_reason, as_int, session_from_row, to_json
from .connection import Part
from .records import SessionRecord, UnknownIdError, calibration_to_dict


class Sessions(Part):
    """Sessions: begin, end, list (the `MapStore` methods of those)."""

    def begin_session(self, robot: str, calibration: Calibration, config: dict | None = None) -> int:
        """Start a session (a new map id, RTAB-Map's multi-session) and return its id."""
        if not isinstance(robot, str) or not robot.strip():
            raise ValueError(f"robot must be a non-empty string, got {robot!r}")
        if not isinstance(calibration, Calibration):
            raise ValueError(f"calibration must be a mnemoslam Calibration, got {type(calibration).__name__}")
        if config is not None and not (isinstance(config, Mapping) or dataclasses.is_dataclass(config)):
            raise ValueError(f"config must be a dict, got {type(config).__name__}")
        calib = to_json(calibration_to_dict(calibration), "calibration")
        conf = to_json(config, "config")
        with self.db.write("begin_session") as c:
            map_id = c.execute("SELECT COALESCE(MAX(map_id) + 1, 0) FROM sessions").fetchone()[0]
            cur = c.execute(
                "INSERT INTO sessions (robot, map_id, started_at, calibration, config) VALUES (?, ?, ?, ?, ?)",
                (robot, map_id, time.time(), calib, conf))
            assert cur.lastrowid is not None  # (set by every INSERT into a rowid table)
            return cur.lastrowid

    def end_session(self, session_id: int, reason: str = "stopped") -> None:
        """Mark a session ended, with why ("stopped" = a normal end); its first end time and
        reason are kept. It takes no more keyframes."""
        sid = as_int(session_id, "session_id")
        why = as_end_reason(reason)
        with self.db.write("end_session") as c:
            cur = c.execute("UPDATE sessions SET ended_at = COALESCE(ended_at, ?), "
                            "end_reason = CASE WHEN ended_at IS NULL THEN ? ELSE end_reason END WHERE id = ?",
                            (time.time(), why, sid))
            if cur.rowcount == 0:
                raise UnknownIdError(f"no session {sid}")

    def end_open_sessions(self, reason: str = "crashed") -> list[SessionRecord]:
        """End every session that has not ended, with `reason`, in one transaction, and return
        them as ended. For the sessions a killed service left open: their end time is their last
        keyframe's (when it was stored), or their start without keyframes."""
        why = as_end_reason(reason)
        with self.db.write("end_open_sessions") as c:
            ids = [r[0] for r in c.execute("SELECT id FROM sessions WHERE ended_at IS NULL ORDER BY id")]
            if ids:
                c.execute("UPDATE sessions SET end_reason = ?, ended_at = COALESCE("
                          "(SELECT MAX(n.time_enter) FROM nodes n WHERE n.session_id = sessions.id), started_at) "
                          "WHERE ended_at IS NULL", (why,))
                q = ",".join("?" * len(ids))
                rows = c.execute(f"SELECT {SESSION_COLUMNS} FROM sessions WHERE id IN ({q}) ORDER BY id",
                                 ids).fetchall()
            else:
                rows = []
        return [session_from_row(r) for r in rows]

    def sessions(self, robot: str | None = None) -> list[SessionRecord]:
        sql = f"SELECT {SESSION_COLUMNS} FROM sessions"
        params: tuple[str, ...] = ()
        if robot is not None:
            sql, params = sql + " WHERE robot = ?", (robot,)
        with self.db.read() as c:
            rows = c.execute(sql + " ORDER BY id", params).fetchall()
        return [session_from_row(r) for r in rows]

    def session(self, session_id: int) -> SessionRecord | None:
        with self.db.read() as c:
            row = c.execute(f"SELECT {SESSION_COLUMNS} FROM sessions WHERE id = ?",
                            (as_int(session_id, "session_id"),)).fetchone()
        return None if row is None else session_from_row(row)

    def calibration(self, session_id: int) -> Calibration:
        s = self.session(session_id)
        if s is None:
            raise UnknownIdError(f"no session {session_id}")
        return s.calibration

    def session_stats(self) -> dict[int, dict]:
        """{session id: {nodes, first_stamp, last_stamp}} for every session (one snapshot)."""
        with self.db.read(snapshot=True) as c:
            out = {r[0]: {"nodes": 0, "first_stamp": None, "last_stamp": None}
                   for r in c.execute("SELECT id FROM sessions ORDER BY id")}
            for sid, n, first, last in c.execute(
                    "SELECT session_id, COUNT(*), MIN(stamp), MAX(stamp) FROM nodes GROUP BY session_id"):
                out[sid] = {"nodes": n, "first_stamp": first, "last_stamp": last}
        return out

