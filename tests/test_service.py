"""The service end to end: `mnemoslam serve` in its own process, camera clients streaming
over a real Zenoh session on loopback, the real SQLite file, the real uvicorn server."""
import dataclasses
import signal
import sqlite3
import struct
import threading
import time

import numpy as np
import pytest
import zenoh

from mnemoslam.client.datasets import open_dataset
from mnemoslam.client.kernel import protocol
from mnemoslam.client.planner import ApiError
from mnemoslam.client.streamer import stream_dataset
from mnemoslam.client.transport import ZenohSettings, open_session
from mnemoslam.service.config import load_config
from mnemoslam.service.demo import ServiceProcess, keyframe_trajectory
from mnemoslam.service.evaluation import evaluate
from mnemoslam.service.runner import run_dataset

from conftest import FIGURE8, service_config, slam_config, synthetic

FRAMES = 90


def _settings(svc):
    return ZenohSettings(connect=[svc.endpoint])


@pytest.fixture
def service(tmp_path):
    # idle_timeout: a loaded machine's map update can trail the last frame by more than the
    # default 60 s; the robot must stay listed until the tests have read its map
    svc = ServiceProcess(tmp_path / "map.db",
                         service_config({"service": {"queue_size": 10000, "idle_timeout": 3600.0}})).start()
    yield svc
    svc.stop()


class _Decoded:
    """A dataset's frames as the service receives them: through the wire codec."""

    def __init__(self, dataset, color, depth):
        self.dataset, self.color, self.depth = dataset, color, depth
        self.name, self.calibration, self.ground_truth = dataset.name, dataset.calibration, None

    def __len__(self):
        return len(self.dataset)

    def frame(self, i):
        wire = protocol.encode_frame(self.dataset.frame(i), "x", i, color=self.color, depth=self.depth)
        return protocol.decode_frame(wire).frame


def _offline_keyframes(dataset, color="png", depth="png"):
    """The same frames through the same codec and an offline run in this process (map update
    inline): the keyframes' stamps and final map poses."""
    out = run_dataset(_Decoded(dataset, color, depth), slam_config(), progress=False)
    return out.keyframes.stamps, out.keyframes.poses


def test_streamed_run_matches_offline_run_and_every_keyframe_is_stored(service):
    ds = open_dataset("synthetic:loop", max_frames=FRAMES)
    stats = stream_dataset(ds, "r1", _settings(service), rate=None, color="png", depth="png",
                           progress=False, wait_for_subscriber=10.0)
    robot = service.wait_processed("r1", stats.frames)
    assert robot["frames_processed"] == FRAMES and robot["frames_dropped"] == 0
    # the map update behind tracking catches up: every keyframe mapped, no backlog
    mapped = service.wait_mapped("r1", timeout=120)
    assert mapped["keyframes_mapped"] == robot["keyframes"] and mapped["map_backlog"] == 0
    session = service.session_of("r1")
    streamed = keyframe_trajectory(service.api, session)
    stamps, poses = _offline_keyframes(ds)
    assert len(streamed) == len(stamps) == robot["keyframes"]
    np.testing.assert_allclose(streamed.stamps, stamps, atol=1e-6)
    # the same map: the service writes poses that moved by more than the graph's 0.1 mm tolerance
    assert np.abs(streamed.poses[:, :3, 3] - poses[:, :3, 3]).max() < 1e-3
    nodes = service.api.nodes(session, limit=1000)
    assert nodes["total"] == robot["keyframes"]


