"""Zenoh session configuration shared by the camera client and the service.

Defaults keep a deployment on one machine self-contained and predictable: the service is a
peer LISTENING on ``tcp/127.0.0.1:7447``; camera clients are peers CONNECTING to it; multicast
and gossip scouting are off, so nothing else has to be started (there is no zenohd router)
and two test runs on one machine never discover each other by accident. For robots on a
network, listen on ``tcp/0.0.0.0:7447`` in the service and connect the cameras to
``tcp/<service host>:7447``.

    from mnemoslam.client.transport import ZenohSettings, open_session
    session = open_session(ZenohSettings.client())             # connect to the local service
    session = open_session(ZenohSettings.service())            # listen on tcp/127.0.0.1:7447
    session = open_session(ZenohSettings(listen=["tcp/127.0.0.1:0"]))   # any free port

Close sessions explicitly (`session.close()` or `with open_session(...) as session:`).
Measured with eclipse-zenoh 1.10.2: a process that reaches interpreter shutdown with an open
session that has Python callbacks (subscriber, queryable) hangs forever: zenoh runs the
callbacks on a non-daemon Python thread that the interpreter waits for. `open_session`
therefore registers every session it opens and closes the ones still open when the main
thread ends (before threads are joined); a session dropped without `close()` stays alive
until then. Sessions opened with `zenoh.open` directly get no such help.

A peer whose `connect` endpoint is not up yet opens anyway and keeps retrying in the
background (so a camera may start before the service); a "client"-mode session fails at once
with `TransportError` instead. Shared memory is used automatically between processes on one
host for payloads above 3 KiB (zenoh's default) when BOTH sessions have it on
(`shared_memory`). Measured with eclipse-zenoh 1.10.2: each session that sends such payloads
makes a 16 MB shared-memory pool (`/dev/shm/<n>.zenoh`), and a receiver maps the pool of every
peer that sent it one and never unmaps it, even after that peer closed: a service receiving
frames from a new camera session every 30 s grew 16 MB of resident memory for each (issue 24).
The service therefore turns shared memory off for its session (`zenoh.shared_memory: false`);
frames then come over the socket (loopback on one host).
"""
from __future__ import annotations

import atexit
import json
import logging
import re
import threading
from dataclasses import dataclass, field

DEFAULT_PORT = 7447
log = logging.getLogger("mnemoslam.transport")

DEFAULT_ENDPOINT = f"tcp/127.0.0.1:{DEFAULT_PORT}"
MODES = ("peer", "client", "router")
_ENDPOINT = re.compile(r"[a-z0-9]+/\S+")
_LOCAL = re.compile(r"(tcp|udp|quic|tls)/(127\.\d+\.\d+\.\d+|localhost|\[::1\]):\d+(#.*)?$|(unixsock-stream|shm)/.+")


class TransportError(ConnectionError):
    """The Zenoh session cannot be opened (bad endpoint, nothing to connect to in client mode,
    port already in use)."""


@dataclass
class ZenohSettings:
    """How to open a Zenoh session. Endpoints are zenoh locators such as
    ``tcp/127.0.0.1:7447`` or ``tcp/[::1]:7447``."""

    mode: str = "peer"
    listen: list[str] = field(default_factory=list)
    connect: list[str] = field(default_factory=list)
    multicast_scouting: bool = False
    gossip_scouting: bool = False
    shared_memory: bool = True  # zenoh's shared-memory transport (both ends must have it on to use it)

    @classmethod
    def service(cls, listen: list[str] | None = None) -> "ZenohSettings":
        """The service's default: a peer listening on tcp/127.0.0.1:7447."""
        return cls(mode="peer", listen=list(listen) if listen else [DEFAULT_ENDPOINT])

    @classmethod
    def client(cls, connect: list[str] | None = None) -> "ZenohSettings":
        """A camera's default: a peer connecting to tcp/127.0.0.1:7447."""
        return cls(mode="peer", connect=list(connect) if connect else [DEFAULT_ENDPOINT])

    @property
    def local(self) -> bool:
        """True when every endpoint it connects to is on this host (loopback, unix socket or
        shared memory) and it discovers nothing by multicast: frames then need not be
        compressed (raw frames cost memory bandwidth, not CPU)."""
        return bool(self.connect) and not self.multicast_scouting and all(_LOCAL.match(e) for e in self.connect)

    def validate(self) -> "ZenohSettings":
        if self.mode not in MODES:
            raise ValueError(f"zenoh mode must be one of {', '.join(MODES)}, got {self.mode!r}")
        for name in ("listen", "connect"):
            eps = getattr(self, name)
            if isinstance(eps, str) or not all(isinstance(e, str) and _ENDPOINT.fullmatch(e) for e in eps):
                raise ValueError(f"zenoh {name} endpoints must be a list like ['tcp/127.0.0.1:7447'], got {eps!r}")
        return self

    def to_config(self):
        """The `zenoh.Config` of these settings."""
        import zenoh

        self.validate()
        conf = zenoh.Config()
        conf.insert_json5("mode", json.dumps(self.mode))
        conf.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
        conf.insert_json5("connect/endpoints", json.dumps(list(self.connect)))
        conf.insert_json5("scouting/multicast/enabled", json.dumps(bool(self.multicast_scouting)))
        conf.insert_json5("scouting/gossip/enabled", json.dumps(bool(self.gossip_scouting)))
        conf.insert_json5("transport/shared_memory/enabled", json.dumps(bool(self.shared_memory)))
        return conf


_open_sessions: list = []
_registry_lock = threading.Lock()


def _register(session) -> None:
    with _registry_lock:
        _open_sessions[:] = [s for s in _open_sessions if not _is_closed(s)]
        _open_sessions.append(session)


def _is_closed(session) -> bool:
    try:
        return session.is_closed()
    except Exception:
        return True


def close_all_sessions() -> None:
    """Close every session `open_session` opened that is still open (runs at exit)."""
    with _registry_lock:
        sessions, _open_sessions[:] = list(_open_sessions), []
    for s in sessions:
        try:
            if not s.is_closed():
                s.close()
        except Exception:
            pass


# zenoh-python runs Python callbacks on a non-daemon `threading` thread, and the interpreter
# joins those BEFORE running atexit handlers: the hook has to run before that join.
try:
    threading._register_atexit(close_all_sessions)  # the hook concurrent.futures uses
except (AttributeError, RuntimeError):  # pragma: no cover - other interpreters
    atexit.register(close_all_sessions)


def open_session(settings: ZenohSettings | None = None):
    """A `zenoh.Session` opened with `settings` (default `ZenohSettings.client()`).
    Raises ValueError for bad settings and TransportError when zenoh refuses to open."""
    import zenoh

    settings = settings if settings is not None else ZenohSettings.client()
    conf = settings.to_config()
    try:
        session = zenoh.open(conf)
    except zenoh.ZError as e:
        where = ", ".join([f"listen {x}" for x in settings.listen] + [f"connect {x}" for x in settings.connect])
        raise TransportError(f"cannot open a zenoh {settings.mode} session ({where or 'no endpoints'}): "
                             f"{str(e).split(' at ')[0]}") from None
    _register(session)
    return session


__all__ = ["DEFAULT_PORT", "DEFAULT_ENDPOINT", "MODES", "TransportError", "ZenohSettings", "open_session",
           "close_all_sessions"]


def undeclare_all(entities) -> None:
    """Undeclare Zenoh subscribers / publishers / queryables; one already gone with its closed
    session is skipped."""
    for entity in entities:
        try:
            entity.undeclare()
        except Exception as e:  # the session is closed already
            log.debug("undeclare failed: %s", e)
