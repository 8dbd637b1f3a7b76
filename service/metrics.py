"""Prometheus metrics of the service, served as GET /metrics (service/api/routes/service.py).

Nothing here keeps counts of its own beside the service's: a collector reads, at scrape time,
what the REST API already shows — the service's counters (`SlamService.status()`), each
robot's session (`SlamService.robots()`: frames received / processed / dropped / rejected by
reason, queue depth, state, ...) — and, from the map's database, the per-keyframe statistics
the map update writes (its time, STM / WM / LTM sizes after it) and the loop-closure links.
The map update's histogram is cumulative over a robot's session: each scrape reads only the
statistics rows written since the previous one. REST latency is the one thing measured here
(a histogram by route template, method and status, from a small ASGI middleware), since
nothing else measures it.

Label sets stay bounded: robots are bounded by `service.max_robots` (a robot's series go
when its session ends, and counters restart with its next session, which Prometheus reads as
a counter reset), routes are the API's templates (`unmatched` for any other path), methods
the HTTP ones (`other` for the rest).

Metric names (prefix `mnemoslam_`; counters end in `_total`):
- service: `uptime_seconds`, `robots`, `robot_slots`, `messages_rejected_total{reason}`
  (every refused message, robots without a slot included), `mapping_process_up`,
  `mapping_process_failures_total`, `mapping_updates_dropped_total`;
- per robot (`robot`): `frames_received_total`, `frames_labelled_total`,
  `frames_processed_total`, `frames_dropped_total` (queue full), `frames_rejected_total{reason}`,
  `frames_tracked_total`, `frames_lost_total`, `keyframes_total`, `keyframes_mapped_total`,
  `robot_restarts_total` (camera restarts: a new session in the same slot),
  `queue_depth`, `queue_bytes`, `frames_per_second`, `frame_processing_seconds` (moving
  mean), `map_backlog`, `robot_state{state}` (1 for the current one);
- per robot, from the map: `map_update_seconds` (histogram), `memory_nodes{memory="stm|wm|ltm"}`,
  `vocabulary_words` (after its latest map update), `loop_closures_total{link="loop|proximity"}`
  (the link types' names, `storage.LINK_NAMES`);
- the semantic map: `semantic_keyframes{state="keyframes|segmented|skipped"}`, `semantic_coverage`
  (segmented / keyframes);
- REST: `http_request_duration_seconds{method, route, status}` (histogram);
- the process (prometheus_client's): `process_resident_memory_bytes`, `process_cpu_seconds_total`, ...
"""
from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field

from prometheus_client import CollectorRegistry, Histogram, ProcessCollector
from prometheus_client.exposition import choose_encoder
from prometheus_client.metrics_core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily
from prometheus_client.registry import Collector
from prometheus_client.utils import floatToGoString

from mnemoslam.storage import LinkType, StoreError

log = logging.getLogger("mnemoslam.metrics")

PREFIX = "mnemoslam_"
# s; a map update takes ~20 ms (odometry only) to ~1 s (dense refinement, many candidates)
UPDATE_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)
# s; a REST read takes ~0.5 ms (nearest object) to ~100 ms (a whole session's graph)
REQUEST_BUCKETS = (0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 10.0)
STATES = ("waiting_for_frames", "tracking", "lost", "stopped")
MEMORIES = ("stm", "wm", "ltm")
LOOP_LINKS = (LinkType.GLOBAL_CLOSURE, LinkType.LOCAL_SPACE)  # counted by their `label`, as `loop_closed` names them
METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS"})

# (snapshot key, metric name, help) of each robot's counters and gauges
ROBOT_COUNTERS = (
    ("frames_received", "frames_received", "frames accepted into the robot's queue"),
    ("frames_labelled", "frames_labelled", "accepted frames that came with a label image"),
    ("frames_processed", "frames_processed", "frames the robot's pipeline processed"),
    ("frames_dropped", "frames_dropped", "oldest frames dropped because the robot's queue was full"),
    ("tracked", "frames_tracked", "processed frames that were tracked"),
    ("lost", "frames_lost", "processed frames where tracking was lost"),
    ("keyframes", "keyframes", "keyframes taken"),
    ("keyframes_mapped", "keyframes_mapped", "keyframes the map update (loop closure, graph) has done"),
    ("restarts", "robot_restarts", "camera restarts (stamps back by more than service.restart_gap): sessions ended "
                                   "\"restarted\" and begun again"),
)
ROBOT_GAUGES = (  # (key, name, help, scale)
    ("queue_depth", "queue_depth", "frames waiting in the robot's queue", 1.0),
    ("queue_mb", "queue_bytes", "decoded image bytes waiting in the robot's queue", 2.0**20),
    ("fps", "frames_per_second", "processed frames per second over the last ~60 frames", 1.0),
    ("processing_ms", "frame_processing_seconds", "pipeline time per frame (moving mean)", 1e-3),
    ("map_backlog", "map_backlog", "keyframes waiting for the map update (0: the map served includes them all)", 1.0),
)


