"""The service's map update in ONE child process at low CPU priority (loop.process).

On a thread of the service process the mapper competes with tracking for the cores and,
worse, for the GIL (GTSAM's calls hold it for 40-100 ms: bench/bench_mapper_gil.py). Here
every robot's `Mapper` lives in one spawned child (all mappers of a map share one
vocabulary, so they must share a process) that opens its own `MapStore` on the same
database (WAL: the service writes keyframes, the child writes words, links, corrected poses
and statistics) and runs at `os.nice(loop.process_nice)`.

The service side hands out one `MapperProxy` per robot session with the `Mapper` interface
the pipeline and the server use:

- `submit(update)` puts the keyframe update on a multiprocessing queue (pickled by the
  queue's feeder thread) and returns: tracking never waits for the map;
- `to_map(odom_pose)` applies the last map→odometry correction the child sent back for
  that robot (identity until the first one);
- `close(timeout)` waits until the child has worked through every update of that robot.

A reader thread receives the corrections and the mappers' events (`loop_closed`,
`map_corrected`) and hands each event to the robot's `on_event`, as the in-process mapper
does. If the child dies, tracking goes on with the last corrections: one error line is
logged, `failures` counts it (reported in the service's status) and later updates are
dropped (counted). The child exits when the service does, even after a kill -9 (it
watches its parent's pid, and starts no update once the service is gone: the keyframes
left in the backlog are mapped by the next start's recovery, service/recovery.py). It holds
the map update's lock (`map_update_lock`) while it runs, which that recovery waits for.
"""
from __future__ import annotations

import contextlib
import fcntl
import logging
import multiprocessing
import os
import queue
import signal
import threading
import time
from collections.abc import Callable, Iterator

import numpy as np

from mnemoslam.client.kernel.frames import PinholeCamera

from ..config import LoopConfig, MemoryConfig
from ..shutdown import exit_process
from .mapper import KeyframeUpdate

log = logging.getLogger("mnemoslam.mapping")

_PARENT_POLL_S = 1.0  # the child checks this often that the service still runs
_ORPHAN_GRACE_S = 30.0  # once the service is gone, the update in hand may take this long before the child exits
LOCK_WAIT_S = 60.0  # how long the child / the start-up recovery wait for the map update's lock


@contextlib.contextmanager
def map_update_lock(db_path, timeout: float = LOCK_WAIT_S) -> Iterator[bool]:
    """Hold the map update's lock of the database at `db_path`: an flock on
    `<db>-mapping.lock`, which the kernel releases when its holder exits, even by kill -9.
    The mapping process holds it for its lifetime and the start-up recovery
    (service.recovery) while it runs, so only one of them writes the map's words, links and
    statistics at a time: a child of a killed service that is still finishing its last
    update is waited for. Yields whether the lock was acquired within `timeout` seconds
    (the caller decides what to do without it).

    A holder removes the file when it lets go (while it still holds the lock), so nothing is
    left beside the database after a clean stop (a kill leaves it, harmless); one who locked
    a file that was removed meanwhile locks the new one instead (the inode under the name is
    checked after each lock)."""
    path = f"{db_path}-mapping.lock"
    deadline = time.monotonic() + timeout
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    acquired = False
    try:
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                try:
                    same = os.path.samestat(os.fstat(fd), os.stat(path))
                except FileNotFoundError:
                    same = False
                if same:
                    acquired = True
                    break
                os.close(fd)  # its holder removed it after we opened it: lock the current one
                fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
                continue
            except BlockingIOError:
                pass
            if time.monotonic() >= deadline:
                break
            time.sleep(0.05)
        yield acquired
    finally:
        if acquired:
            try:
                os.unlink(path)  # still held: whoever opens the name next makes a new file
            except OSError:
                pass
        os.close(fd)  # releases the lock


def _slim(update: KeyframeUpdate, keep_images: bool) -> KeyframeUpdate:
    """The update with only what the mapper keeps and uses (no colour image etc.)."""
    from ..tracking.features import FrameFeatures

    f = update.features
    features = FrameFeatures(f.keypoints, f.descriptors, f.points, f.octaves,
                             f.depth if keep_images else None, f.grey if keep_images else None,
                             f.depth_sigma, f.level_scale)
    return KeyframeUpdate(update.node_id, update.stamp, update.odom_pose, features, update.odom_from,
                          update.transform, update.information, update.point_ids)


# -- child process -------------------------------------------------------------------------

def _watch_parent(parent_pid: int, busy: threading.Event) -> None:
    """End the child once the service is gone (and the update in hand is done, for at most
    `_ORPHAN_GRACE_S`). A thread, not the main loop: when the service dies in the middle of
    putting a message, the child's read of the inbox blocks for good (the child holds the
    queue's write end too, so no EOF comes). os._exit is as safe as a kill for the database;
    the keyframes left unmapped are the next start's recovery's."""
    while os.getppid() == parent_pid:
        time.sleep(_PARENT_POLL_S)
    log.error("mapping process: the service (pid %d) is gone, exiting", parent_pid)
    deadline = time.monotonic() + _ORPHAN_GRACE_S
    while busy.is_set() and time.monotonic() < deadline:
        time.sleep(0.05)
    logging.shutdown()
    os._exit(0)


