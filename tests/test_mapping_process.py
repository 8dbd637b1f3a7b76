"""The service's map update in a child process (service/mapping/process.py): a real spawned
child, the real SQLite file written by two processes, the real mapper."""
import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from mnemoslam.client.datasets import open_dataset
from mnemoslam.service.config import load_config
from mnemoslam.service.mapping.process import MappingProcess
from mnemoslam.service.memory.keyframes import KeyframeWriter
from mnemoslam.service.pipeline import Pipeline
from mnemoslam.storage import LinkType, MapStore

from conftest import FIGURE8, synthetic, tracked_once


@pytest.fixture(scope="module")
def mapped(tmp_path_factory, figure8_run):
    """The figure-8 (tests/conftest.py FIGURE8: the second lap revisits the first, loops from
    ~frame 280) tracked here, its map update in the mapping process, as in the service. The
    in-process mapper it is compared with is the session's offline run of the same frames
    (`figure8_run`: the same tracking, so the same keyframes and updates, mapped inline). The
    tracking here is that run's, replayed (tests/conftest.py `tracked_once`): what is compared
    is the map update in the child against the inline one."""
    ds = synthetic("figure8", **FIGURE8)  # rendered once for the session (tests/conftest.py)
    # every keyframe goes to the child with its images however far behind it falls (frames are fed
    # as fast as tracking goes): the comparison with the inline run needs them all
    # (no occupancy grid: the keyframes' local grids are stored beside them and never read by the map update)
    cfg = load_config(overrides={"loop": {"backlog_images": 10**9}, "grid": {"enabled": False}})
    db = tmp_path_factory.mktemp("mp") / "map.db"
    store = MapStore(db)
    events = []
    mp = MappingProcess(db, cfg.loop)
    try:
        proxy = mp.mapper("r1", ds.calibration.camera, lambda kind, data: events.append((kind, data)))
        memory = KeyframeWriter(store, "r1", ds.calibration, cfg)
        pipeline = Pipeline(ds.calibration, cfg, memory, proxy)
        tracked_once(pipeline, ds, cfg)
        results = [pipeline.process(ds.frame(i)) for i in range(len(ds))]
        assert proxy.close(timeout=600)
        correction = proxy.correction
        stats = mp.stats()
        store.end_session(memory.session_id)
    finally:
        mp.close()
    assert mp.failures == 0 and not mp.alive
    _, offline, _, offline_dir = figure8_run
    keyframes = [r for r in results if r.node_id is not None]
    np.testing.assert_array_equal(offline.keyframes.stamps, [r.stamp for r in keyframes])  # the same keyframes
    with MapStore(offline_dir / "map.db", create=False) as s:
        assert [n.id for n in s.nodes(limit=None)] == [r.node_id for r in keyframes]  # with the same ids
        loops = [(a.from_id, a.to_id) for a in s.links() if a.type in (LinkType.GLOBAL_CLOSURE, LinkType.LOCAL_SPACE)]
        merges = [n.id for n in s.nodes(limit=None)  # rehearsal's loop closures (merges back into the map)
                  if (((s.statistics(n.id) or {}).get("rehearsal") or {}).get("loop"))]
    reference = dict(loops=loops, merges=merges,
                     poses={r.node_id: p for r, p in zip(keyframes, offline.keyframes.poses)})
    yield dict(ds=ds, db=db, store=store, events=events, reference=reference, results=results,
               correction=correction, stats=stats, pid=mp.pid)
    store.close()


def test_child_closes_the_same_loops_as_the_inprocess_mapper(mapped):
    store, reference = mapped["store"], mapped["reference"]
    closed = [d for kind, d in mapped["events"] if kind == "loop_closed"]
    assert closed, "the second lap closes loops"
    assert any(kind == "map_corrected" for kind, _ in mapped["events"])
    links = store.links(type=LinkType.GLOBAL_CLOSURE) + store.links(type=LinkType.LOCAL_SPACE)
    # rehearsal: a merge that came back to an older part of the map is a loop closure too,
    # (survivor, previous keyframe), with a `merged` link in the database instead of a loop link
    merges = [(d["from"], d["to"]) for d in closed if d["link"] == "merged"]
    assert {(a.from_id, a.to_id) for a in links} == {(d["from"], d["to"]) for d in closed if d["link"] != "merged"}
    assert sorted((a.from_id, a.to_id) for a in links) == sorted(reference["loops"])  # identical to the offline run
    assert len(merges) == len(reference["merges"])
    assert {d["link"] for d in closed} <= {"loop", "proximity", "merged"}
    # the child wrote words, statistics and corrected poses into the service's database
    nodes = store.nodes(limit=None)
    assert mapped["stats"]["mapped"] == mapped["stats"]["submitted"] == len(nodes)
    assert all(store.statistics(n.id) is not None for n in nodes)