def test_loop_closed_and_map_corrected_events_are_published(service):
    """A subscriber of mnemoslam/<robot>/events sees the map update's events with the fields
    documented in client/kernel/protocol.py."""
    events = []
    z = open_session(_settings(service))
    sub = z.declare_subscriber(protocol.KeySpace().events("ev"), lambda s: events.append(
        protocol.decode_event(s.payload.to_bytes())))
    try:
        # the figure-8's first 260 frames (~200 keyframes): the second lap revisits the first from
        # frame ~190 on (~90 loops); its frames rendered once for the session (tests/conftest.py)
        ds = synthetic("figure8", **FIGURE8, max_frames=260)
        stats = stream_dataset(ds, "ev", _settings(service), rate=None, progress=False, wait_for_subscriber=10.0)
        service.wait_processed("ev", stats.frames)
        service.wait_mapped("ev", timeout=180)
        time.sleep(0.5)  # the last events are on their way
    finally:
        sub.undeclare()
        z.close()
    kinds = [e.kind for e in events]
    assert kinds[0] == "session_started" and isinstance(events[0]["session_id"], int)
    closed = [e for e in events if e.kind == "loop_closed"]
    assert closed, f"no loop_closed among {sorted(set(kinds))}"
    keyframes = {e["node_id"] for e in events if e.kind == "keyframe_added"}
    for e in closed:
        assert e["robot"] == "ev" and e["link"] in ("loop", "proximity", "merged")
        assert e["from"] in keyframes and e["to"] in keyframes and e["from"] < e["to"]
        assert isinstance(e["inliers"], int) and e["inliers"] > 0
    corrected = [e for e in events if e.kind == "map_corrected"]
    assert corrected and all(isinstance(e["nodes"], int) and e["nodes"] > 0 for e in corrected)
    graph = service.api.get(f"/sessions/{service.session_of('ev')}/graph")
    loops = {(lk["from"], lk["to"]) for lk in graph["links"] if lk["type"] in ("loop", "proximity")}
    assert loops == {(e["from"], e["to"]) for e in closed if e["link"] != "merged"}
    merged = {(lk["from"], lk["to"]) for lk in graph["links"] if lk["type"] == "merged"}
    assert {(e["from"], e["to"]) for e in closed if e["link"] == "merged"} <= merged


def test_three_robots_three_sessions_no_cross_talk(service):
    paths = {"alpha": "loop", "bravo": "walk_a", "charlie": "walk_b"}
    datasets = {r: open_dataset(f"synthetic:{p}", max_frames=45) for r, p in paths.items()}
    threads = [threading.Thread(target=stream_dataset, args=(ds, r, _settings(service)),
                                kwargs=dict(rate=None, color="jpeg", depth="png", progress=False,
                                            wait_for_subscriber=10.0))
               for r, ds in datasets.items()]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for robot, ds in datasets.items():
        r = service.wait_processed(robot, len(ds))
        assert r["frames_processed"] == len(ds)
        traj = keyframe_trajectory(service.api, service.session_of(robot))
        ev = evaluate(ds.ground_truth, traj)  # each map follows its own camera
        assert ev.ate_rmse < 0.05, (robot, ev.ate_rmse)
    sessions = service.api.sessions()
    assert sorted(s["robot"] for s in sessions) == sorted(paths)


def _malformed(rng, valid: bytes):
    kinds = ["random", "truncated", "bitflip", "version", "oversize_claim", "nan_stamp"]
    kind = kinds[rng.integers(len(kinds))]
    if kind == "random":
        return rng.integers(0, 256, rng.integers(0, 4000), dtype=np.uint8).tobytes()
    if kind == "truncated":
        return valid[: rng.integers(0, len(valid) - 1)]
    b = bytearray(valid)
    if kind == "bitflip":
        i = rng.integers(0, 64)  # somewhere in the header
        b[i] ^= 1 << int(rng.integers(8))
        return bytes(b) if bytes(b) != valid else b"x"
    if kind == "version":
        b[4] = 99
        return bytes(b)
    if kind == "oversize_claim":  # header claims a 65535 x 65535 image
        b[29:33] = b"\xff\xff\xff\xff"
        return bytes(b)
    b[18:26] = struct.pack("<d", float("nan"))  # NaN stamp
    return bytes(b)


