"""Issue 22 item 3: localization only (`memory.incremental: false`, RTAB-Map's
Mem/IncrementalMemory; per robot: the camera info's `localize`, `mnemoslam stream --localize`).

`walk_a` is mapped first (`mnemoslam run --db`); `walk_b` then localizes against that map. B
starts more than 2 m from A's start in a frame of its own (the identity), relocalizes by
appearance once it walks A's stretch, and from then on its poses go out in A's map frame. The
map file is not written: its sha256 is the same after the run / the stream, and a robot that
localizes inside a mapping service adds no row. B's poses are compared in A's frame as
bench/bench_multisession.py does: A's first pose places A's map frame in the scene (A's
trajectory starts at its ground truth's first pose)."""
import hashlib
import json
import shutil
import threading
import time

import numpy as np
import pytest

from mnemoslam.client.datasets import open_dataset
from mnemoslam.client.kernel.geometry import invert
from mnemoslam.client.kernel.trajectory import read_tum
from mnemoslam.storage import MapStore

from conftest import run_cli as _run
from conftest import service_config

RATE = 5.0  # frames/s of each walk
B_FRAMES = (40, 130)  # walk_b's frames streamed: B starts 2 m off A's path and relocalizes in A's stretch (frame 74)
B_LOCALIZE = (90, 130)  # a shorter range for the per-robot test (B relocalizes soon after it starts)


