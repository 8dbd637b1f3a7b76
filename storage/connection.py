"""Connection and checkpointing of the long-term memory: `Connection` opens the file (its
pragmas), owns the writer connection and the pool of reader connections, the `write` /
`read` transactions every part of the store goes through, the background WAL
checkpointer, the schema migrations, the `admin` key-value table and closing. Its state
(connections, locks, the commit count) is touched nowhere else: the parts `MapStore` is
composed of (`storage.sessions`, `storage.nodes`, `storage.queries`, `storage.words`,
`storage.objects`: each a `Part` holding the one `Connection`) use only `write`, `read`,
`rtree` and `path`.

Durability: WAL journal with synchronous=NORMAL. A transaction is durable against a
process crash (kill -9) once COMMIT returns; `add_keyframe` returns only after COMMIT, so
a reported node id is always in the file. (A power loss may drop the last few commits but
never corrupts the file.)

Threads: every method may be called from any thread. Writes go through one connection
behind a lock, each in one `BEGIN IMMEDIATE` transaction; reads use a pool of separate
connections, so in WAL mode they never wait for a writer and see the last committed state.
WAL checkpoints (copying the WAL into the database file, with its fsyncs) run in a
background thread instead of inside a commit, which keeps add_keyframe's p99 near its
median; when writes outpace it, it briefly holds the writer off so the WAL stays bounded
(~16 MB). Other processes may open the same file (e.g. `mnemoslam db info` while the
service runs): writers then queue on SQLite's lock for up to `busy_timeout` seconds.
"""
from __future__ import annotations

import json
import logging
import sqlite3
import threading
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator, Self

import sqlite_utils

from . import schema
from .codec import to_json
from .records import StoreError

log = logging.getLogger("mnemoslam.storage")