def test_malformed_flood_is_counted_and_valid_robot_unaffected(service):
    ds = open_dataset("synthetic:loop", max_frames=60)
    valid = protocol.encode_frame(ds.frame(0), "evil", 0, color="jpeg", depth="png")
    rng = np.random.default_rng(0)
    keys = protocol.KeySpace()
    z = open_session(_settings(service))
    sent = 0
    try:
        time.sleep(1.0)
        streamer = threading.Thread(target=stream_dataset, args=(ds, "good", _settings(service)),
                                    kwargs=dict(rate=30.0, progress=False, wait_for_subscriber=10.0))
        streamer.start()
        pub_evil = z.declare_publisher(keys.frame("evil"), congestion_control=zenoh.CongestionControl.BLOCK)
        pub_other = z.declare_publisher(keys.frame("mallory"), congestion_control=zenoh.CongestionControl.BLOCK)
        for i in range(1100):
            payload = _malformed(rng, valid)
            try:
                protocol.decode_frame(payload)
                continue  # a flip that still decodes is not malformed
            except protocol.ProtocolError:
                pass
            (pub_evil if i % 2 else pub_other).put(payload)
            sent += 1
        # robot id in the header differs from the key: also refused
        pub_other.put(valid)
        sent += 1
        streamer.join()
    finally:
        z.close()
    assert sent >= 1000
    robot = service.wait_processed("good", len(ds))
    deadline = time.monotonic() + 30
    while service.api.stats()["service"]["rejected_total"] < sent and time.monotonic() < deadline:
        time.sleep(0.2)
    stats = service.api.stats()
    assert stats["service"]["rejected_total"] == sent
    assert service.api.health()["status"] == "ok"
    assert robot["frames_processed"] == len(ds) and robot["lost"] == 0
    assert {r["robot"] for r in service.api.robots()} == {"good"}  # malformed traffic made no session
    traj = keyframe_trajectory(service.api, service.session_of("good"))
    assert evaluate(ds.ground_truth, traj).ate_rmse < 0.02


def test_sigkill_mid_stream_keeps_every_reported_keyframe(tmp_path):
    db = tmp_path / "map.db"
    svc = ServiceProcess(db, {"service": {"queue_size": 10000}}).start()
    reported = []
    z = open_session(ZenohSettings(connect=[svc.endpoint]))
    sub = z.declare_subscriber(protocol.KeySpace().events("k1"), lambda s: reported.append(
        protocol.decode_event(s.payload.to_bytes())))
    ds = open_dataset("synthetic:loop", max_frames=600)
    t = threading.Thread(target=stream_dataset, args=(ds, "k1", ZenohSettings(connect=[svc.endpoint])),
                         kwargs=dict(rate=60.0, progress=False, wait_for_subscriber=10.0), daemon=True)
    t.start()
    deadline = time.monotonic() + 120
    while sum(e["kind"] == "keyframe_added" for e in reported) < 15 and time.monotonic() < deadline:
        time.sleep(0.05)
    svc.proc.send_signal(signal.SIGKILL)
    svc.proc.wait()
    stored = [e["node_id"] for e in list(reported) if e["kind"] == "keyframe_added"]
    sub.undeclare()
    z.close()
    assert len(stored) >= 15
    with sqlite3.connect(db) as conn:
        assert conn.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    svc2 = ServiceProcess(db).start(timeout=180)  # restarts on the same database (its map backlog mapped first)
    try:
        session = svc2.api.sessions()[0]
        assert session["end_reason"] == "crashed"  # found open at start-up
        ids = {n["id"] for n in svc2.api.nodes(session["id"], limit=10000)["nodes"]}
        assert set(stored) <= ids
    finally:
        svc2.stop()