def _sha(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def walk_a_map(tmp_path_factory):
    """walk_a's first 90 frames (its part B's frames below walk by: its frames 46-81 lie within
    0.5 m of B's 90-149) mapped by `run --db` at 5 frames/s: (the map file, A's map frame -> the
    scene)."""
    root = tmp_path_factory.mktemp("walk_a")
    db = root / "map.db"
    _run(f"synthetic:walk_a?rate={RATE:g}", "--frames", "0:90", "--db", str(db), "--out", str(root / "a"))
    ta, ga = read_tum(root / "a" / "trajectory.tum"), read_tum(root / "a" / "groundtruth.tum")
    assert ta.stamps[0] == ga.stamps[0]
    return db, ga.poses[0] @ invert(ta.poses[0])


def _copy(db, folder):
    folder.mkdir()
    out = folder / "map.db"
    shutil.copy(db, out)
    return out


def _errors(stamps, poses, to_truth) -> np.ndarray:
    """Position errors (m) of B's poses (A's map frame) against B's ground truth."""
    gt = open_dataset(f"synthetic:walk_b?rate={RATE:g}").ground_truth
    k = np.searchsorted(gt.stamps, stamps)
    assert np.allclose(gt.stamps[k], stamps)
    est = np.einsum("ij,njk->nik", to_truth, np.asarray(poses))
    return np.linalg.norm(est[:, :3, 3] - gt.poses[k, :3, 3], axis=1)


@pytest.mark.slow  # (walk_a mapped once for the module: ~30 s; each test 10-25 s)
def test_run_localizes_against_the_map_without_writing_it(walk_a_map, tmp_path):
    """`run walk_b --db A.db --set memory.incremental=false`: the map file's bytes are the same,
    B relocalizes in map 0 after it entered A's stretch (not at its start: it starts in a frame
    of its own) and from then on its poses are in A's frame within 2 cm; the localizer kept
    only its newest keyframes."""
    a_db, to_truth = walk_a_map
    db = _copy(a_db, tmp_path / "map")
    before = _sha(db)
    out = tmp_path / "b"
    printed = _run(f"synthetic:walk_b?rate={RATE:g}", "--frames", f"{B_FRAMES[0]}:{B_FRAMES[1]}", "--db", str(db),
                   "--out", str(out), "--set", "memory.incremental=false", "--set", "memory.localization_nodes=12")
    assert _sha(db) == before  # nothing written: no session, keyframe, word, link
    assert not (out / "map.db").exists()
    with MapStore(db, readonly=True) as store:
        assert len(store.sessions()) == 1
    s = json.loads((out / "summary.json").read_text())
    assert s["localization"] and s["session"] is None and s["map"] == 0, s
    assert s["relocalized_index"] is not None and s["relocalized_index"] > 5, s  # not at once: B starts 2 m off A
    assert f"localization only: relocalized in map 0 at frame {s['relocalized_index']}" in printed
    assert s["forgotten"] > 0 and 12 <= s["held"] <= 24, s  # bounded: it keeps memory.localization_nodes (x2)
    t = read_tum(out / "trajectory.tum")
    after = t.stamps >= s["relocalized_stamp"] - 1e-9
    assert after.sum() >= 30, after.sum()  # (measured: ~70 frames after the first relocalization)
    assert s["frames_in_map"] >= 0.9 * after.sum(), (s["frames_in_map"], after.sum())
    err = _errors(t.stamps[after], t.poses[after], to_truth)
    assert np.mean(err < 0.02) >= 0.9, np.percentile(err, [50, 90, 100])
    # before it relocalized, B's poses are in its own frame: the identity at its first frame, not A's
    assert np.allclose(t.poses[0], np.eye(4), atol=1e-6)


def test_run_localization_needs_an_existing_map(tmp_path, capsys):
    from mnemoslam.service.cli import main

    assert main(["run", "synthetic:walk_b?rate=5", "--frames", "0:3", "--db", str(tmp_path / "none.db"),
                 "--out", str(tmp_path / "o"), "-q", "--set", "memory.incremental=false"]) != 0
    assert "needs a map to localize in" in capsys.readouterr().err
    assert not (tmp_path / "none.db").exists()


def _poses_of(z, robot):
    """Collect the robot's pose messages (decoded) from the service."""
    from mnemoslam.client.kernel import protocol

    got, lock = [], threading.Lock()

    def on(sample):
        m = protocol.decode_pose(sample.payload.to_bytes())
        with lock:
            got.append(m)
    return got, z.declare_subscriber(protocol.KeySpace().pose(robot), on)


@pytest.mark.slow  # (walk_a mapped once for the module: ~30 s; each test 10-25 s)
def test_service_localization_only_publishes_map_frame_poses_and_leaves_the_map_untouched(walk_a_map, tmp_path):
    """A real `serve` (memory.incremental: false) on walk_a's map, walk_b streamed through Zenoh:
    the pose messages say their frame (null = B's own, then map 0 once relocalized: one
    `relocalized` event), >= 90 % of those after the first relocalization are in map 0 within
    2 cm of the truth in A's frame, /robots/B shows the live pose and state, writes are refused
    (409) and the map file's sha256 is unchanged after the service stopped."""
    from mnemoslam.client.kernel import protocol
    from mnemoslam.client.streamer import stream_dataset
    from mnemoslam.client.transport import ZenohSettings, open_session
    from mnemoslam.service.demo import ServiceProcess

    a_db, to_truth = walk_a_map
    db = _copy(a_db, tmp_path / "map")
    before = _sha(db)
    conf = service_config({"memory": {"incremental": False}, "service": {"queue_size": 10000},
                           "loop": {"backlog_images": 100000}, "api": {"token": "t"}})
    svc = ServiceProcess(db, conf).start()
    try:
        z = open_session(ZenohSettings(connect=[svc.endpoint]))
        events = []
        ev = z.declare_subscriber(protocol.KeySpace().events("B"),
                                  lambda s: events.append(protocol.decode_event(s.payload.to_bytes())))
        poses, sub = _poses_of(z, "B")
        try:
            ds = open_dataset(f"synthetic:walk_b?rate={RATE:g}")
            from mnemoslam.client.datasets.subrange import frame_range

            ds = frame_range(ds, B_FRAMES)
            # at the camera's pace (5 frames/s): the map update behind tracking keeps up, as on a robot
            stats = stream_dataset(ds, "B", ZenohSettings(connect=[svc.endpoint]), rate=RATE, progress=False,
                                   wait_for_subscriber=10.0)
            r = svc.wait_processed("B", stats.frames)
            time.sleep(1.0)
        finally:
            sub.undeclare()
            ev.undeclare()
            z.close()
        assert r["mode"] == "localization" and r["session_id"] is None
        assert r["localized"] and r["map"] == 0, r
        assert svc.api.get("/robots")[0]["map"] == 0
        assert len(svc.api.sessions()) == 1  # walk_a's only: B has none
        # reads that make something (the grid's local grids from stored depth) keep it in RAM
        import urllib.error
        import urllib.request

        for path in ("/maps", "/maps/0/grid", "/stats", "/metrics", "/viewer"):
            with urllib.request.urlopen(f"http://127.0.0.1:{svc.http_port}{path}", timeout=60) as answer:
                assert answer.status == 200, path
        # writes are refused: the map is open read-only

        req = urllib.request.Request(f"http://127.0.0.1:{svc.http_port}/nodes/1/label", method="POST",
                                     data=b'{"label": "x"}', headers={"Authorization": "Bearer t",
                                                                      "Content-Type": "application/json"})
        with pytest.raises(urllib.error.HTTPError) as e:
            urllib.request.urlopen(req, timeout=10)
        assert e.value.code == 409
    finally:
        assert svc.stop() == 0
    assert _sha(db) == before
    poses.sort(key=lambda m: m.seq)
    # one pose message per frame tracked; a frame the service drops under load (counted) has none
    assert len(poses) == r["frames_processed"] and r["frames_processed"] + r["frames_dropped"] == stats.frames, (
        len(poses), r["frames_processed"], r["frames_dropped"], stats.frames)
    assert r["frames_dropped"] <= 0.05 * stats.frames, r["frames_dropped"]
    assert all(m.has_map for m in poses)
    assert poses[0].map is None and np.allclose(poses[0].pose, np.eye(4), atol=1e-6)  # its own frame first
    first = next((i for i, m in enumerate(poses) if m.map is not None), None)
    assert first is not None and first > 5, first  # (never in the map's frame: None)
    after = [m for m in poses[first:] if m.pose is not None]
    in_map = [m for m in after if m.map == 0]
    assert len(after) >= 30 and len(in_map) >= 0.9 * len(after), (len(in_map), len(after))
    err = _errors(np.array([m.stamp for m in in_map]), [m.pose for m in in_map], to_truth)
    assert np.sum(err < 0.02) >= 0.9 * len(after), np.percentile(err, [50, 90, 100])
    reloc = [e for e in events if e.kind == "relocalized"]
    assert len(reloc) == 1 and reloc[0]["map"] == 0 and reloc[0]["stamp"] == pytest.approx(poses[first].stamp)
    # the live pose over REST is the last one published
    assert np.allclose(r["position"], poses[-1].pose[:3, 3], atol=1e-6)
    assert np.allclose(np.reshape(r["pose"], (4, 4)), poses[-1].pose, atol=1e-6)


def _rows(db) -> dict:
    with MapStore(db, readonly=True) as store:
        return {"sessions": len(store.sessions()), "nodes": store.count_nodes(), "links": len(store.link_pairs()),
                "words": store.count_words(), "objects": store.count_objects()}


@pytest.mark.slow  # (walk_a mapped once for the module: ~30 s; each test 10-25 s)
def test_a_robot_asks_for_localization_in_a_mapping_service(walk_a_map, tmp_path):
    """A mapping service (the default config), walk_b streamed with `mnemoslam stream
    --localize`: B is localizing over REST, relocalizes in map 0 (its position then in A's
    frame), and the map gains no session, keyframe, link, word or object (a robot that maps
    adds all of those). A robot that maps there next says its poses are in its own session's
    map (the pose messages' `map`)."""
    from mnemoslam.client.streamer import stream_dataset
    from mnemoslam.client.transport import ZenohSettings, open_session
    from mnemoslam.service.cli import main
    from mnemoslam.service.demo import ServiceProcess

    a_db, to_truth = walk_a_map
    db = _copy(a_db, tmp_path / "map")
    before = _rows(db)
    svc = ServiceProcess(db, service_config({"service": {"queue_size": 10000}})).start()
    try:
        start, end = B_LOCALIZE
        assert main(["stream", f"synthetic:walk_b?rate={RATE:g}", "--frames", f"{start}:{end}", "--robot", "B",
                     "--localize", "--rate", f"{RATE:g}", "--connect", svc.endpoint, "-q"]) == 0
        r = svc.wait_processed("B", end - start)
        r = svc.wait_mapped("B")
        r = svc.api.robot("B")
        assert (r["mode"], r["session_id"], r["localized"], r["map"]) == ("localization", None, True, 0), r
        assert _rows(db) == before  # (a keyframe is committed before it is reported: B's would be there)
        z = open_session(ZenohSettings(connect=[svc.endpoint]))
        poses, sub = _poses_of(z, "M")
        try:
            ds = open_dataset(f"synthetic:walk_a?rate={RATE:g}")
            from mnemoslam.client.datasets.subrange import frame_range

            stats = stream_dataset(frame_range(ds, (0, 6)), "M", ZenohSettings(connect=[svc.endpoint]), rate=None,
                                   progress=False, wait_for_subscriber=10.0)
            m = svc.wait_processed("M", stats.frames)
            time.sleep(0.5)
        finally:
            sub.undeclare()
            z.close()
        own = next(s for s in svc.api.sessions() if s["robot"] == "M")
        assert m["mode"] == "mapping" and own["map_id"] == 1
        assert len(poses) == stats.frames and {(p.has_map, p.map) for p in poses} == {(True, 1)}
    finally:
        assert svc.stop() == 0
    gt = open_dataset(f"synthetic:walk_b?rate={RATE:g}").ground_truth
    k = int(np.searchsorted(gt.stamps, r["last_stamp"] - 1e-6))
    assert np.linalg.norm((to_truth @ np.r_[r["position"], 1.0])[:3] - gt.poses[k, :3, 3]) < 0.02

# -- the pieces, cheap ------------------------------------------------------------------------------

def test_read_only_store_refuses_writes_and_leaves_the_file_as_it_was(tmp_path):
    """MapStore(readonly=True): reads work, every write is a StoreError, the file's bytes stay,
    and a file that is not there is an error (not a new map)."""
    from mnemoslam.client.kernel.frames import Calibration, PinholeCamera
    from mnemoslam.storage import StoreError

    db = tmp_path / "m.db"
    cal = Calibration(PinholeCamera(500.0, 500.0, 320.0, 240.0, 640, 480))
    with MapStore(db) as store:
        store.begin_session("r", cal)
    before = _sha(db)
    with MapStore(db, readonly=True) as store:
        assert store.readonly and [s.robot for s in store.sessions()] == ["r"]
        with pytest.raises(StoreError, match="read-only"):
            store.begin_session("r2", cal)
        with pytest.raises(StoreError, match="read-only"):
            store.set_info("x", 1)
    assert _sha(db) == before
    with pytest.raises(StoreError, match="no database"):
        MapStore(tmp_path / "none.db", readonly=True)
    assert not (tmp_path / "none.db").exists()


def test_camera_info_localize_and_the_pose_messages_frame_stay_backward_compatible():
    from mnemoslam.client.kernel import protocol
    from mnemoslam.client.kernel.frames import Calibration, PinholeCamera

    cal = Calibration(PinholeCamera(500.0, 500.0, 320.0, 240.0, 640, 480))
    plain = protocol.encode_info("r1", cal)
    assert b"localize" not in plain and not protocol.decode_info_message(plain).localize  # as before: maps
    assert protocol.decode_info_message(protocol.encode_info("r1", cal, localize=True)).localize
    with pytest.raises(protocol.ProtocolError):
        protocol.decode_info_message(json.dumps({**json.loads(plain), "localize": "yes"}).encode())
    old = protocol.decode_pose(protocol.encode_pose("r1", 3, 1.0, "ok", np.eye(4)))
    assert b'"map"' not in protocol.encode_pose("r1", 3, 1.0, "ok", np.eye(4)) and not old.has_map
    own = protocol.decode_pose(protocol.encode_pose("r1", 3, 1.0, "ok", np.eye(4), map=None))
    assert own.has_map and own.map is None
    assert protocol.decode_pose(protocol.encode_pose("r1", 3, 1.0, "ok", np.eye(4), map=7)).map == 7


def test_a_ros_robot_can_ask_for_localization_too():
    from mnemoslam.service.config import ConfigError, RosConfig
    from mnemoslam.service.ros import parse_robots

    entry = {"robot": "r", "color": "c", "depth": "d", "info": "i"}
    assert not parse_robots(RosConfig(robots=[entry]))[0].localize
    assert parse_robots(RosConfig(robots=[{**entry, "localize": True}]))[0].localize
    with pytest.raises(ConfigError, match="localize"):
        parse_robots(RosConfig(robots=[{**entry, "localize": "yes"}]))


def test_the_transient_map_is_a_map_update_store_that_writes_nothing(tmp_path):
    """TransientMap has every MapUpdateStore method with MapStore's signature (the map update
    calls it as its store); its writes leave the file as it was, links stay in RAM."""
    import inspect

    from mnemoslam.client.kernel.frames import Calibration, PinholeCamera
    from mnemoslam.service.localization import TRANSIENT_BASE, TransientMap
    from mnemoslam.storage import LinkType, MapUpdateStore

    names = [n for n in dir(MapUpdateStore) if not n.startswith("_") and callable(getattr(MapUpdateStore, n))]
    assert len(names) >= 15
    for n in names:
        assert inspect.signature(getattr(TransientMap, n)) == inspect.signature(getattr(MapStore, n)), n
    db = tmp_path / "m.db"
    with MapStore(db) as store:
        store.begin_session("r", Calibration(PinholeCamera(500.0, 500.0, 320.0, 240.0, 640, 480)))
    before = _sha(db)
    with MapStore(db, readonly=True) as store:
        t = TransientMap(store)
        assert isinstance(t, MapUpdateStore)
        k = TRANSIENT_BASE + 3
        t.add_link(1, k, LinkType.GLOBAL_CLOSURE, np.eye(4), np.eye(6))
        t.update_poses({k: np.eye(4)})
        t.set_statistics(k, {"x": 1})
        t.save_node_words(k, np.arange(3))
        assert t.take_map_links() == [(1, k)] and t.take_map_links() == []
        assert t.get_node(k) is None and t.load_images(k) == (None, None) and len(t.made) == 1
        assert [lk[:2] for lk in t.prune({k})] == [] and t.made == []
    assert _sha(db) == before