class Connection:
    """One SQLite file opened for the long-term memory: the writer connection, the reader
    pool, the checkpointer and the schema. See the module docstring for the durability and
    threading guarantees."""

    def __init__(self, path: str | Path, *, create: bool = True, busy_timeout: float = 10.0,
                 migrations: tuple[schema.Migration, ...] = schema.MIGRATIONS, readonly: bool = False):
        if str(path) in ("", ":memory:") or str(path).startswith("file:"):
            raise ValueError(f"MapStore needs a file path, got {str(path)!r}")
        self.path = Path(path)
        self.busy_timeout = float(busy_timeout)
        #: migrations[i] upgrades schema version i to i + 1; the current version is their count.
        self.migrations = tuple(migrations)
        if self.path.is_dir():
            raise StoreError(f"{self.path} is a directory, not a database file")
        #: opened read-only (localization, memory.incremental: false): every connection is
        #: `mode=ro`, nothing is migrated, checkpointed or optimised, and a write is a StoreError,
        #: so the database file's bytes stay as they were (SQLite may make empty -wal / -shm
        #: files beside a WAL database: it needs them to read it)
        self.readonly = bool(readonly)
        if readonly:
            create = False
        if not create and not self.path.exists():
            raise StoreError(f"no database at {self.path}")
        if create:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lock = threading.RLock()  # the writer connection
        self._pool_lock = threading.Lock()
        self._idle: list[sqlite3.Connection] = []
        self._closed = False
        self._commits = 0  # since the last checkpoint
        self._checkpoint_wake = threading.Event()
        self._checkpointer: threading.Thread | None = None
        self._writer = self._connect("ro" if readonly else "rwc" if create else "rw")
        try:
            if readonly:
                self._wal = False  # (no checkpointer: this connection writes nothing)
                self._check_version()
            else:
                self._configure_writer()
                self._utils = sqlite_utils.Database(self._writer, execute_plugins=False)  # (the migrations')
                self._migrate(create)
            self.rtree = self._writer.execute(
                "SELECT 1 FROM sqlite_master WHERE name = 'nodes_rtree'").fetchone() is not None
            if self.rtree and not schema.has_rtree(self._writer):
                raise StoreError(f"{self.path} uses an R*Tree index but this SQLite build has no R*Tree module")
        except BaseException:
            self._closed = True
            self._writer.close()
            raise
        if self._wal:
            self._checkpointer = threading.Thread(target=self._checkpoint_loop, daemon=True,
                                                  name=f"mnemoslam-checkpoint-{self.path.name}")
            self._checkpointer.start()

    # -- connections ------------------------------------------------------------------------
    def _connect(self, mode: str) -> sqlite3.Connection:
        uri = self.path.resolve().as_uri() + f"?mode={mode}"
        try:
            conn = sqlite3.connect(uri, uri=True, timeout=self.busy_timeout, isolation_level=None,
                                   check_same_thread=False)
        except sqlite3.Error as e:
            raise StoreError(f"cannot open database {self.path}: {e}") from e
        try:
            conn.execute("PRAGMA foreign_keys = ON")
            conn.execute("PRAGMA synchronous = NORMAL")
        except sqlite3.DatabaseError as e:
            conn.close()
            raise StoreError(f"{self.path} is not a SQLite database ({e})") from e
        return conn

    def _configure_writer(self) -> None:
        try:
            mode = self._writer.execute("PRAGMA journal_mode = WAL").fetchone()[0]
            self._writer.execute("PRAGMA journal_size_limit = 67108864")  # truncate the WAL to 64 MB after checkpoints
        except sqlite3.DatabaseError as e:
            raise StoreError(f"{self.path} is not a SQLite database ({e})") from e
        self._wal = mode.lower() == "wal"
        if self._wal:
            # Checkpoints (WAL -> database file, with fsyncs) run in a background thread so a
            # commit never pays for one: p99 of add_keyframe drops from ~7 ms to < 1 ms.
            self._writer.execute("PRAGMA wal_autocheckpoint = 0")
        else:
            log.warning("%s: journal_mode is %s, not WAL (file system without shared memory?): "
                        "readers will wait for writers", self.path, mode)

    CHECKPOINT_COMMITS = 32  # wake the checkpointer after this many commits
    CHECKPOINT_PERIOD = 2.0  # seconds; and at least this often when there were commits
    WAL_PAGES = 4096  # WAL size (pages, 16 MB at 4 kB) past which a checkpoint briefly holds the writer

    def _checkpoint_loop(self) -> None:
        try:
            conn = self._connect("rw")
        except StoreError as e:  # pragma: no cover - the writer opened the same file
            log.warning("checkpointer not started: %s; falling back to automatic checkpoints", e)
            with self._lock:
                if not self._closed:
                    self._writer.execute("PRAGMA wal_autocheckpoint = 1000")
            return
        try:
            while True:
                self._checkpoint_wake.wait(self.CHECKPOINT_PERIOD)
                self._checkpoint_wake.clear()
                if self._closed:
                    return
                if self._commits == 0:
                    continue
                self._commits = 0
                try:
                    # PASSIVE: copies what is committed, never waits for (nor blocks) the
                    # writer or readers.
                    (_, wal_pages, _), = conn.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchall()
                    if wal_pages > self.WAL_PAGES:
                        # The WAL restarts from its beginning only when a write starts after a
                        # checkpoint has caught up with it, which never happens under
                        # continuous writes. Catch up without the lock while that shrinks the
                        # tail, then finish the rest with the writer held off, so the WAL
                        # stays bounded.
                        for _ in range(4):
                            (_, now, _), = conn.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchall()
                            tail, wal_pages = now - wal_pages, now
                            if tail < 256:
                                break
                        with self._lock:
                            if self._closed:
                                return
                            conn.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchall()
                except sqlite3.Error as e:
                    log.warning("%s: WAL checkpoint failed: %s", self.path, e)
        finally:
            conn.close()

    def checkpoint(self) -> tuple[int, int]:
        """Copy the whole WAL into the database file now, holding writers off meanwhile, so
        the next write restarts the WAL from its beginning. The background checkpointer
        normally does this; returns (WAL pages, pages checkpointed)."""
        deadline = time.monotonic() + self.busy_timeout
        with self._lock:
            self._check_open()
            try:
                while True:
                    (busy, pages, done), = self._writer.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchall()
                    if not busy or time.monotonic() > deadline:
                        break
                    time.sleep(0.002)  # another checkpoint (the background one) is running
            except sqlite3.Error as e:
                raise StoreError(f"checkpoint of {self.path}: {e}") from e
        if busy:
            raise StoreError(f"checkpoint of {self.path}: another checkpoint kept running for {self.busy_timeout:g} s")
        return pages, done

    def _check_open(self) -> None:
        if self._closed:
            raise StoreError(f"the store {self.path} is closed")

    @contextmanager
    def write(self, what: str) -> Iterator[sqlite3.Connection]:
        """One write transaction (BEGIN IMMEDIATE … COMMIT) on the writer connection; rolled
        back on any exception. sqlite3 errors come out as StoreError."""
        with self._lock:
            self._check_open()
            if self.readonly:
                raise StoreError(f"{what}: {self.path} is open read-only (localization: memory.incremental is false)")
            conn = self._writer
            try:
                conn.execute("BEGIN IMMEDIATE")
            except sqlite3.Error as e:
                raise StoreError(f"{what}: cannot start a write transaction on {self.path}: {e}") from e
            try:
                yield conn
                conn.execute("COMMIT")
                self._commits += 1
                if self._commits >= self.CHECKPOINT_COMMITS:
                    self._checkpoint_wake.set()
            except BaseException as e:
                if conn.in_transaction:
                    conn.execute("ROLLBACK")
                if isinstance(e, sqlite3.Error):
                    raise StoreError(f"{what}: {e}") from e
                raise

    @contextmanager
    def read(self, snapshot: bool = False) -> Iterator[sqlite3.Connection]:
        """A pooled read connection; with `snapshot`, all its queries see one committed state."""
        self._check_open()
        with self._pool_lock:
            conn = self._idle.pop() if self._idle else None
        if conn is None:
            conn = self._connect("ro" if self.readonly else "rw")
            conn.execute("PRAGMA query_only = ON")
        try:
            if snapshot:
                conn.execute("BEGIN")
            yield conn
        except sqlite3.Error as e:
            raise StoreError(f"reading {self.path}: {e}") from e
        finally:
            if conn.in_transaction:
                conn.execute("COMMIT")
            with self._pool_lock:
                if self._closed:
                    conn.close()
                else:
                    self._idle.append(conn)

    def close(self) -> None:
        """Close every connection (idempotent). In-flight reads finish on their own. The
        last connection to close checkpoints the WAL into the database file."""
        with self._lock:
            if self._closed:
                return
            self._closed = True  # from here on no write starts and no read connection is lent
        if self._checkpointer is not None:  # (outside the lock: the checkpointer may want it)
            self._checkpoint_wake.set()
            self._checkpointer.join(10)
        with self._lock:
            with self._pool_lock:
                idle, self._idle = self._idle, []
            for c in idle:
                c.close()
            if not self.readonly:
                try:
                    self._writer.execute("PRAGMA optimize")
                except sqlite3.Error:
                    pass
            self._writer.close()

    @property
    def closed(self) -> bool:
        return self._closed

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- schema -----------------------------------------------------------------------------
    @property
    def current_version(self) -> int:
        """The schema version this code writes (the number of migrations)."""
        return len(self.migrations)

    @property
    def schema_version(self) -> int:
        """The schema version stored in the file."""
        with self.read() as c:
            return c.execute("PRAGMA user_version").fetchone()[0]

    def _check_version(self) -> None:
        """(read-only) The file must be a mnemoslam database of this code's schema version: a
        read-only store migrates nothing."""
        try:
            version = self._writer.execute("PRAGMA user_version").fetchone()[0]
        except sqlite3.DatabaseError as e:
            raise StoreError(f"{self.path} is not a SQLite database ({e})") from e
        if version > self.current_version:
            raise StoreError(self._newer_message(version))
        if version == 0:
            raise StoreError(f"{self.path} is not a mnemoslam database (no schema)")
        if version < self.current_version:
            raise StoreError(f"{self.path} has schema version {version}; this mnemoslam writes "
                             f"{self.current_version} and opens it read-only (localization) only once it "
                             f"is migrated: open it once for mapping (e.g. `mnemoslam db info`)")

    def _migrate(self, create: bool) -> None:
        target = self.current_version
        c = self._writer
        try:
            version = c.execute("PRAGMA user_version").fetchone()[0]
            tables = [r[0] for r in c.execute(
                "SELECT name FROM sqlite_master WHERE type = 'table' AND name NOT LIKE 'sqlite_%'")]
        except sqlite3.DatabaseError as e:
            raise StoreError(f"{self.path} is not a SQLite database ({e})") from e
        if version > target:
            raise StoreError(self._newer_message(version))
        if version == 0:
            if tables:
                raise StoreError(f"{self.path} is not a mnemoslam database "
                                 f"(it has tables {', '.join(sorted(tables)[:5])} but no mnemoslam schema version)")
            if not create:
                raise StoreError(f"{self.path} is not a mnemoslam database (no schema)")
        while True:
            with self.write("schema migration") as c:
                # Re-read under the write lock: another process may have migrated meanwhile.
                version = c.execute("PRAGMA user_version").fetchone()[0]
                if version > target:
                    raise StoreError(self._newer_message(version))
                if version == target:
                    break
                log.info("%s: migrating schema v%d -> v%d (%s)", self.path, version, version + 1,
                         getattr(self.migrations[version], "__name__", "migration"))
                self.migrations[version](self._utils)
                c.execute(f"PRAGMA user_version = {version + 1}")
                c.execute("INSERT OR REPLACE INTO admin (key, value) VALUES ('schema_version', ?)",
                          (json.dumps(version + 1),))
                if version == 0:
                    c.execute("INSERT OR REPLACE INTO admin (key, value) VALUES ('created_at', ?)",
                              (json.dumps(time.time()),))

    def _newer_message(self, version: int) -> str:
        return (f"{self.path} has schema version {version}, newer than this mnemoslam knows "
                f"(up to {self.current_version}): upgrade mnemoslam to open it")

    def get_info(self, key: str, default: Any = None) -> Any:
        """A value of the `admin` key-value table (JSON-decoded)."""
        with self.read() as c:
            row = c.execute("SELECT value FROM admin WHERE key = ?", (key,)).fetchone()
        return default if row is None or row[0] is None else json.loads(row[0])

    def set_info(self, key: str, value: Any) -> None:
        """Store a JSON-encodable value in the `admin` key-value table."""
        if not isinstance(key, str) or not key:
            raise ValueError("info key must be a non-empty string")
        text = to_json(value, f"info[{key!r}]")
        with self.write("set_info") as c:
            c.execute("INSERT OR REPLACE INTO admin (key, value) VALUES (?, ?)", (key, text))


    def change_counter(self) -> ChangeCounter:
        """A cheap change counter of the file (see `ChangeCounter`); close it when done."""
        self._check_open()
        return ChangeCounter(self.path)


class ChangeCounter:
    """`PRAGMA data_version` of the file on a read-only connection of its own: calling it
    gives a number that changes whenever another connection or process commits (the store's
    own writer included), for a cache of the map that rebuilds when it changed
    (`service.semantics.queries.ObjectIndex`). Any thread; StoreError once closed."""

    def __init__(self, path: Path):
        self.path = path
        try:
            self._conn = sqlite3.connect(f"{path.resolve().as_uri()}?mode=ro", uri=True, check_same_thread=False)
        except sqlite3.Error as e:
            raise StoreError(f"cannot open {path} for its change counter: {e}") from e
        self._lock = threading.Lock()

    def __call__(self) -> int:
        with self._lock:
            try:
                return self._conn.execute("PRAGMA data_version").fetchone()[0]
            except sqlite3.Error as e:
                raise StoreError(f"change counter of {self.path}: {e}") from e

    def close(self) -> None:
        with self._lock:
            self._conn.close()


class Part:
    """One part of `MapStore` (a group of tables and the methods on them), on the store's one
    `Connection`: its reads and writes go through `db.read()` / `db.write()`."""

    def __init__(self, db: Connection):
        self.db = db