@pytest.fixture(scope="module")
def service_with_p1(tmp_path_factory):
    """A service holding one short session (robot p1, 5 frames), shared by the parameter
    cases: each only reads it, and each used to start its own service holding the same."""
    svc = ServiceProcess(tmp_path_factory.mktemp("p1") / "map.db",
                         service_config({"service": {"queue_size": 10000}})).start()
    try:
        ds = open_dataset("synthetic:loop", max_frames=5)
        stream_dataset(ds, "p1", _settings(svc), rate=None, progress=False, wait_for_subscriber=10.0)
        svc.wait_processed("p1", 5)
        yield svc
    finally:
        svc.stop()


@pytest.mark.parametrize("path,status", [
    ("/sessions/999/nodes", 404),
    ("/robots/nobody", 404),
    ("/sessions/1/nodes?bbox=1,2,3", 400),
    ("/sessions/1/nodes?bbox=a,b,c,d,e,f", 400),
    ("/sessions/1/nodes?limit=0", 422),
    ("/sessions/1/trajectory?format=xml", 422),
    ("/sessions/abc/graph", 422),
])
def test_rest_bad_parameters_are_clear_4xx(service_with_p1, path, status):
    service = service_with_p1
    assert [s["robot"] for s in service.api.sessions()] == ["p1"]  # the one session, as in a fresh service
    with pytest.raises(ApiError) as e:
        service.api.get(path)
    assert e.value.status == status and e.value.detail


# -- rough edges of a first use (issue 24) ------------------------------------------------------

def test_camera_restart_ends_the_session_and_the_same_sequence_maps_again(service):
    """The same sequence streamed twice under one robot id (its stamps start again from 0, as
    after a camera or clock restart, more than service.restart_gap = 5 s back): the first
    session ends "restarted", a second one maps the second pass; the camera hears of it
    (session_ended, session_started). A small step back stays a refused frame (stamp_order)."""
    from mnemoslam.client.streamer import CameraStreamer

    ds = synthetic("loop", rate=5, max_frames=35)  # stamps 0 .. 6.8 s: the second pass starts 6.8 s back
    events = []
    z = open_session(_settings(service))
    sub = z.declare_subscriber(protocol.KeySpace().events("again"), lambda s: events.append(
        protocol.decode_event(s.payload.to_bytes())))
    try:
        first = stream_dataset(ds, "again", _settings(service), rate=None, progress=False, wait_for_subscriber=10.0)
        service.wait_processed("again", len(ds))
        second = stream_dataset(ds, "again", _settings(service), rate=None, progress=False, wait_for_subscriber=10.0)
        robot = service.wait_processed("again", 2 * len(ds))
        # jitter: a frame 0.5 s before the last one is refused, and the camera is told why
        with CameraStreamer(z, "again", ds.calibration, color="png", depth="png") as cam:
            assert cam.wait_for_subscriber(10.0)
            last = ds.frame(len(ds) - 1)
            cam.send(dataclasses.replace(last, stamp=last.stamp - 0.5), 0)
            deadline = time.monotonic() + 20
            while not getattr(cam, "rejected", None) and time.monotonic() < deadline:
                time.sleep(0.05)
            rejected = dict(getattr(cam, "rejected", {}))
            detail = getattr(cam, "rejected_detail", {}).get("stamp_order", "")
        robot = service.wait_mapped("again", timeout=120)
    finally:
        sub.undeclare()
        z.close()
    sessions = [s for s in service.api.sessions() if s["robot"] == "again"]
    assert [s["end_reason"] for s in sessions] == ["restarted", None]  # (the second pass was refused: one session)
    assert robot["frames_processed"] == 2 * len(ds) and robot["restarts"] == 1
    assert robot["frames_rejected"] == {"stamp_order": 1}
    assert rejected == {"stamp_order": 1} and "restart_gap" in detail
    assert first.rejected_total == 0 and second.rejected_total == 0 and second.answered == len(ds)
    old, new = (s["id"] for s in sessions)
    assert robot["session_id"] == new and second.restarts == 1 and second.sessions == [new]
    for sid in (old, new):  # both passes mapped: as many keyframes each
        assert service.api.nodes(sid, limit=1)["total"] >= 5
    assert service.api.nodes(old, limit=1)["total"] == service.api.nodes(new, limit=1)["total"]
    kinds = [(e.kind, e.get("session_id"), e.get("reason")) for e in events
             if e.kind in ("session_started", "session_ended")]
    assert kinds == [("session_started", old, None), ("session_ended", old, "restarted"),
                     ("session_started", new, None)]
    assert "camera restart robot=again" in service.log_path.read_text()
    assert 'mnemoslam_robot_restarts_total{robot="again"} 1.0' in service.api.get("/metrics")
    assert load_config().service.restart_gap == 5.0  # the default, which the service ran with


