"""Crash recovery at service start-up.

A service killed with kill -9 (or a power cut) leaves its sessions open and, behind
tracking, a map-update backlog: keyframes stored and reported (tracking commits each one
before it is reported) that never went through the map update (vocabulary, loop detection
and verification, graph, statistics). `recover`, called by `SlamService.start` before the
mapping process and the Zenoh subscriptions exist:

1. ends every session that did not end with reason "crashed" (one log line each);
2. for every crashed session with keyframes that have no map update (no statistics row:
   the map update's last write, `MapStore.unmapped_nodes`), resumes a mapper on the session
   (`Mapper.resume`: its graph holds the session's mapped keyframes and links at their
   stored poses, the map's vocabulary is loaded from the store) and runs the update of each
   such keyframe in id order, rebuilt from the database (`KeyframeUpdate.from_store`), so
   they close loops to the mapped ones as they would have. What an interrupted update had
   already written for a keyframe (loop links; its words are redone) is replaced.

It runs synchronously in the service's process while holding the map update's lock
(`mapping.process.map_update_lock`), so nothing else writes the vocabulary meanwhile and
the mapping child of the killed service, if it is still finishing an update, is waited
for. A keyframe whose update fails is logged and counted and stays unmapped (the next
start tries again); nothing here stops the service from starting. Sessions recorded
with the map update off (their stored config) are only ended. The map update runs with the
service's current `loop` configuration.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

from mnemoslam.storage import MapStore, SessionRecord
from mnemoslam.storage.store import MAP_UPDATE_LINKS

from .config import Config
from .mapping.mapper import KeyframeUpdate, Mapper
from .mapping.process import LOCK_WAIT_S, map_update_lock

log = logging.getLogger("mnemoslam.recovery")

_PROGRESS_S = 5.0  # a progress line at most this often per session


@dataclass
class RecoveryReport:
    crashed: list[int] = field(default_factory=list)  # sessions found open, now ended "crashed"
    sessions: int = 0  # crashed sessions whose backlog was worked on
    keyframes: int = 0  # keyframes of crashed sessions without their map update, found at start
    mapped: int = 0  # ... that have it now
    failed: int = 0  # ... whose update failed (logged; tried again at the next start)
    skipped: int = 0  # ... left alone: map update off, or its lock not acquired
    loops: int = 0  # loop closures (appearance or proximity) the recovered updates made
    seconds: float = 0.0
    error: str | None = None  # recovery stopped by an unexpected error (logged)


def recover(config: Config) -> RecoveryReport:
    """End the sessions a killed service left open and run the map update of their
    backlog (see the module docstring). Never raises: problems are logged and counted."""
    t0 = time.perf_counter()
    report = RecoveryReport()
    try:
        with MapStore(config.storage.path) as store:
            _recover(store, config, report)
    except Exception as e:  # noqa: BLE001 - start-up goes on with what is done
        log.exception("recovery stopped by an error: %s", e)
        report.error = f"{type(e).__name__}: {e}"
    report.seconds = time.perf_counter() - t0
    if report.crashed or report.keyframes or report.error:
        log.info("recovery done crashed_sessions=%d keyframes=%d mapped=%d failed=%d skipped=%d loops=%d "
                 "seconds=%.1f", len(report.crashed), report.keyframes, report.mapped, report.failed,
                 report.skipped, report.loops, report.seconds)
    return report


def _recover(store: MapStore, config: Config, report: RecoveryReport) -> None:
    for s in store.end_open_sessions("crashed"):
        report.crashed.append(s.id)
        log.warning("session crashed session=%d robot=%s keyframes=%d started_at=%.3f ended_at=%.3f "
                    "(open at start-up: ended with reason crashed)", s.id, s.robot,
                    store.count_nodes(session_id=s.id), s.started_at, s.ended_at)
    backlog = store.unmapped_nodes(end_reason="crashed")
    report.keyframes = sum(len(v) for v in backlog.values())
    if not backlog:
        return
    if not config.loop.enabled:
        log.info("recovery: map update disabled (loop.enabled false): %d keyframe(s) of crashed sessions stay "
                 "unmapped", report.keyframes)
        report.skipped = report.keyframes
        return
    log.info("recovery: map update of %d keyframe(s) of %d crashed session(s)", report.keyframes, len(backlog))
    with map_update_lock(config.storage.path) as locked:
        if not locked:
            log.error("recovery: the map update's lock of %s is held by another process after %.0f s "
                      "(a second service on this map?): backlog left for the next start",
                      config.storage.path, LOCK_WAIT_S)
            report.skipped = report.keyframes
            return
        for sid, node_ids in backlog.items():
            session = store.session(sid)
            if not ((session.config or {}).get("loop") or {}).get("enabled", True):
                report.skipped += len(node_ids)  # recorded without the map update: nothing to resume
                continue
            _recover_session(store, session, node_ids, config, report)


def _recover_session(store: MapStore, session: SessionRecord, node_ids: list[int], config: Config,
                     report: RecoveryReport) -> None:
    sid = session.id
    t0 = time.perf_counter()
    report.sessions += 1
    try:
        todo = _finish_merged(store, node_ids)
        report.mapped += len(node_ids) - len(todo)  # their update is complete now
        node_ids = todo
        redone = store.delete_links(node_ids, MAP_UPDATE_LINKS)  # what an interrupted update wrote
        mapper = Mapper.resume(store, sid, config.loop, memory=config.memory)
    except Exception:  # noqa: BLE001 - e.g. a corrupt stored graph: the other sessions go on
        log.exception("recovery: session %d cannot be resumed: %d keyframe(s) stay unmapped", sid, len(node_ids))
        report.failed += len(node_ids)
        return
    loops0 = len(mapper.loops)
    log.info("recovery session=%d robot=%s mapped=%d backlog=%d loops=%d resumed_in_s=%.1f%s", sid, session.robot,
             len(mapper.graph), len(node_ids), loops0, time.perf_counter() - t0,
             f" replaced_links={redone}" if redone else "")
    last = time.monotonic()
    failed = 0
    for k, nid in enumerate(node_ids, 1):
        try:
            u = KeyframeUpdate.from_store(store, nid, images=config.loop.refine_dense)
            if u.odom_from is not None and u.odom_from not in mapper.graph:
                log.warning("recovery: node %d: its odometry predecessor %d is not in the graph: starts a segment",
                            nid, u.odom_from)
                u.odom_from = u.transform = u.information = None
            mapper.submit(u)
            report.mapped += 1
        except Exception:  # noqa: BLE001 - one keyframe must not stop the others
            log.exception("recovery: map update of node %d (session %d) failed", nid, sid)
            report.failed += 1
            failed += 1
        if time.monotonic() - last >= _PROGRESS_S:
            last = time.monotonic()
            log.info("recovery session=%d progress=%d/%d loops=%d failed=%d", sid, k, len(node_ids),
                     len(mapper.loops) - loops0, failed)
    try:
        mapper.flush_poses()  # the database holds the graph's final estimate
    except Exception:  # noqa: BLE001
        log.exception("recovery: session %d: writing the final poses failed", sid)
    report.loops += len(mapper.loops) - loops0
    log.info("recovery session=%d robot=%s done keyframes=%d failed=%d loops=%d seconds=%.1f", sid, session.robot,
             len(node_ids), failed, len(mapper.loops) - loops0, time.perf_counter() - t0)


def _finish_merged(store: MapStore, node_ids: list[int]) -> list[int]:
    """Backlog keyframes whose rehearsal merge had committed before the interruption (the merge
    is one transaction: survivor, `merged` link, features gone) cannot be redone, and need not
    be: only their statistics row, the update's last write, is missing. Write it, so that
    `Mapper.resume` takes them as merged, and return the keyframes left to map."""
    merged = {n.id: n.merged_into for n in store.get_nodes(node_ids) if n.merged_into is not None}
    for nid, survivor in merged.items():
        store.set_statistics(nid, {"recovered": "merged before the interruption", "merged_into": survivor})
    if merged:
        log.info("recovery: %d keyframe(s) had been merged before the interruption: %s", len(merged), sorted(merged))
    return [n for n in node_ids if n not in merged]