def test_corrections_reach_to_map(mapped):
    c = mapped["correction"]
    last = [r for r in mapped["results"] if r.node_id is not None][-1]
    ref = mapped["reference"]
    expected = ref["poses"][last.node_id] @ np.linalg.inv(last.odometry_pose)
    np.testing.assert_allclose(c, expected, atol=1e-9)
    assert np.abs(c - np.eye(4)).max() > 1e-4  # the loops moved the map against odometry
    late = mapped["results"][-1]
    assert not np.allclose(late.pose, late.odometry_pose)  # published poses are map poses


def test_killed_child_leaves_tracking_running(tmp_path):
    ds = open_dataset("synthetic:loop", rate=15, noise=True, max_frames=80)
    cfg = load_config()
    store = MapStore(tmp_path / "map.db")
    mp = MappingProcess(tmp_path / "map.db", cfg.loop)
    try:
        proxy = mp.mapper("k1", ds.calibration.camera)
        pipeline = Pipeline(ds.calibration, cfg, KeyframeWriter(store, "k1", ds.calibration, cfg), proxy)
        results = []
        for i in range(len(ds)):
            if i == 40:
                deadline = time.monotonic() + 120
                while proxy.mapped == 0 and time.monotonic() < deadline:  # the child has mapped something
                    time.sleep(0.1)
                assert proxy.mapped > 0
                os.kill(mp.pid, signal.SIGKILL)
                deadline = time.monotonic() + 30
                while mp.alive and time.monotonic() < deadline:
                    time.sleep(0.05)
                assert not mp.alive
            results.append(pipeline.process(ds.frame(i)))
        assert all(r.tracked for r in results)
        assert len(store.nodes(limit=None)) == sum(r.node_id is not None for r in results)  # memory goes on
        assert mp.failures == 1 and mp.stats()["failures"] == 1 and mp.stats()["dropped_updates"] > 0
        assert proxy.close(timeout=5) is False  # nobody waits for a dead child
    finally:
        mp.close(timeout=5)
        store.close()


@pytest.mark.parametrize("mid_message", [False, True])
def test_child_exits_when_its_parent_is_killed(tmp_path, mid_message):
    # mid_message: the parent dies in the middle of putting a message on the child's inbox
    # (a keyframe update is ~2 MB with its images): the child's read of it never ends
    script = textwrap.dedent(f"""
        import os, struct, sys, time
        sys.path.insert(0, {os.getcwd()!r})
        from mnemoslam.service.config import load_config
        from mnemoslam.service.mapping.process import MappingProcess
        from mnemoslam.storage import MapStore
        MapStore({str(tmp_path / 'map.db')!r}).close()
        mp = MappingProcess({str(tmp_path / 'map.db')!r}, load_config().loop)
        mp.wait_ready(120)
        if {mid_message!r}:
            os.write(mp._inbox._writer.fileno(), struct.pack("!i", 2_000_000) + bytes(1000))
        print(mp.pid, flush=True)
        time.sleep(600)
    """)
    parent = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True,
                              cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    child = int(parent.stdout.readline())
    time.sleep(1.0)
    parent.kill()
    parent.wait()
    deadline = time.monotonic() + 120  # the child may still be importing (loaded machine)
    while time.monotonic() < deadline:
        try:
            os.kill(child, 0)
        except ProcessLookupError:
            break
        try:
            with open(f"/proc/{child}/stat") as f:
                if f.read().split(")")[-1].split()[0] == "Z":  # exited, not reaped yet
                    break
        except FileNotFoundError:
            break
        time.sleep(0.2)
    else:
        os.kill(child, signal.SIGKILL)
        pytest.fail("the mapping process outlived its parent")
