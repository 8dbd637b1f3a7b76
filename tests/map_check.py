"""The consistency check of a map database, for tests that kill or interrupt the writers of
the node life cycle (keyframe commit, map update, memory transfer / retrieval, and later
merges): `check_map(path, committed)` raises AssertionError naming every problem found.

What a consistent map is, whatever happened to the process that wrote it:

- SQLite's `PRAGMA integrity_check` and `foreign_key_check` are clean (`MapStore.integrity_check`);
- no committed node is lost: every id in `committed` (nodes whose commit was reported, nodes
  seen at an earlier check) is still a node;
- every node belongs to a session, has a finite rigid pose, its features load
  (`MapStore.load_features`: counts and blobs agree) and every word id they point at is a
  stored word; its images load; a keyframe merged by rehearsal instead has a survivor that is
  a node of the map, a `merged` link from it, and neither features nor images;
- every link's endpoints are nodes, its transform is finite and rigid; a node has at most
  one incoming odometry link, from a node of its own session;
- every statistics row parses; the memory moves it records (`memory.transferred`,
  `memory.retrieved`) name nodes that exist: a node in long-term memory lives in the
  database only, so one that left RAM must be there; `memory.merged` holds ids (a merge may
  delete its node: callers that merge leave those out of `committed`);
- with `mapped=True` (after recovery): no session is open and every node has its map update
  (`MapStore.unmapped_nodes` is empty).
"""
from __future__ import annotations

import json
import sqlite3
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mnemoslam.storage import LinkType, MapStore


@dataclass
class MapCheck:
    nodes: set[int]
    sessions: dict[int, str | None]  # session id -> end reason (None: open)
    unmapped: dict[int, list[int]]  # session id -> node ids without their map update
    statistics: dict[int, dict] = field(default_factory=dict)  # node id -> parsed statistics

    def moves(self, session_nodes) -> tuple[int, int]:
        """(transfers, retrievals) the stored map updates of these nodes recorded."""
        t = r = 0
        for n in session_nodes:
            m = (self.statistics.get(n) or {}).get("memory") or {}
            t += len(m.get("transferred", ()))
            r += len(m.get("retrieved", ()))
        return t, r


def _rigid(T: np.ndarray) -> bool:
    return (T.shape == (4, 4) and bool(np.isfinite(T).all()) and np.allclose(T[3], [0, 0, 0, 1])
            and np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6))


def check_map(path: str | Path, committed=(), *, mapped: bool = False) -> MapCheck:
    """Check the map at `path` (see the module docstring); returns what it read."""
    problems: list[str] = []
    with MapStore(path, create=False) as store:
        integrity = store.integrity_check()
        if integrity != "ok":
            problems.append(f"integrity: {integrity}")
        sessions = {s.id: s.end_reason for s in store.sessions()}
        nodes = {n.id: n for n in store.nodes(limit=None)}
        lost = sorted(set(committed) - set(nodes))
        if lost:
            problems.append(f"{len(lost)} committed node(s) lost: {lost[:20]}")
        with sqlite3.connect(f"file:{Path(path)}?mode=ro", uri=True) as raw:
            words = {r[0] for r in raw.execute("SELECT id FROM words")}
            stat_ids = [r[0] for r in raw.execute("SELECT node_id FROM statistics")]
        raw.close()
        for nid, n in nodes.items():
            if n.session_id not in sessions:
                problems.append(f"node {nid}: no session {n.session_id}")
            if not _rigid(n.pose):
                problems.append(f"node {nid}: pose not rigid/finite")
            if n.merged_into is not None:
                survivor = nodes.get(n.merged_into)
                if survivor is None or survivor.merged_into is not None:
                    problems.append(f"node {nid}: merged into {n.merged_into}, which is not a node of the map")
                if not store.links(node_ids=[nid], type=LinkType.MERGED):
                    problems.append(f"node {nid}: merged without a merged link")
                if store.load_images(nid) != (None, None):
                    problems.append(f"node {nid}: merged but its images are still stored")
                continue
            try:
                kp, desc, pts, word_ids = store.load_features(nid)
                if not (len(kp) == len(desc) == len(pts)) or (word_ids is not None and len(word_ids) != len(kp)):
                    problems.append(f"node {nid}: feature arrays disagree")
                if word_ids is not None:
                    unknown = set(word_ids[word_ids >= 0].tolist()) - words
                    if unknown:
                        problems.append(f"node {nid}: {len(unknown)} word id(s) not stored, e.g. {sorted(unknown)[:5]}")
                store.load_images(nid)
            except Exception as e:  # noqa: BLE001 - every problem is reported
                problems.append(f"node {nid}: features/images do not load: {type(e).__name__}: {e}")
        incoming: dict[int, int] = {}
        for link in store.links():
            a, b = link.from_id, link.to_id
            if a not in nodes or b not in nodes:
                problems.append(f"link {a}->{b} type {link.type}: endpoint missing")
                continue
            if not _rigid(link.transform) or not np.isfinite(link.information).all():
                problems.append(f"link {a}->{b} type {link.type}: transform/information not finite/rigid")
            if link.type == LinkType.NEIGHBOR:
                incoming[b] = incoming.get(b, 0) + 1
                if nodes[a].session_id != nodes[b].session_id:
                    problems.append(f"odometry link {a}->{b} crosses sessions")
        problems += [f"node {b}: {k} incoming odometry links" for b, k in incoming.items() if k > 1]
        statistics = {}
        for nid in stat_ids:
            try:
                st = store.statistics(nid)
                statistics[nid] = st
            except (json.JSONDecodeError, TypeError, ValueError) as e:
                problems.append(f"statistics of node {nid} do not parse: {e}")
                continue
            if not isinstance(st, dict):
                problems.append(f"statistics of node {nid}: not an object")
                continue
            mem = st.get("memory")
            if not mem:  # rows written without the map update (e.g. by add_keyframe) carry no memory dict
                continue
            for key in ("transferred", "retrieved", "merged"):
                ids = mem.get(key, [])
                if not isinstance(ids, list) or not all(isinstance(i, int) for i in ids):
                    problems.append(f"statistics of node {nid}: memory.{key} is not a list of ids: {ids!r}")
                elif key != "merged" and set(ids) - set(nodes):
                    problems.append(f"statistics of node {nid}: memory.{key} names missing node(s) "
                                    f"{sorted(set(ids) - set(nodes))}")
        unmapped = store.unmapped_nodes()
        if mapped:
            still_open = [s for s, why in sessions.items() if why is None]
            if still_open:
                problems.append(f"session(s) still open: {still_open}")
            if unmapped:
                problems.append(f"node(s) without their map update: {unmapped}")
    assert not problems, f"map {path} is not consistent:\n  " + "\n  ".join(problems)
    return MapCheck(set(nodes), sessions, unmapped, statistics)
