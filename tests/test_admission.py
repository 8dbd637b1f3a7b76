"""Hostile and clumsy input against the real service (`mnemoslam serve` in its own process,
real Zenoh on loopback, real SQLite): robot slots are given on calibration and expire, frames
are bounded by the calibration before decoding, stamps must increase, calibration is taken
only from the robot's own key, and the camera sees the service's drops."""
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import zenoh

from mnemoslam.client.datasets import open_dataset
from mnemoslam.client.kernel import protocol
from mnemoslam.client.planner import ApiError
from mnemoslam.client.streamer import stream_dataset
from mnemoslam.client.transport import ZenohSettings, open_session
from mnemoslam.service.demo import ServiceProcess, keyframe_trajectory
from mnemoslam.service.evaluation import evaluate

from conftest import service_config

KEYS = protocol.KeySpace()


def _settings(svc):
    return ZenohSettings(connect=[svc.endpoint])


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError("no VmRSS")


def _until(cond, timeout=20.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        v = cond()
        if v:
            return v
        time.sleep(0.1)
    return cond()


def _rejected(svc) -> dict:
    return svc.api.stats()["service"]["rejected"]


@pytest.fixture(scope="module")
def svc(tmp_path_factory):
    s = ServiceProcess(tmp_path_factory.mktemp("adm") / "map.db",
                       service_config({"service": {"max_robots": 4, "idle_timeout": 3.0, "info_timeout": 0.5}})).start()
    yield s
    s.stop()


@pytest.fixture(scope="module")
def dataset():
    return open_dataset("synthetic:loop", max_frames=40)


@pytest.fixture
def z(svc):
    session = open_session(_settings(svc))
    yield session
    session.close()


def _publisher(z, robot):
    return z.declare_publisher(KEYS.frame(robot), congestion_control=zenoh.CongestionControl.BLOCK)


def _wait_no_robots(svc):
    assert _until(lambda: not svc.api.robots(), timeout=15), svc.api.robots()


def test_frames_of_unknown_robots_take_no_slot_and_a_camera_then_maps_normally(svc, z, dataset):
    _wait_no_robots(svc)
    before = _rejected(svc).get("no_calibration", 0)
    frame = dataset.frame(0)
    for i in range(300):  # hundreds of made-up robot ids, one frame each, no camera info
        robot = f"fake{i}"
        # BLOCK: a loaded machine must not drop them on the way (put's default drops under congestion)
        z.put(KEYS.frame(robot), protocol.encode_frame(frame, robot, 0, color="jpeg", depth="png"),
              congestion_control=zenoh.CongestionControl.BLOCK)
    assert _until(lambda: _rejected(svc).get("no_calibration", 0) - before >= 300), _rejected(svc)
    assert svc.api.robots() == []
    stats = stream_dataset(dataset, "real", _settings(svc), rate=None, progress=False, wait_for_subscriber=10.0)
    r = svc.wait_processed("real", stats.frames)
    assert r["frames_processed"] == len(dataset) and r["frames_dropped"] == 0 and not r["frames_rejected"]
    assert stats.answered == len(dataset) and stats.dropped == 0
    assert evaluate(dataset.ground_truth, keyframe_trajectory(svc.api, svc.session_of("real"))).ate_rmse < 0.02
    assert [x["robot"] for x in svc.api.robots()] == ["real"]


def test_slots_are_bounded_and_idle_ones_expire(svc, z, dataset):
    _wait_no_robots(svc)
    before = _rejected(svc).get("too_many_robots", 0)
    for i in range(6):  # squatters: camera info, never a frame; two more than the 4 slots
        z.put(KEYS.info(f"squat{i}"), protocol.encode_info(f"squat{i}", dataset.calibration))
    assert _until(lambda: len(svc.api.robots()) == 4)
    assert _until(lambda: _rejected(svc).get("too_many_robots", 0) - before == 2)
    assert svc.api.health()["robots"] == 4
    # a real camera while every slot is taken: refused at first, admitted once the idle squatters
    # expire (idle_timeout 3 s), asked for its info again because its frames keep coming
    longer = open_dataset("synthetic:loop", max_frames=150)  # 7.5 s at 20 Hz: frames keep coming past the expiry
    # (answer_timeout: the last answers may trail the last frame by seconds on a loaded machine; with
    # the default 2 s the stream once closed 3 answers short of what the service processed)
    stats = stream_dataset(longer, "late", _settings(svc), rate=20.0, progress=False, wait_for_subscriber=10.0,
                           answer_timeout=30.0)
    r = svc.wait_processed("late", 1, timeout=30)
    assert r["frames_processed"] > 0 and r["frames_dropped"] == 0
    assert stats.answered == r["frames_processed"]
    assert not any(x["robot"].startswith("squat") for x in svc.api.robots())
    assert any(s["robot"] == "late" for s in svc.api.sessions())


def test_calibration_only_from_the_robots_own_key_and_kept_before_its_first_frame(svc, z, dataset):
    _wait_no_robots(svc)
    before = _rejected(svc).get("bad_info", 0)
    z.put(KEYS.info("bob"), protocol.encode_info("alice", dataset.calibration))  # alice's info on bob's key
    assert _until(lambda: _rejected(svc).get("bad_info", 0) == before + 1)
    assert svc.api.robots() == []
    # info put before any frame, and no queryable to answer a later query: the put is what is kept
    z.put(KEYS.info("early"), protocol.encode_info("early", dataset.calibration))
    assert _until(lambda: [x["robot"] for x in svc.api.robots()] == ["early"])
    pub = _publisher(z, "early")
    for i in range(10):
        pub.put(protocol.encode_frame(dataset.frame(i), "early", i, color="raw", depth="raw"))
    r = svc.wait_processed("early", 10)
    assert r["frames_processed"] == 10 and not r["frames_rejected"]
    pub.undeclare()


def test_frames_that_beat_the_camera_info_are_held_until_it_arrives(svc, z, dataset):
    """A stream's first frames can reach the service before its camera info: the newest
    `service.hold_frames` (2) are kept undecoded and mapped once the info arrives, in order;
    older ones are counted `no_calibration`."""
    _wait_no_robots(svc)
    before = _rejected(svc).get("no_calibration", 0)
    pub = _publisher(z, "racer")
    for i in range(5):  # no camera info anywhere yet, no queryable to answer the service's ask
        pub.put(protocol.encode_frame(dataset.frame(i), "racer", i, color="jpeg", depth="png"))
    assert _until(lambda: _rejected(svc).get("no_calibration", 0) - before == 3)
    z.put(KEYS.info("racer"), protocol.encode_info("racer", dataset.calibration))  # within info_timeout + 1 s
    r = svc.wait_processed("racer", 2)
    assert r["frames_processed"] == 2 and not r["frames_rejected"] and r["frames_dropped"] == 0
    for i in range(5, 8):  # the stream goes on after the held frames
        pub.put(protocol.encode_frame(dataset.frame(i), "racer", i, color="jpeg", depth="png"))
    r = svc.wait_processed("racer", 5)
    assert r["frames_processed"] == 5 and not r["frames_rejected"]
    first = _until(lambda: svc.api.trajectory(svc.session_of("racer"))["poses"])
    assert first[0]["stamp"] == pytest.approx(dataset.frame(3).stamp)  # the map starts at the oldest held frame
    assert _rejected(svc).get("no_calibration", 0) - before == 3
    pub.undeclare()


def test_held_frames_of_a_camera_that_never_answers_are_counted_and_freed(svc, z, dataset):
    _wait_no_robots(svc)
    before = _rejected(svc).get("no_calibration", 0)
    pub = _publisher(z, "mute")
    for i in range(2):  # held (hold_frames 2) ...
        pub.put(protocol.encode_frame(dataset.frame(i), "mute", i, color="jpeg", depth="png"))
    # ... and counted once info_timeout (0.5 s) + 1 s passed without its camera info
    assert _until(lambda: _rejected(svc).get("no_calibration", 0) - before == 2, timeout=10)
    z.put(KEYS.info("mute"), protocol.encode_info("mute", dataset.calibration))
    assert _until(lambda: any(x["robot"] == "mute" for x in svc.api.robots()))
    time.sleep(0.5)
    assert svc.api.robot("mute")["frames_processed"] == 0  # nothing held was left to replay
    pub.undeclare()


def test_non_increasing_stamps_are_rejected_and_counted(svc, z, dataset):
    _wait_no_robots(svc)
    z.put(KEYS.info("clock"), protocol.encode_info("clock", dataset.calibration))
    assert _until(lambda: any(x["robot"] == "clock" for x in svc.api.robots()))
    pub = _publisher(z, "clock")
    stamps = [0.0, 0.1, 0.05, 0.1, 0.2, 0.0, 0.3]  # 0.05, the second 0.1 and the late 0.0 go back
    for seq, stamp in enumerate(stamps):
        f = dataset.frame(seq)
        f.stamp = stamp
        pub.put(protocol.encode_frame(f, "clock", seq, color="raw", depth="raw"))
    r = svc.wait_processed("clock", len(stamps))
    assert r["frames_processed"] == 4 and r["frames_rejected"] == {"stamp_order": 3}
    traj = svc.api.trajectory(svc.session_of("clock"))["poses"]
    assert all(b["stamp"] > a["stamp"] for a, b in zip(traj, traj[1:]))
    pub.undeclare()


def test_decoded_size_bomb_is_refused_before_decoding(svc, z, dataset):
    _wait_no_robots(svc)
    z.put(KEYS.info("small"), protocol.encode_info("small", dataset.calibration))  # 640×480
    assert _until(lambda: any(x["robot"] == "small" for x in svc.api.robots()))
    # a 4096² PNG of one colour is a few kB on the wire and 48 MB (+ 64 MB depth) decoded
    big = np.zeros((4096, 4096, 3), np.uint8)
    colour = cv2.imencode(".png", big)[1].tobytes()
    depth = cv2.imencode(".png", np.zeros((4096, 4096), np.uint16))[1].tobytes()
    rss0 = _rss_mb(svc.proc.pid)
    before = dict(_rejected(svc))
    for robot in ("small", "nocal"):
        header = protocol.encode_frame(dataset.frame(0), robot, 0, color="png", depth="png")
        # same message layout with the big payloads: patch width/height and payload lengths
        wire = bytearray(header[:protocol.FIXED_HEADER_BYTES + len(robot) + 8])
        wire[29:33] = (4096).to_bytes(2, "little") * 2
        n = protocol.FIXED_HEADER_BYTES + len(robot)
        wire[n:n + 8] = len(colour).to_bytes(4, "little") + len(depth).to_bytes(4, "little")
        pub = _publisher(z, robot)
        for _ in range(8):
            pub.put(bytes(wire) + colour + depth)
        pub.undeclare()
    # the robot's own count first, polled while it is still there (it sends nothing valid, so it
    # expires idle_timeout after its camera info: a loaded machine must not outwait that)
    def counted():
        try:
            r = svc.api.robot("small")
        except ApiError:  # expired: the assertion below says so
            return None
        return r if r["frames_rejected"].get("size_mismatch", 0) >= 8 else None
    small = _until(counted)
    assert small and small["frames_rejected"] == {"size_mismatch": 8}, small
    after = _until(lambda: (lambda r: r if r.get("size_mismatch", 0) - before.get("size_mismatch", 0) == 8
                            and r.get("no_calibration", 0) - before.get("no_calibration", 0) == 8 else None)(
        _rejected(svc)))
    assert after, _rejected(svc)
    assert _rss_mb(svc.proc.pid) - rss0 < 60  # nothing was decoded (one decode would be 112 MB)


class _Rendered:
    """A dataset's frames rendered beforehand: the client then sends faster than any service."""

    def __init__(self, dataset):
        self.name, self.calibration = dataset.name, dataset.calibration
        self.frames = [dataset.frame(i) for i in range(len(dataset))]

    def __len__(self):
        return len(self.frames)

    def __iter__(self):
        return iter(self.frames)


def test_the_camera_sees_the_services_drops_and_flow_control_avoids_them(tmp_path):
    ds = _Rendered(open_dataset("synthetic:loop", max_frames=60))
    svc = ServiceProcess(tmp_path / "map.db", service_config({"service": {"queue_size": 1}})).start()
    try:
        fast = stream_dataset(ds, "fast", _settings(svc), rate=500.0, progress=False, wait_for_subscriber=10.0,
                              answer_timeout=30.0)  # (every answer in, as in test_slots_are_bounded_…)
        r = svc.wait_processed("fast", fast.frames)
        assert r["frames_dropped"] > 0
        assert fast.dropped == r["frames_dropped"]  # told by the pose messages
        assert fast.answered == r["frames_processed"]
        paced = stream_dataset(ds, "paced", _settings(svc), rate=None, window=1, progress=False,
                               wait_for_subscriber=10.0)
        r = svc.wait_processed("paced", paced.frames)
        assert r["frames_dropped"] == 0 and r["frames_processed"] == len(ds) == paced.answered
    finally:
        svc.stop()