@dataclass
class _Updates:
    """One session's map updates read so far (cumulative histogram) and the latest sizes."""

    last_node: int = 0
    buckets: list = field(default_factory=lambda: [0] * len(UPDATE_BUCKETS))
    count: int = 0
    total_s: float = 0.0
    latest: tuple | None = None  # (stm, wm, ltm, words) after the latest update

    def add(self, rows) -> None:
        for node, ms, stm, wm, ltm, words in rows:
            self.last_node = max(self.last_node, node)
            if ms is not None:
                s = ms / 1e3
                self.count += 1
                self.total_s += s
                for i, bound in enumerate(UPDATE_BUCKETS):
                    if s <= bound:
                        self.buckets[i] += 1
            if wm is not None:
                self.latest = (stm, wm, ltm, words)

    def histogram(self) -> list[tuple[str, float]]:
        return [(floatToGoString(b), n) for b, n in zip(UPDATE_BUCKETS, self.buckets)] + [("+Inf", self.count)]


def _num(v, scale: float = 1.0) -> float | None:
    if v is None or isinstance(v, bool):
        return None
    try:
        return float(v) * scale
    except (TypeError, ValueError):
        return None


class ServiceCollector(Collector):
    """The service's state as metric families, read at each scrape (`collect`)."""

    def __init__(self, service):
        self.service = service
        self._lock = threading.Lock()  # scrapes may overlap (thread pool)
        self._updates: dict[int, _Updates] = {}  # session id -> its map updates read so far
        self._store = None  # the store the map updates were read from (a restarted service has a new one)

    def describe(self):
        return []  # nothing to check at registration (the service may not run yet)

    def collect(self):
        status = self.service.status()
        robots = self.service.robots()
        yield from self._service(status)
        yield from self._robots(robots)
        yield from self._map(robots)

    # -- the service ---------------------------------------------------------------------------
    def _service(self, status: dict):
        for key, name, doc in (("uptime_s", "uptime_seconds", "seconds since the service started"),
                               ("robots", "robots", "robots with a slot (a session)"),
                               ("robot_slots", "robot_slots", "robot slots (service.max_robots)")):
            v = _num(status.get(key))
            if v is not None:
                yield GaugeMetricFamily(PREFIX + name, doc, value=v)
        rejected = CounterMetricFamily(PREFIX + "messages_rejected", "messages refused before reaching a robot's "
                                       "pipeline, by reason (all robots, those without a slot included)",
                                       labels=["reason"])
        for reason, n in sorted((status.get("rejected") or {}).items()):
            rejected.add_metric([str(reason)], n)
        yield rejected
        mp = status.get("mapping_process")
        if mp:
            yield GaugeMetricFamily(PREFIX + "mapping_process_up", "1 while the map update's child process runs",
                                    value=1.0 if mp.get("alive") else 0.0)
            yield CounterMetricFamily(PREFIX + "mapping_process_failures", "times the map update's process died",
                                      value=mp.get("failures", 0))
            yield CounterMetricFamily(PREFIX + "mapping_updates_dropped", "keyframe updates not sent because the "
                                      "map update's process was gone", value=mp.get("dropped_updates", 0))

    # -- each robot's session ------------------------------------------------------------------
    def _robots(self, robots: list[dict]):
        counters = {key: CounterMetricFamily(PREFIX + name, doc, labels=["robot"]) for key, name, doc in ROBOT_COUNTERS}
        gauges = {key: (GaugeMetricFamily(PREFIX + name, doc, labels=["robot"]), scale)
                  for key, name, doc, scale in ROBOT_GAUGES}
        rejected = CounterMetricFamily(PREFIX + "frames_rejected", "the robot's frames refused, by reason",
                                       labels=["robot", "reason"])
        state = GaugeMetricFamily(PREFIX + "robot_state", "the robot's state (1: current)", labels=["robot", "state"])
        for r in robots:
            robot = str(r.get("robot"))
            for key, family in counters.items():
                v = _num(r.get(key))
                if v is not None:
                    family.add_metric([robot], v)
            for key, (family, scale) in gauges.items():
                v = _num(r.get(key), scale)
                if v is not None:
                    family.add_metric([robot], v)
            for reason, n in sorted((r.get("frames_rejected") or {}).items()):
                rejected.add_metric([robot, str(reason)], n)
            for s in STATES:
                state.add_metric([robot, s], 1.0 if r.get("state") == s else 0.0)
        yield from counters.values()
        yield from (family for family, _ in gauges.values())
        yield rejected
        yield state

    # -- the map (database) ----------------------------------------------------------------------
    def _map(self, robots: list[dict]):
        update = HistogramMetricFamily(PREFIX + "map_update_seconds", "time of each keyframe's map update (loop "
                                       "closure, graph, memory management), over the robot's session",
                                       labels=["robot"])
        memory = GaugeMetricFamily(PREFIX + "memory_nodes", "nodes in short-term, working and long-term memory "
                                   "after the robot's latest map update", labels=["robot", "memory"])
        words = GaugeMetricFamily(PREFIX + "vocabulary_words", "searchable visual words after the robot's latest "
                                  "map update", labels=["robot"])
        loops = CounterMetricFamily(PREFIX + "loop_closures", "loop-closure links of the robot's session, by how "
                                    "they were found", labels=["robot", "link"])
        store = getattr(self.service, "store", None)
        live = {r.get("robot"): r.get("session_id") for r in robots if isinstance(r.get("session_id"), int)}
        if store is not None and live:
            try:
                with self._lock:
                    if store is not self._store:
                        self._store, self._updates = store, {}
                    for sid in set(self._updates) - set(live.values()):  # ended sessions
                        del self._updates[sid]
                    for robot, sid in sorted(live.items()):
                        u = self._updates.setdefault(sid, _Updates())
                        u.add(store.map_updates(sid, u.last_node))
                        update.add_metric([robot], u.histogram(), u.total_s)
                        if u.latest is not None:
                            for name, v in zip(MEMORIES, u.latest[:3]):
                                if _num(v) is not None:
                                    memory.add_metric([robot, name], float(v))
                            if _num(u.latest[3]) is not None:
                                words.add_metric([robot], float(u.latest[3]))
                        counts = store.count_links(LOOP_LINKS, session_id=sid)
                        for kind in LOOP_LINKS:
                            loops.add_metric([robot, kind.label], counts.get(kind, 0))
            except StoreError as e:  # the store closed under the scrape (service stopping)
                log.debug("metrics: map statistics not read: %s", e)
        yield from (update, memory, words, loops)
        if store is not None:
            yield from self._coverage(store)

    def _coverage(self, store):
        """The semantic map's coverage: the map's keyframes, those segmented, those skipped."""
        try:
            c = store.segmentation_coverage()
        except StoreError as e:  # the store closed under the scrape (service stopping)
            log.debug("metrics: semantic coverage not read: %s", e)
            return
        family = GaugeMetricFamily(PREFIX + "semantic_keyframes", "the map's keyframes (all), those whose labels are "
                                   "in the semantic map (segmented) and those with nothing to segment (skipped)",
                                   labels=["state"])
        for state in ("keyframes", "segmented", "skipped"):
            family.add_metric([state], float(c[state]))
        yield family
        if c["keyframes"]:
            yield GaugeMetricFamily(PREFIX + "semantic_coverage", "share of the map's keyframes in the semantic map",
                                    value=c["segmented"] / c["keyframes"])


