"""Does the background mapper slow tracking down? (issue #4: "tracking never waits for
mapping ... mind the GIL: measure it").

    .venv/bin/python bench/bench_mapper_gil.py [--frames 900] [--repeats 2] [--pace] [--7scenes]

Everything runs in one process on the same pre-rendered frames (synthetic figure-8 path at
15 Hz with sensor noise: the second lap revisits the first, so loops are detected, verified
and optimised). Tracking runs on the main thread like a robot session's worker thread; the
map update runs on the mapper's own thread (`Mapper(..., background=True)`) as in the
service. Scenarios, interleaved and repeated (medians over the repeats are printed):

1. tracking only: `Pipeline.process` with memory (SQLite) and no map update (a stub keeps
   the keyframe updates for part 4);
2. + background mapper, as the service runs it;
3. + background mapper with a large map: vocabulary pre-filled with 500k random words of
   1000 older nodes, pose graph pre-filled with a 10k-keyframe session (square laps with
   loop links) so every loop closure optimises, checks and reads a 10k-node graph.

Frames are fed back to back (the session thread when frames are queued; this keeps the
mapper busiest relative to tracking, an upper bound for the service at 15 Hz), or at the
camera rate with --pace. Per frame: wall time of `Pipeline.process` (p50/p95/p99/max) and,
from the kernel's per-thread scheduler statistics (/proc/thread-self/schedstat), the time
on a CPU, "runq" (runnable, waiting for a CPU: other jobs on the machine, our own threads)
and "blkd" = the rest: blocked on the GIL (or the map database's lock, or I/O); frames/s;
ratios against scenario 1 of the same process.

4. The GIL probe: a pure-Python counter thread runs beside one mapper operation at a time
   (repeated for a fixed window). The counter only ever blocks on the GIL, so the share of
   the window it spent blocked (neither on a CPU nor waiting for one) is the share of the
   time the operation held the GIL ("GIL held": ~0 % the op releases it, ~50 % plain
   Python, both threads take turns every switch interval, ~100 % C code that never lets
   go); this stays meaningful when other jobs take the cores (they show as "runq"), which
   its raw speed ("counter", iterations/s beside the op / beside a sleep) does not. "max
   stall" is the counter's longest gap: how long a tracking thread could be blocked at
   once. The other direction: "op ms" alone (counter paused) and "beside" the running
   counter, "x" = their ratio (a thread that wants the GIL back after a GIL-free call
   waits up to one switch interval while a Python thread runs). OpenCV runs on 1 thread
   during the probe ("cores" = the op's CPU / wall).

4. + the service's mapping process (service/mapping/process.py, loop.process): the same
   mapper in one spawned child at nice loop.process_nice (--mapper-nice), its own GIL and
   its own connection to the map; tracking gets the corrections it sends back.
--switch-interval S runs everything with sys.setswitchinterval(S) (e.g. 0.0005).
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from importlib.metadata import version
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import gtsam  # noqa: E402

from mnemoslam.client.synthetic import SyntheticDataset  # noqa: E402
from mnemoslam.service.config import Config, load_config  # noqa: E402
from mnemoslam.service.mapping.graph import PoseGraph  # noqa: E402
from mnemoslam.service.mapping.mapper import Mapper  # noqa: E402
from mnemoslam.service.mapping.process import MappingProcess  # noqa: E402
from mnemoslam.service.mapping.verification import verify  # noqa: E402
from mnemoslam.service.memory.keyframes import KeyframeWriter  # noqa: E402
from mnemoslam.service.memory.vocabulary import Vocabulary  # noqa: E402
from mnemoslam.service.pipeline import Pipeline  # noqa: E402
from mnemoslam.service.tracking.matching import match_descriptors as _match  # noqa: E402
from mnemoslam.storage import LinkType, MapStore  # noqa: E402

PREFILL_NODE = 10_000_000  # ids of the pre-filled vocabulary nodes / graph nodes: never the store's
PREFILL_GRAPH = 20_000_000
LAP = 1000  # pre-filled graph: keyframes per lap of a square, 0.5 m apart
ODOM_SIGMAS = np.array([np.deg2rad(0.5)] * 3 + [0.01] * 3)
ODOM_INFO = np.diag(1.0 / ODOM_SIGMAS**2)


def schedstat(path: str = "/proc/thread-self/schedstat") -> tuple[float, float]:
    """(s on a CPU, s runnable but waiting for a CPU) of a thread, from the kernel's scheduler
    statistics; the rest of its wall time it was blocked (GIL, locks, I/O, sleep). Without
    schedstat: (process-wide thread CPU time of the caller, 0)."""
    try:
        with open(path) as f:
            on_cpu, runq, _ = f.read().split()
        return int(on_cpu) / 1e9, int(runq) / 1e9
    except (OSError, ValueError):
        return time.thread_time(), 0.0


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


# -- frames ------------------------------------------------------------------------------------

def render(trajectory: str, rate: float, frames: int, duration: float | None):
    ds = SyntheticDataset(trajectory, rate=rate, noise=True, max_frames=frames, duration=duration)
    out = []
    for i in tqdm(range(len(ds)), desc=f"render {trajectory}", unit="frame", leave=False):
        f = ds.frame(i)
        f.extras = {}  # labels/instances are not used by tracking
        out.append(f)
    return ds.calibration, out, rate


def load_7scenes(data: Path, frames: int):
    from mnemoslam.client.datasets import open_dataset

    ds = open_dataset(data / "7scenes_redkitchen", max_frames=frames)
    out = [ds.frame(i) for i in tqdm(range(len(ds)), desc="decode 7-scenes", unit="frame", leave=False)]
    return ds.calibration, out, 30.0


# -- the large map of scenario 3 -----------------------------------------------------------------

def prefilled_vocabulary(words: int, nodes: int, nndr: float, seed: int = 1) -> dict:
    """`Vocabulary.state()` arrays of `words` random words spread over `nodes` older nodes."""
    rng = np.random.default_rng(seed)
    st = Vocabulary(nndr=nndr).state()
    ids = np.arange(words, dtype=np.int64)
    node_of = PREFILL_NODE + ids % nodes
    st.update(word_ids=ids, descriptors=rng.integers(0, 256, (words, 32), dtype=np.uint8),
              post_word=ids, post_node=node_of, post_count=np.ones(words, np.int64),
              node_ids=PREFILL_NODE + np.arange(nodes, dtype=np.int64),
              node_nfeat=np.full(nodes, -(-words // nodes), np.int64), next_id=np.array([words], np.int64))
    return st


def prefilled_graph(n: int, max_error: float, seed: int = 2) -> PoseGraph:
    """A PoseGraph holding an older session of `n` keyframes: laps of a square with noisy
    odometry and a loop link every two laps (the Bayes tree of a real map, not a bare chain)."""
    rng = np.random.default_rng(seed)
    side = LAP // 4
    fwd = gtsam.Pose3.Expmap(np.array([0, 0, 0, 0.5, 0, 0])).matrix()
    turn = gtsam.Pose3.Expmap(np.array([0, 0, np.pi / 2, 0, 0, 0])).matrix()
    g = PoseGraph(max_error=max_error)
    truth = [np.eye(4)]
    g.add_node(PREFILL_GRAPH, truth[0])
    for k in range(1, n):
        step = fwd @ turn if k % side == 0 else fwd
        truth.append(truth[-1] @ step)
        meas = step @ gtsam.Pose3.Expmap(rng.normal(size=6) * ODOM_SIGMAS * 0.3).matrix()
        g.add_node(PREFILL_GRAPH + k, np.eye(4), odom_from=PREFILL_GRAPH + k - 1, transform=meas, information=ODOM_INFO)
        if k >= LAP and (k + 1) % (2 * LAP) == 0:
            g.add_loop(PREFILL_GRAPH + k, PREFILL_GRAPH + k - LAP, np.linalg.inv(truth[k]) @ truth[k - LAP], ODOM_INFO)
    g.changed_poses()  # published already: a session's loop must not report the old map's poses
    g.truth = truth  # for the probe's loop links
    return g


# -- scenario runs -------------------------------------------------------------------------------

class KeyframeRecorder:
    """Stands in for the mapper in the tracking-only run: keeps the keyframe updates (inputs of
    the GIL probe), no map update, no correction."""

    def __init__(self):
        self.updates = []

    def submit(self, update) -> None:
        self.updates.append(update)

    def to_map(self, pose):
        return pose

    def close(self) -> None:
        pass


@dataclass
class Run:
    scenario: str
    wall: np.ndarray  # ms per frame
    cpu: np.ndarray  # ms on a CPU
    runq: np.ndarray  # ms runnable, waiting for a CPU (other processes, our own threads)
    elapsed: float  # s for all frames
    keyframes: int
    mapped: int = 0  # keyframes the mapper finished while tracking ran
    loops: int = 0
    stages: list = field(default_factory=list)  # per keyframe mapped: {stage: ms}
    mapper_busy: float = 0.0  # mapper time / tracking time
    drain_s: float = 0.0  # waiting for the mapper's backlog after the last frame
    late: int = 0  # paced: frames whose processing overran the next frame's arrival

    @property
    def mapper_ms(self) -> np.ndarray:
        return np.array([sum(t.values()) for t in self.stages])

    @property
    def fps(self) -> float:
        return len(self.wall) / self.elapsed

    @property
    def blocked(self) -> np.ndarray:
        """ms neither on a CPU nor waiting for one: waiting for the GIL (or a lock, or I/O)."""
        return np.maximum(self.wall - self.cpu - self.runq, 0.0)


def run_scenario(name: str, kind: str, calibration, frames, config: Config, rate: float, pace: bool,
                 large=None, nice: int | None = None):
    """One pass of the frames through a fresh pipeline and a fresh map database, on this thread.
    kind: "tracking" (no map update), "thread" (Mapper on its thread, as the service), "large"
    (the same with `large()`'s vocabulary and graph), "process" (the service's MappingProcess)."""
    with tempfile.TemporaryDirectory(prefix="bench-gil-") as tmp:
        store = MapStore(Path(tmp) / "map.db")
        try:
            memory = KeyframeWriter(store, "bench", calibration, config)
            if kind == "tracking":
                mapper = KeyframeRecorder()
            elif kind == "process":
                loop = config.loop if nice is None else dataclasses.replace(config.loop, process_nice=nice)
                owner = MappingProcess(Path(tmp) / "map.db", loop)
                if not owner.wait_ready(300):  # imported and ready before the clock starts
                    raise RuntimeError("the mapping process did not start")
                mapper = owner.mapper("bench", calibration.camera)
            else:
                mapper = Mapper(calibration.camera, config.loop, store, background=True)
                if kind == "large":
                    mapper.memory._vocabulary, mapper.graph = large()  # memory owns the vocabulary
                    mapper.detector.vocabulary = mapper.vocabulary
                    mapper.merge_links.graph = mapper.graph
            pipeline = Pipeline(calibration, config, memory, mapper)
            wall, cpu, runq = np.zeros(len(frames)), np.zeros(len(frames)), np.zeros(len(frames))
            kf, late = 0, 0
            bar = tqdm(total=len(frames), desc=name, unit="frame", leave=False)
            t_start = time.perf_counter()
            for i, f in enumerate(frames):
                if pace:
                    delay = t_start + i / rate - time.perf_counter()
                    if delay > 0:
                        time.sleep(delay)
                (c0, q0), t0 = schedstat(), time.perf_counter()
                r = pipeline.process(f)
                t1 = time.perf_counter()
                c1, q1 = schedstat()
                wall[i], cpu[i], runq[i] = (t1 - t0) * 1e3, (c1 - c0) * 1e3, (q1 - q0) * 1e3
                kf += r.node_id is not None
                late += pace and t1 > t_start + (i + 1) / rate
                bar.update()
            elapsed = time.perf_counter() - t_start
            bar.close()
            run = Run(name, wall, cpu, runq, elapsed, kf, late=late)
            if isinstance(mapper, Mapper):
                done = list(mapper.statistics.values())  # the keyframes mapped while tracking ran
                run.mapped = len(done)
                run.mapper_busy = sum(sum(s.timings_ms.values()) for s in done) / 1e3 / elapsed
                t0 = time.perf_counter()
                mapper.close(timeout=600)
                run.drain_s = time.perf_counter() - t0
                run.stages = [s.timings_ms for s in list(mapper.statistics.values())]
                run.loops = len(mapper.loops)
            elif kind == "process":
                run.mapped = mapper.mapped
                t0 = time.perf_counter()
                mapper.close(timeout=600)
                run.drain_s = time.perf_counter() - t0
                owner.close()
                if owner.failures:
                    raise RuntimeError("the mapping process died")
                nodes = store.nodes(session_id=memory.session_id, limit=None)
                run.stages = [st["timings_ms"] for n in nodes if (st := store.statistics(n.id))]
                run.loops = len(store.links(type=LinkType.GLOBAL_CLOSURE)) + len(store.links(type=LinkType.LOCAL_SPACE))
                run.mapper_busy = float(run.mapper_ms[:run.mapped].sum()) / 1e3 / elapsed
            store.end_session(memory.session_id)
            return run, mapper
        finally:
            store.close()


# -- GIL probe -----------------------------------------------------------------------------------

class Counter:
    """A pure-Python thread counting loop iterations; gaps > 1 ms are recorded (its stalls)."""

    def __init__(self):
        self.n = 0
        self.gaps: list[tuple[float, float]] = []  # (end time, gap s)
        self.paused = False
        self._stop = False
        self._thread = threading.Thread(target=self._run, name="gil-counter", daemon=True)
        self._thread.start()
        while not self.n:
            time.sleep(0.001)
        self.stat = f"/proc/self/task/{self._thread.native_id}/schedstat"

    def _run(self) -> None:
        pc = time.perf_counter
        gaps = self.gaps
        last = pc()
        n = 0
        while not self._stop:
            if self.paused:
                while self.paused and not self._stop:
                    time.sleep(0.002)
                last = pc()
            t = pc()
            if t - last > 1e-3:
                gaps.append((t, t - last))
            last = t
            n += 1
            self.n = n

    def sched(self) -> tuple[float, float]:
        return schedstat(self.stat)

    def stop(self) -> None:
        self._stop = True
        self._thread.join()


@dataclass
class Probe:
    name: str
    op_ms: float  # median wall per call, counter paused
    op_beside_ms: float  # median wall per call beside the running counter
    speed: float  # counter iterations/s beside the op / beside a sleep
    blocked: float  # fraction of the window the counter was blocked (waiting for the GIL)
    runq: float  # fraction it waited for a CPU
    stall_ms: float  # counter's longest gap
    cores: float  # CPU of the op (all its threads) / wall
    calls: int


def probe(counter: Counter, name: str, fn, window: float, repeats: int) -> Probe:
    speeds, stalls, cores, per_call, alone, blocked, runq = [], [], [], [], [], [], []
    calls = 0
    for _ in range(repeats):
        counter.paused = True
        t0 = time.perf_counter()
        while not alone or time.perf_counter() - t0 < window / 2:
            s = time.perf_counter()
            fn()
            alone.append((time.perf_counter() - s) * 1e3)
        counter.paused = False
        n0, t0 = counter.n, time.perf_counter()
        time.sleep(0.1)
        rate0 = (counter.n - n0) / (time.perf_counter() - t0)
        n0, (c0, q0), p0, t0 = counter.n, counter.sched(), time.process_time(), time.perf_counter()
        k = 0
        while k == 0 or time.perf_counter() - t0 < window:
            s = time.perf_counter()
            fn()
            per_call.append((time.perf_counter() - s) * 1e3)
            k += 1
        t1 = time.perf_counter()
        c1, q1 = counter.sched()
        speeds.append((counter.n - n0) / (t1 - t0) / rate0)
        cores.append(((time.process_time() - p0) - (c1 - c0)) / (t1 - t0))
        blocked.append(max(0.0, 1.0 - ((c1 - c0) + (q1 - q0)) / (t1 - t0)))
        runq.append((q1 - q0) / (t1 - t0))
        stalls.append(max([g for te, g in counter.gaps if t0 < te <= t1 + 0.05] or [0.0]) * 1e3)
        calls += k
    return Probe(name, statistics.median(alone), statistics.median(per_call), statistics.median(speeds),
                 statistics.median(blocked), statistics.median(runq), max(stalls),
                 statistics.median(cores), calls)


def gil_probes(config: Config, calibration, frames, updates, mapper: Mapper | None, big: Mapper | None,
               window: float, repeats: int) -> list[Probe]:
    """Each mapper operation alone beside the counter thread, on the run's real keyframes."""
    camera = calibration.camera
    by_id = {u.node_id: u for u in updates}
    feats = [u.features for u in updates]
    rng = np.random.default_rng(3)
    big_list = list(rng.integers(0, 1 << 30, 300_000).tolist())
    big_arr = rng.random(2_000_000)
    state = {"id": 900_000_000}

    def next_id() -> int:
        state["id"] += 1
        return state["id"]

    def nth(seq, k=[0]):  # noqa: B006 - a cursor over the keyframes
        k[0] = (k[0] + 1) % len(seq)
        return seq[k[0]]

    def py_loop():
        x = 0
        for i in range(50_000):
            x += i

    track = {"i": 0, "p": None}

    def tracking():  # the next frame of a fresh session (restarted at the end of the first 300)
        if track["p"] is None or track["i"] >= min(len(frames), 300):
            track["p"], track["i"] = Pipeline(calibration, config), 0
        track["p"].process(frames[track["i"]])
        track["i"] += 1

    ops = [
        ("control: time.sleep(5 ms)  [releases]", lambda: time.sleep(0.005)),
        ("control: Python loop  [shares]", py_loop),
        ("control: sorted(300k ints)  [holds]", lambda: sorted(big_list)),
        ("control: np.sort(2M floats)  [releases]", lambda: np.sort(big_arr)),
        ("tracking: Pipeline.process (no memory)", tracking),
    ]
    # a real accepted loop pair (new keyframe, candidate) for verification
    pair = None
    if mapper is not None and mapper.loops:
        cand, new = mapper.loops[len(mapper.loops) // 2]
        if cand in by_id and new in by_id:
            pair = (by_id[new].features, by_id[cand].features)
    if pair is None:  # consecutive keyframes: always overlap
        pair = (feats[min(1, len(feats) - 1)], feats[0])
    nf, cf = pair
    has = np.nonzero(np.isfinite(cf.points[:, 2]))[0]
    q, t = _match(nf.descriptors, cf.descriptors[has], 0.8, 80)
    obj = cf.points[has[t]].astype(np.float64)
    img = nf.keypoints[q].astype(np.float64)

    def pnp():
        cv2.solvePnPRansac(obj, img, camera.K, None, iterationsCount=300, reprojectionError=2.0,
                           confidence=0.999, flags=cv2.SOLVEPNP_AP3P)

    ops += [
        ("verify: BFMatcher knnMatch + ratio test", lambda: _match(nf.descriptors, cf.descriptors[has], 0.8, 80)),
        ("verify: cv2.solvePnPRansac", pnp),
        ("verify() (match + PnP + refine)", lambda: verify(camera, nf.keypoints, nf.descriptors, cf.descriptors,
                                                           cf.points, min_inliers=config.loop.min_inliers)),
    ]
    for label, m in (("session", mapper), ("500k words/10k nodes", big)):
        if m is None:
            continue
        voc, det, graph = m.vocabulary, m.detector, m.graph
        nodes = sorted(m.statistics)
        ops.append((f"vocabulary.add [{label}, {len(voc)} words]",
                    lambda voc=voc: voc.add(next_id(), nth(feats).descriptors)))
        words = [voc.query(f.descriptors) for f in feats[:50]]  # words of known keyframes (no insertion)

        def detect(det=det, nodes=nodes, words=words):
            det.process(next_id(), nth(words), {}, nodes)

        ops.append((f"LoopDetector.process [{label}, {len(nodes)} candidates]", detect))
        last = {"id": None}

        def add_node(graph=graph, last=last):
            nid = next_id()
            src = last["id"]
            graph.add_node(nid, np.eye(4), odom_from=src, transform=None if src is None else np.eye(4),
                           information=None if src is None else ODOM_INFO)
            last["id"] = nid

        ops.append((f"PoseGraph.add_node (iSAM2 update) [{label}, {len(graph)} nodes]", add_node))
    if big is not None and hasattr(big.graph, "truth"):
        g = big.graph
        truth = g.truth
        n = len(truth)
        cursor = {"k": n - 1}

        def add_loop():  # a lap loop (accepted) in the old session: iSAM2 iterations + error check
            k = cursor["k"]
            cursor["k"] -= 7
            g.add_loop(PREFILL_GRAPH + k, PREFILL_GRAPH + k - LAP, np.linalg.inv(truth[k]) @ truth[k - LAP], ODOM_INFO)

        ops.append((f"PoseGraph.add_loop (iSAM2 iterations) [{len(g)} nodes]", add_loop))
        ops.append((f"PoseGraph.changed_poses [{len(g)} nodes]", g.changed_poses))
        fg = g.factor_graph()
        values = gtsam.Values()
        for k, p in g.poses().items():
            values.insert(k, gtsam.Pose3(p))
        ops.append((f"gtsam: NonlinearFactorGraph.error [{fg.size()} factors]", lambda: fg.error(values)))

    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    counter = Counter()
    out = []
    try:
        for name, fn in tqdm(ops, desc="GIL probe", unit="op", leave=False):
            out.append(probe(counter, name, fn, window, repeats))
    finally:
        counter.stop()
        cv2.setNumThreads(threads)
    return out


# -- report --------------------------------------------------------------------------------------

def summarize(runs: list[Run]) -> dict:
    med = statistics.median
    return {
        "frames": len(runs[0].wall), "kf": runs[0].keyframes,
        "p50": med(np.percentile(r.wall, 50) for r in runs), "p95": med(np.percentile(r.wall, 95) for r in runs),
        "p99": med(np.percentile(r.wall, 99) for r in runs), "max": med(r.wall.max() for r in runs),
        "p99_range": (min(np.percentile(r.wall, 99) for r in runs), max(np.percentile(r.wall, 99) for r in runs)),
        "runq": med(r.runq.mean() for r in runs), "blocked": med(r.blocked.mean() for r in runs),
        "blocked_p99": med(np.percentile(r.blocked, 99) for r in runs),
        "cpu_p50": med(np.percentile(r.cpu, 50) for r in runs),
        "fps": med(r.fps for r in runs), "late": med(r.late for r in runs),
        "loops": med(r.loops for r in runs), "mapped": med(r.mapped for r in runs),
        "busy": med(r.mapper_busy for r in runs), "drain": med(r.drain_s for r in runs),
        "map_p50": med(np.percentile(r.mapper_ms, 50) if len(r.mapper_ms) else 0.0 for r in runs),
        "map_max": med(r.mapper_ms.max() if len(r.mapper_ms) else 0.0 for r in runs),
        "stages": {k: med(float(np.mean([t.get(k, 0.0) for t in r.stages])) for r in runs)
                   for k in (runs[0].stages[0] if runs[0].stages else {})},
    }


def print_scenarios(title: str, rows: list[tuple[str, dict]], pace: bool) -> list[str]:
    base = rows[0][1]
    print(f"\n{title}")
    head = (f"{'scenario':<38} {'p50':>6} {'p95':>6} {'p99':>6} {'max':>6} {'cpu50':>6} {'runq':>5} {'blkd':>5} "
            f"{'blkd99':>6} {'fps':>6} | {'x p50':>5} {'x p99':>5} {'x max':>5} {'x fps':>5} | {'kf':>4} {'mapped':>6} "
            f"{'loops':>5} {'busy':>5} {'map p50':>7} {'map max':>7} {'drain':>6}" + (f" {'late':>4}" if pace else ""))
    print(head)
    print("-" * len(head))
    flags = []
    for name, s in rows:
        line = (f"{name:<38} {s['p50']:6.1f} {s['p95']:6.1f} {s['p99']:6.1f} {s['max']:6.1f} {s['cpu_p50']:6.1f} "
                f"{s['runq']:5.1f} {s['blocked']:5.1f} {s['blocked_p99']:6.1f} {s['fps']:6.1f} | "
                f"{s['p50'] / base['p50']:5.2f} {s['p99'] / base['p99']:5.2f} {s['max'] / base['max']:5.2f} "
                f"{s['fps'] / base['fps']:5.2f} | "
                f"{s['kf']:>4} {s['mapped']:>6.0f} {s['loops']:>5.0f} {100 * s['busy']:4.0f}% {s['map_p50']:7.1f} "
                f"{s['map_max']:7.0f} {s['drain']:5.1f}s" + (f" {s['late']:>4.0f}" if pace else ""))
        print(line)
        if s is not base and (s["p99"] > 1.2 * base["p99"] or s["fps"] < base["fps"] / 1.2):
            flags.append(f"{title.split(':')[0]} / {name}: p99 x{s['p99'] / base['p99']:.2f}, "
                         f"frames/s x{s['fps'] / base['fps']:.2f} (> 20 % worse than tracking only)")
    for name, s in rows:
        if s["stages"]:
            print(f"  mapper ms per keyframe by stage (mean), {name}: "
                  + ", ".join(f"{k} {v:.1f}" for k, v in s["stages"].items()))
    lo, hi = zip(*(s["p99_range"] for _, s in rows))
    print("p99 over the repeats: " + ", ".join(f"{a:.1f}-{b:.1f}" for a, b in zip(lo, hi)))
    return flags


def print_probes(probes: list[Probe]) -> None:
    print("\nGIL probe: a pure-Python counter thread beside one operation at a time (medians). op ms: alone / beside "
          "the counter, x = ratio; cores = the op's CPU / wall; counter = its iterations/s beside the op / beside a "
          "sleep; GIL held = share of the time the counter was blocked (neither on a CPU nor waiting for one); "
          "runq = share it waited for a CPU; max stall = its longest gap")
    head = (f"{'operation':<66} {'op ms':>7} {'beside':>7} {'x':>5} {'calls':>5} {'cores':>5} {'counter':>7} "
            f"{'GIL held':>8} {'runq':>5} {'max stall ms':>12}")
    print(head)
    print("-" * len(head))
    for p in probes:
        print(f"{p.name:<66} {p.op_ms:7.2f} {p.op_beside_ms:7.2f} {p.op_beside_ms / p.op_ms:5.2f} {p.calls:>5} "
              f"{p.cores:5.2f} {100 * p.speed:6.0f}% {100 * p.blocked:7.0f}% {100 * p.runq:4.0f}% {p.stall_ms:12.1f}")


def _revision() -> str:
    try:
        head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], check=False,
                              capture_output=True, text=True, timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(ROOT), "status", "--porcelain", "--", "service", "client", "storage"],
                               check=False, capture_output=True, text=True, timeout=10).stdout.strip()
        return f"{head}{' + uncommitted changes in service/client/storage' if dirty else ''}"
    except (OSError, subprocess.SubprocessError):
        return "?"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trajectory", default="figure8", help="synthetic path (revisiting: figure8, loop)")
    ap.add_argument("--rate", type=float, default=15.0, help="camera rate, Hz")
    ap.add_argument("--frames", type=int, default=620,
                    help="synthetic frames (figure8 in 60 s at 15 Hz: loops closed from frame ~420)")
    ap.add_argument("--duration", type=float, default=60.0,
                    help="s to walk the whole path (figure8: 90 s by default, 60 s = 0.45-0.9 m/s, so that "
                         "the revisits come within the time budget; 0 = the path's own)")
    ap.add_argument("--repeats", type=int, default=2, help="runs per scenario (interleaved)")
    ap.add_argument("--pace", action="store_true", help="feed frames at the camera rate instead of back to back")
    ap.add_argument("--words", type=int, default=500_000, help="scenario 3: pre-filled vocabulary words")
    ap.add_argument("--graph-nodes", type=int, default=10_000, help="scenario 3: pre-filled graph keyframes")
    ap.add_argument("--budget", type=float, default=285.0,
                    help="s: skip further repeats that would not end within it (0 = always run all)")
    ap.add_argument("--probe-window", type=float, default=0.2, help="s per GIL probe repeat")
    ap.add_argument("--probe-repeats", type=int, default=3)
    ap.add_argument("--7scenes", dest="sevenscenes", type=int, nargs="?", const=600, default=0, metavar="N",
                    help="also run scenarios 1-2 on N frames of 7-Scenes redkitchen from MNEMOSLAM_DATA")
    ap.add_argument("--process-mapper", action="store_true", help=argparse.SUPPRESS)  # scenario 4 always runs now
    ap.add_argument("--mapper-nice", type=int, default=None, metavar="N",
                    help="scenario 4: the mapping process's nice increment (default: loop.process_nice)")
    ap.add_argument("--config", help="YAML config (default: the defaults)")
    ap.add_argument("--switch-interval", type=float, default=None, metavar="S",
                    help="sys.setswitchinterval for the whole run (CPython's default: 0.005)")
    args = ap.parse_args()
    args.duration = args.duration or None
    if args.switch_interval is not None:
        sys.setswitchinterval(args.switch_interval)
    config = load_config(args.config)
    t_all = time.perf_counter()
    load0 = os.getloadavg()

    calibration, frames, rate = render(args.trajectory, args.rate, args.frames, args.duration)
    log(f"rendered {len(frames)} frames in {time.perf_counter() - t_all:.0f} s")
    vocab_state = prefilled_vocabulary(args.words, 1000, config.loop.nndr_ratio)

    def large():
        t = time.perf_counter()
        voc = Vocabulary.from_state(vocab_state)
        graph = prefilled_graph(args.graph_nodes, config.loop.optimize_max_error)
        log(f"  large map built in {time.perf_counter() - t:.1f} s")
        return voc, graph

    scenarios = [("1 tracking only", "tracking"), ("2 + background mapper", "thread"),
                 (f"3 + bg mapper, {args.words // 1000}k words/{args.graph_nodes // 1000}k nodes", "large")]
    nice = config.loop.process_nice if args.mapper_nice is None else args.mapper_nice
    scenarios.append((f"4 + mapping process (nice {nice})", "process"))
    runs: dict[str, list[Run]] = {name: [] for name, _ in scenarios}
    kept: dict[str, object] = {}
    t_runs0 = time.perf_counter()
    repeats = 0
    for rep in range(args.repeats):
        per_repeat = (time.perf_counter() - t_runs0) / max(rep, 1)
        if rep and args.budget and time.perf_counter() - t_all + per_repeat + 40 > args.budget:
            log(f"repeat {rep + 1} skipped: it would end past the --budget of {args.budget:g} s (load "
                f"{os.getloadavg()[0]:.1f})")
            break
        repeats += 1
        for name, kind in scenarios:
            run, kept[kind] = run_scenario(name, kind, calibration, frames, config, rate, args.pace, large,
                                           args.mapper_nice)
            runs[name].append(run)
            log(f"  {name} #{rep + 1}: p50 {np.percentile(run.wall, 50):.1f} p99 {np.percentile(run.wall, 99):.1f} "
                f"ms, {run.fps:.1f} frames/s, loops {run.loops}, drain {run.drain_s:.1f} s")
    t_runs = time.perf_counter()
    probes = gil_probes(config, calibration, frames, kept["tracking"].updates, kept["thread"], kept["large"],
                        args.probe_window, args.probe_repeats)
    t_probe = time.perf_counter()

    extra = []
    data = Path(os.environ.get("MNEMOSLAM_DATA", ROOT.parent / "shared" / "data"))
    if args.sevenscenes and (data / "7scenes_redkitchen").exists():
        cal7, frames7, rate7 = load_7scenes(data, args.sevenscenes)
        for name, kind in scenarios[:2]:
            extra.append((name, [run_scenario(name + " 7s", kind, cal7, frames7, config, rate7, args.pace)[0]]))
    elif args.sevenscenes:
        log(f"7-Scenes: {data / '7scenes_redkitchen'} not found, skipped")

    cam = calibration.camera
    print(f"mapper vs tracking, one process: {args.trajectory} @ {rate:g} Hz with noise, {len(frames)} frames "
          f"{cam.width}x{cam.height}, {'paced at the camera rate' if args.pace else 'fed back to back'}, "
          f"{repeats} repeat(s) {'' if repeats == args.repeats else f'(of {args.repeats}: time budget) '}"
          f"interleaved, medians; switch interval {1e3 * sys.getswitchinterval():g} ms; {os.cpu_count()} cores, "
          f"load {load0[0]:.2f} -> {os.getloadavg()[0]:.2f}; Python {sys.version.split()[0]}, "
          f"OpenCV {cv2.__version__}, numpy {np.__version__}, gtsam {version('gtsam')}; code {_revision()}")
    print("ms per frame of Pipeline.process (wall); cpu50 = the thread's CPU p50; runq = mean ms waiting for a CPU; "
          "blkd = ms blocked, neither on a CPU nor waiting for one (the GIL, the map's lock, I/O; mean, p99); "
          "x = ratio to scenario 1; busy = mapper time / tracking time; map = ms per keyframe update; "
          "drain = backlog left after the last frame")
    flags = print_scenarios(f"synthetic {args.trajectory}:", [(n, summarize(runs[n])) for n, _ in scenarios],
                            args.pace)
    if extra:
        flags += print_scenarios(f"7-Scenes redkitchen ({len(extra[0][1][0].wall)} frames, 1 run):",
                                 [(n, summarize(r)) for n, r in extra], args.pace)
    print_probes(probes)
    print(f"\ntimes: scenario runs {t_runs - t_all:.0f} s, probe {t_probe - t_runs:.0f} s, "
          f"total {time.perf_counter() - t_all:.0f} s")
    if flags:
        print("DEGRADED: " + "; ".join(flags))
    else:
        print("no scenario degraded tracking p99 or frames/s by more than 20 %")
    return 0


if __name__ == "__main__":
    sys.exit(main())