def _child_main(db_path: str, config: LoopConfig, inbox, conn, parent_pid: int, log_level: int,
                memory: MemoryConfig | None = None) -> None:
    """Host one Mapper per robot key; messages in: ("open", key, camera), ("update", key,
    KeyframeUpdate), ("close", key), None = drain and stop. Messages out over `conn`:
    ("ready", pid), ("correction", key, T_map_odom), ("event", key, kind, data),
    ("closed", key, updates), ("stopped",)."""
    for sig in (signal.SIGINT, signal.SIGTERM):  # Ctrl-C, timeout(1), systemd reach the whole group:
        signal.signal(sig, signal.SIG_IGN)  # the service decides when we stop (we exit when it is gone)
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s")  # as the CLI's
    logging.getLogger("mnemoslam").setLevel(log_level)
    if config.process_nice:
        try:
            os.nice(config.process_nice)
        except OSError as e:
            log.warning("mapping process: os.nice(%d) failed: %s", config.process_nice, e)
    from mnemoslam.storage import MapStore

    from .mapper import Mapper

    send_lock = threading.Lock()

    def send(msg) -> None:
        with send_lock:
            conn.send(msg)

    busy = threading.Event()  # a message is being handled
    threading.Thread(target=_watch_parent, args=(parent_pid, busy), name="mapping-parent-watch", daemon=True).start()
    lock = contextlib.ExitStack()
    if not lock.enter_context(map_update_lock(db_path)):
        log.error("mapping process: another process held the map update's lock of %s for %.0f s "
                  "(a second service on this map?): mapping anyway", db_path, LOCK_WAIT_S)
    store = MapStore(db_path, create=False)
    cameras: dict[str, PinholeCamera] = {}
    mappers: dict[str, Mapper] = {}
    counts: dict[str, int] = {}
    send(("ready", os.getpid()))
    log.info("mapping process started pid=%d nice=%d db=%s", os.getpid(), config.process_nice, db_path)
    try:
        while True:
            try:
                msg = inbox.get(timeout=_PARENT_POLL_S)
            except queue.Empty:
                continue
            if os.getppid() != parent_pid:
                continue  # the service is gone: start nothing (_watch_parent ends the process)
            if msg is None:
                break
            busy.set()
            try:
                _handle(msg, config, memory, store, cameras, mappers, counts, send)
            finally:
                busy.clear()
        send(("stopped",))
    except (BrokenPipeError, EOFError, OSError):
        pass  # the service closed its end
    finally:
        store.close()
        lock.close()
    # every message answered and the database closed: skip Python's finalization (service/shutdown.py),
    # which the service's stop would wait for
    exit_process(0)


def _handle(msg, config, memory, store, cameras, mappers, counts, send) -> None:
    from .mapper import Mapper

    op, key = msg[0], msg[1]
    if op == "open":
        cameras[key] = msg[2]
    elif op == "update":
        u: KeyframeUpdate = msg[2]
        m = mappers.get(key)
        if m is None:
            def on_event(kind: str, data: dict, k=key) -> None:
                send(("event", k, kind, data))

            m = mappers[key] = Mapper(cameras[key], config, store, background=False, memory=memory,
                                      on_event=on_event)
        try:
            m.submit(u)
        except Exception:  # a failed map update must not stop the mapper
            log.exception("map update of node %d failed (robot key %s)", u.node_id, key)
        counts[key] = counts.get(key, 0) + 1
        send(("correction", key, m.to_map(np.eye(4))))
    elif op == "close":
        m = mappers.pop(key, None)
        if m is not None:
            m.close()  # the graph's final poses to the database
        cameras.pop(key, None)
        send(("closed", key, counts.pop(key, 0)))


# -- service side --------------------------------------------------------------------------

class MapperProxy:
    """One robot's mapper in the mapping process, with the Mapper interface."""

    def __init__(self, owner: MappingProcess, key: str, on_event: Callable[[str, dict], None]):
        self._owner = owner
        self.key = key
        self.on_event = on_event
        self._correction = np.eye(4)
        self._lock = threading.Lock()
        self._closed = threading.Event()
        self.submitted = 0
        self.mapped = 0  # corrections received (= updates done by the child)

    def submit(self, update: KeyframeUpdate) -> None:
        if self._owner._send(("update", self.key, _slim(update, self._owner.config.refine_dense))):
            self.submitted += 1
            with self._owner._lock:
                self._owner.submitted += 1

    def to_map(self, odom_pose: np.ndarray) -> np.ndarray:
        with self._lock:
            return self._correction @ odom_pose

    @property
    def correction(self) -> np.ndarray:
        with self._lock:
            return self._correction.copy()

    def close(self, timeout: float = 30.0) -> bool:
        """Wait until the child has done every update submitted for this robot (True), or the
        child is gone / `timeout` passed (False)."""
        if not self._owner._send(("close", self.key)):
            self._owner._forget(self.key)
            return False
        done = self._closed.wait(timeout)
        self._owner._forget(self.key)
        return done

    # reader thread
    def _set_correction(self, t: np.ndarray) -> None:
        with self._lock:
            self._correction = t
            self.mapped += 1
            self._owner.mapped += 1