def test_stream_whose_frames_are_all_refused_says_so_and_exits_1(service, capsys):
    """A short sequence streamed twice under one robot id: its stamps step back by less than
    service.restart_gap, so the service refuses the second pass (stamp_order); `stream`
    prints the refusals, names the reason and exits 1 instead of 0."""
    from mnemoslam.service.cli import main

    args = ["stream", "synthetic:loop", "--robot", "twice", "--connect", service.endpoint, "--max-frames", "12", "-q"]
    assert main(args) == 0
    out, err = capsys.readouterr()
    assert "the service answered 12 and dropped 0" in out and "rejected" not in out
    assert main(args) == 1
    out, err = capsys.readouterr()
    assert "the service answered 0 and dropped 0, rejected 12 (stamp_order: 12)" in out
    assert "stream: error: the service refused 12 of 12 frames (stamp_order: 12): stamp_order" in err
    assert service.api.robot("twice")["frames_rejected"] == {"stamp_order": 12}


def test_stream_labels_of_a_dataset_without_labels_leaves_no_robot(service, tmp_path):
    """`stream <real dataset> --labels` fails before its camera is announced: the service
    admits no robot that would wait for frames."""
    from mnemoslam.service.cli import main
    from tests.test_datasets import make_tum

    tum = make_tum(tmp_path)
    assert main(["stream", str(tum), "--robot", "ghost", "--connect", service.endpoint, "--labels", "-q"]) == 2
    time.sleep(2.0)  # a camera info would have reached the service by now
    assert [r["robot"] for r in service.api.robots()] == []
    assert service.api.sessions() == []


def test_sessions_filter_by_robot_and_keep_their_config_apart(service_with_p1):
    service = service_with_p1
    (p1,) = service.api.get("/sessions", robot="p1")
    assert service.api.get("/sessions", robot="nobody") == []
    assert "config" not in p1 and p1["robot"] == "p1" and p1["calibration"]["width"] == 640
    one = service.api.get(f"/sessions/{p1['id']}")
    assert one["config"]["service"]["restart_gap"] == 5.0 and {**one, "config": None} == {**p1, "config": None}
    with pytest.raises(ApiError) as e:
        service.api.get("/sessions/999")
    assert e.value.status == 404


def test_config_hides_the_environment_token_and_no_lock_file_stays(tmp_path, monkeypatch):
    """/config shows the token as *** when it comes from MNEMOSLAM_API_TOKEN; after a clean
    stop nothing but the database is left beside it (no <db>-mapping.lock)."""
    monkeypatch.setenv("MNEMOSLAM_API_TOKEN", "secret-from-env")
    svc = ServiceProcess(tmp_path / "map.db", service_config()).start()
    try:
        assert svc.api.get("/config")["api"]["token"] == "***"
        stream_dataset(open_dataset("synthetic:loop", max_frames=5), "lk", _settings(svc), rate=None,
                       progress=False, wait_for_subscriber=10.0)
        svc.wait_processed("lk", 5)
        lock = tmp_path / "map.db-mapping.lock"  # the mapping process holds it while it runs
        deadline = time.monotonic() + 60
        while not lock.exists() and time.monotonic() < deadline:
            time.sleep(0.1)
        assert lock.exists()
    finally:
        assert svc.stop() == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map.db"]