class RequestTimer:
    """ASGI middleware: each HTTP request's time (to its response's end) into `observe(method,
    route template, status, seconds)`. The route is the template the router matched (set in the
    request's scope), so /robots/r1 and /robots/r2 are one series."""

    def __init__(self, app, observe):
        self.app, self.observe = app, observe

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        status = 500  # unless a response starts (an exception reaches the server's handler)

        async def send_status(message):
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        t = time.perf_counter()
        try:
            await self.app(scope, receive, send_status)
        finally:
            route = getattr(scope.get("route"), "path", None)
            method = scope.get("method", "")
            self.observe(method if method in METHODS else "other", route if isinstance(route, str) else "unmatched",
                         status, time.perf_counter() - t)


class Metrics:
    """The metrics of one app: its own registry (several apps in one process stay apart) with
    the service's collector, the REST latency histogram and the process's collector."""

    def __init__(self, service):
        self.registry = CollectorRegistry(auto_describe=True)
        self.registry.register(ServiceCollector(service))
        self.requests = Histogram(PREFIX + "http_request_duration_seconds", "REST request time, by route template",
                                  ["method", "route", "status"], buckets=REQUEST_BUCKETS, registry=self.registry)
        ProcessCollector(registry=self.registry)

    def observe_request(self, method: str, route: str, status: int, seconds: float) -> None:
        self.requests.labels(method, route, str(status)).observe(seconds)

    def render(self, accept: str | None) -> tuple[bytes, str]:
        """(body, content type) for a scrape: Prometheus text 0.0.4, or OpenMetrics when the
        scraper's Accept header asks for it."""
        encode, content_type = choose_encoder(accept or "")
        return encode(self.registry), content_type