class MappingProcess:
    """One child process hosting every robot's mapper of the map at `db_path`."""

    def __init__(self, db_path, config: LoopConfig, memory: MemoryConfig | None = None):
        self.db_path = str(db_path)
        self.config = config
        self.failures = 0  # times the child died while the service ran
        self.dropped = 0  # updates not sent because the child was gone
        self.submitted = 0  # keyframe updates sent to the child (all robots)
        self.mapped = 0  # ... and done by it
        self._proxies: dict[str, MapperProxy] = {}
        self._lock = threading.Lock()
        self._next = 0
        self._alive = True
        self._stopping = False
        self._stopped = threading.Event()
        self._ready = threading.Event()
        self.pid: int | None = None
        ctx = multiprocessing.get_context("spawn")
        self._inbox = ctx.Queue()
        recv_end, send_end = ctx.Pipe(duplex=False)
        self._proc = ctx.Process(target=_child_main, name="mnemoslam-mapping", daemon=True,
                                 args=(self.db_path, config, self._inbox, send_end, os.getpid(),
                                       logging.getLogger("mnemoslam").getEffectiveLevel(), memory))
        self._proc.start()
        send_end.close()  # ours: so the reader sees EOF when the child dies
        self._conn = recv_end
        self.pid = self._proc.pid
        self._reader = threading.Thread(target=self._read, name="mapping-process-reader", daemon=True)
        self._reader.start()
        log.info("mapping process spawned pid=%d nice=%d", self.pid, config.process_nice)

    @property
    def alive(self) -> bool:
        return self._alive and self._proc.is_alive()

    def mapper(self, robot: str, camera: PinholeCamera,
               on_event: Callable[[str, dict], None] | None = None) -> MapperProxy:
        """A new mapper for one robot session (its mapper is created in the child on its first update)."""
        with self._lock:
            self._next += 1
            key = f"{robot}#{self._next}"
            proxy = self._proxies[key] = MapperProxy(self, key, on_event or (lambda kind, data: None))
        self._send(("open", key, camera))
        return proxy

    def wait_ready(self, timeout: float | None = None) -> bool:
        """Until the child has imported the mapper and opened the map (benchmarks start their clock after)."""
        return self._ready.wait(timeout)

    def stats(self) -> dict:
        return {"alive": self.alive, "pid": self.pid, "failures": self.failures, "dropped_updates": self.dropped,
                "submitted": self.submitted, "mapped": self.mapped, "robots": len(self._proxies)}

    def close(self, timeout: float = 60.0) -> None:
        """Let the child finish every queued update, then stop it (terminated after `timeout`)."""
        self._stopping = True
        if self._alive:
            try:
                self._inbox.put(None)
            except (ValueError, OSError):
                pass
        self._proc.join(timeout)
        if self._proc.is_alive():
            log.error("mapping process pid=%d did not stop in %.0f s: terminated", self.pid, timeout)
            self._proc.terminate()
            self._proc.join(5)
        self._reader.join(5)
        self._conn.close()
        self._inbox.close()
        self._inbox.join_thread()

    # -- internals -------------------------------------------------------------------------
    def _send(self, msg) -> bool:
        if not self._alive:
            self.dropped += msg[0] == "update"
            return False
        try:
            self._inbox.put(msg)
            return True
        except (ValueError, OSError):  # queue closed
            self.dropped += msg[0] == "update"
            return False

    def _forget(self, key: str) -> None:
        with self._lock:
            self._proxies.pop(key, None)

    def _read(self) -> None:
        while True:
            try:
                msg = self._conn.recv()
            except Exception:  # noqa: BLE001 - EOF: the child is gone (or died mid-message)
                break
            kind = msg[0]
            if kind == "stopped":
                self._stopped.set()
                continue
            if kind == "ready":
                self._ready.set()
                continue
            proxy = self._proxies.get(msg[1])
            if proxy is None:
                continue
            if kind == "correction":
                proxy._set_correction(msg[2])
            elif kind == "event":
                try:
                    proxy.on_event(msg[2], msg[3])
                except Exception:
                    log.exception("mapping process: event handler failed for %s", msg[1])
            elif kind == "closed":
                proxy._closed.set()
        self._alive = False
        self._inbox.cancel_join_thread()  # a dead child reads nothing: do not wait to flush to it
        if not self._stopped.is_set():  # the child died (crash, kill) instead of stopping when asked
            self._proc.join(1.0)
            self.failures += 1
            log.error("mapping process died pid=%d exitcode=%s failures=%d robots=%d: tracking continues "
                      "with the last map corrections, later keyframes are not mapped",
                      self.pid, self._proc.exitcode, self.failures, len(self._proxies))
        for p in list(self._proxies.values()):  # nobody waits for a dead child
            p._closed.set()
