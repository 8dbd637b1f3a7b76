"""The camera client over real Zenoh sessions on loopback (free ports, scouting off), and the
video-file capture source."""
from __future__ import annotations

import argparse
import logging
import os
import socket
import threading
import time
import uuid

import cv2
import numpy as np
import pytest

from mnemoslam.client.capture import CaptureSource, default_calibration
from mnemoslam.client.datasets import open_dataset
from mnemoslam.client.kernel.frames import DatasetError, Frame
from mnemoslam.client.kernel.protocol import (
    KeySpace,
    ProtocolError,
    decode_frame,
    decode_info,
    decode_info_message,
    encode_pose,
    peek_seq,
    quantize_depth,
)
from mnemoslam.client.streamer import CameraStreamer, add_stream_arguments, stream_dataset, stream_main
from mnemoslam.client.transport import DEFAULT_ENDPOINT, TransportError, ZenohSettings, open_session


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


class Collector:
    """A service-like session listening on a free port, subscribed to all frames and infos,
    which answers each frame with a pose message (no pose) as the service does: the camera's
    flow control (`stream_dataset` with `rate=None` keeps at most `window` frames unanswered)
    then goes on at once, where a collector that never answered made it wait `answer_timeout`
    (2 s) for every frame beyond the window (20 frames: ~34 s of the suite's time)."""

    def __init__(self, prefix: str):
        self.port = free_port()
        self.keyspace = KeySpace(prefix)
        self.session = open_session(ZenohSettings.service([endpoint(self.port)]))
        self.frames: list[tuple[str, bytes]] = []
        self.infos: list[tuple[str, bytes]] = []
        self.lock = threading.Lock()
        self._subs = [
            self.session.declare_subscriber(self.keyspace.frames_wildcard(), self._on(self.frames, answer=True)),
            self.session.declare_subscriber(self.keyspace.info_wildcard(), self._on(self.infos)),
        ]

    def _on(self, store, answer: bool = False):
        def callback(sample):
            key, payload = str(sample.key_expr), sample.payload.to_bytes()
            with self.lock:
                store.append((key, payload))
            seq, robot = peek_seq(payload), self.keyspace.robot_of(key)
            if answer and seq is not None and robot is not None:
                self.session.put(self.keyspace.pose(robot), encode_pose(robot, seq, 0.0, "ok", None))
        return callback

    @property
    def client_settings(self) -> ZenohSettings:
        return ZenohSettings.client([endpoint(self.port)])

    def wait_frames(self, n: int, timeout: float = 10.0) -> list[tuple[str, bytes]]:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            with self.lock:
                if len(self.frames) >= n:
                    break
            time.sleep(0.01)
        with self.lock:
            return list(self.frames)

    def close(self):
        self.session.close()


@pytest.fixture
def collector():
    c = Collector(f"test{uuid.uuid4().hex[:8]}")
    yield c
    c.close()


def test_settings_defaults():
    assert ZenohSettings.service().listen == [DEFAULT_ENDPOINT] == ["tcp/127.0.0.1:7447"]
    assert ZenohSettings.client().connect == [DEFAULT_ENDPOINT] and ZenohSettings.client().listen == []
    s = ZenohSettings()
    assert (s.mode, s.multicast_scouting, s.gossip_scouting) == ("peer", False, False)
    conf = ZenohSettings.client(["tcp/127.0.0.1:1234"]).to_config()
    assert '"tcp/127.0.0.1:1234"' in conf.get_json("connect/endpoints")
    assert conf.get_json("scouting/multicast/enabled") == "false"
    assert conf.get_json("scouting/gossip/enabled") == "false"
    assert conf.get_json("transport/shared_memory/enabled") == "true"  # zenoh's default for cameras
    # the service's session has shared memory off (issue 24: zenoh 1.10 kept every camera
    # session's 16 MB pool mapped in the service after the camera left)
    from mnemoslam.service.config import Config

    assert Config().zenoh.shared_memory is False
    assert ZenohSettings(shared_memory=False).to_config().get_json("transport/shared_memory/enabled") == "false"
    with pytest.raises(ValueError):
        ZenohSettings(mode="server").validate()
    with pytest.raises(ValueError):
        ZenohSettings(connect="tcp/127.0.0.1:1").validate()
    # client mode with nobody listening fails at once, as a ConnectionError (an OSError)
    with pytest.raises(TransportError):
        open_session(ZenohSettings(mode="client", connect=[endpoint(free_port())]))
    assert issubclass(TransportError, OSError)


def test_stream_synthetic_loop(collector):
    dataset = open_dataset("synthetic:loop")
    stats = stream_dataset(dataset, "bot1", collector.client_settings, prefix=collector.keyspace.prefix,
                           progress=False, max_frames=20, wait_for_subscriber=5.0, color="jpeg", depth="png")
    assert stats.frames == 20 and stats.subscriber and stats.bytes > 0 and stats.fps > 0 and stats.mbps > 0
    received = collector.wait_frames(20)
    assert len(received) == 20
    total = 0
    for k, (key, payload) in enumerate(received):
        assert collector.keyspace.robot_of(key) == "bot1"
        w = decode_frame(payload)
        total += w.size
        assert (w.robot, w.seq, w.kind, w.color_encoding, w.depth_encoding) == ("bot1", k, "rgbd", "jpeg", "png")
        ref = dataset.frame(k)
        assert w.frame.stamp == ref.stamp
        valid = ref.depth > 0
        np.testing.assert_array_equal(w.frame.depth == 0, ~valid)
        assert np.abs(w.frame.depth[valid] - ref.depth[valid]).max() <= 0.001
        np.testing.assert_array_equal(w.frame.depth, quantize_depth(ref.depth, 1000.0) / np.float32(1000.0))
        assert np.abs(w.frame.image.astype(int) - ref.image.astype(int)).mean() < 4.0
    assert total == stats.bytes
    # the camera info was put once at start
    assert len(collector.infos) == 1
    key, info = collector.infos[0]
    robot, cal = decode_info(info)
    assert key == collector.keyspace.info("bot1") and robot == "bot1" and cal == dataset.calibration


def test_late_session_gets_camera_info():
    """A service that starts after the camera asks the queryable for the camera info."""
    ks = KeySpace(f"late{uuid.uuid4().hex[:8]}")
    port = free_port()
    dataset = open_dataset("synthetic:loop", max_frames=2)
    cam_session = open_session(ZenohSettings.service([endpoint(port)]))  # the camera listens here
    try:
        with CameraStreamer(cam_session, "late-bot", dataset.calibration, ks, color="png", depth="raw") as cam:
            assert not cam.has_subscriber
            cam.send(dataset.frame(0), 0)  # nobody listening: not stored, not an error
            late = open_session(ZenohSettings.client([endpoint(port)]))
            try:
                replies = []
                end = time.monotonic() + 5.0
                while not replies and time.monotonic() < end:
                    replies = [r for r in late.get(ks.info("late-bot"), timeout=1.0) if r.ok is not None]
                    if not replies:
                        time.sleep(0.05)
                assert len(replies) == 1
                assert str(replies[0].ok.key_expr) == ks.info("late-bot")
                info = decode_info_message(replies[0].ok.payload.to_bytes())
                assert (info.robot, info.kind, info.calibration) == ("late-bot", "rgbd", dataset.calibration)
                # a wildcard query finds every camera, the reply key names the robot
                wild = [r.ok for r in late.get(ks.info_wildcard(), timeout=2.0) if r.ok is not None]
                assert [ks.robot_of(s.key_expr) for s in wild] == ["late-bot"]
                # frames flow once the late session subscribes
                got = []
                sub = late.declare_subscriber(ks.frame("late-bot"), lambda s: got.append(s.payload.to_bytes()))
                assert cam.wait_for_subscriber(5.0)
                cam.send(dataset.frame(1), 1)
                end = time.monotonic() + 5.0
                while not got and time.monotonic() < end:
                    time.sleep(0.01)
                assert [decode_frame(p).seq for p in got] == [1]
                sub.undeclare()
            finally:
                late.close()
        # after close the queryable is gone
        assert cam._closed
        with pytest.raises(RuntimeError):
            cam.send(dataset.frame(0), 2)
    finally:
        cam_session.close()


def test_streamer_rejects_wrong_frames(collector):
    session = open_session(collector.client_settings)
    try:
        cal = open_dataset("synthetic:loop", max_frames=1).calibration
        with pytest.raises(ProtocolError):
            CameraStreamer(session, "bad robot", cal, collector.keyspace)
        with pytest.raises(ValueError):
            CameraStreamer(session, "r", cal, collector.keyspace, color="webp")
        with CameraStreamer(session, "r", cal, collector.keyspace) as cam:
            img = np.zeros((480, 640, 3), np.uint8)
            with pytest.raises(ProtocolError) as e:
                cam.send(Frame(0, 0.0, img), 0)  # an rgbd camera sending a frame without depth
            assert e.value.reason == "bad_frame"
        with CameraStreamer(session, "m", cal, collector.keyspace, kind="mono") as cam:
            assert cam.send(Frame(0, 0.0, img, depth=np.ones((480, 640), np.float32)), 0) > 0
    finally:
        session.close()


def _write_video(path, n=12, size=(96, 64), fps=10.0):
    w, h = size
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (w, h))
    assert writer.isOpened()
    yy, xx = np.mgrid[0:h, 0:w]
    for k in range(n):
        img = np.stack([(xx * 2 + 10 * k) % 256, (yy * 3) % 256, np.full_like(xx, 20 * k % 256)], -1).astype(np.uint8)
        writer.write(img)
    writer.release()
    return n


def test_capture_source_video_file(tmp_path):
    path = tmp_path / "clip.avi"
    n = _write_video(path)
    src = CaptureSource(str(path))
    assert len(src) == n and src.kind == "mono" and (src.width, src.height) == (96, 64)
    assert src.calibration == default_calibration(96, 64)
    assert src.calibration.camera.fx == pytest.approx(0.9 * 96) and src.calibration.camera.cx == pytest.approx(47.5)
    frames = list(src)
    assert len(frames) == n
    assert [f.index for f in frames] == list(range(n))
    np.testing.assert_allclose([f.stamp for f in frames], np.arange(n) / 10.0, atol=1e-6)
    assert all(f.image.shape == (64, 96, 3) and f.depth is None and f.right is None for f in frames)
    # random access seeks; a second iteration starts over
    np.testing.assert_array_equal(src.frame(5).image, frames[5].image)
    assert len(list(src)) == n
    src.release()
    assert len(CaptureSource(path, max_frames=4)) == 4 and len(list(CaptureSource(path, max_frames=4))) == 4
    for bad in (tmp_path / "missing.avi", tmp_path):
        with pytest.raises(DatasetError):
            CaptureSource(bad)
    junk = tmp_path / "junk.avi"
    junk.write_bytes(b"not a video" * 50)
    with pytest.raises(DatasetError):
        CaptureSource(junk)


def test_capture_source_streams_over_zenoh(tmp_path, collector):
    path = tmp_path / "clip.avi"
    n = _write_video(path)
    src = CaptureSource(path)
    reference = [f.image for f in CaptureSource(path)]
    stats = stream_dataset(src, "webcam", collector.client_settings, prefix=collector.keyspace.prefix,
                           progress=False, wait_for_subscriber=5.0, color="png")
    assert stats.frames == n
    received = collector.wait_frames(n)
    decoded = [decode_frame(p) for _, p in received]
    assert [w.seq for w in decoded] == list(range(n))
    assert all(w.kind == "mono" and w.frame.depth is None for w in decoded)
    for w, ref in zip(decoded, reference):
        np.testing.assert_array_equal(w.frame.image, ref)  # PNG is lossless
    info = decode_info_message(collector.infos[0][1])
    assert info.kind == "mono" and info.calibration == src.calibration


def _parse(argv):
    p = argparse.ArgumentParser(prog="mnemoslam")
    sub = p.add_subparsers(dest="command", required=True)
    add_stream_arguments(sub.add_parser("stream"))
    return p.parse_args(argv)


def test_stream_main(collector, capsys):
    args = _parse(["stream", "synthetic:loop", "--robot", "cli-bot", "--connect", endpoint(collector.port),
                   "--prefix", collector.keyspace.prefix, "--max-frames", "5", "--rate", "50", "--encoding", "raw",
                   "--depth-encoding", "raw", "-q"])
    assert args.func is stream_main
    t0 = time.perf_counter()
    assert args.func(args) == 0
    assert time.perf_counter() - t0 >= 4 / 50  # paced at 50 Hz
    assert "streamed 5 frames" in capsys.readouterr().out
    got = collector.wait_frames(5)
    assert [decode_frame(p).seq for _, p in got] == list(range(5))
    assert decode_frame(got[0][1]).color_encoding == "raw"
    # bad inputs are one-line errors of the kinds the CLI catches
    with pytest.raises(DatasetError):
        stream_main(_parse(["stream", "/nonexistent/dataset", "-q"]))
    with pytest.raises(DatasetError):
        stream_main(_parse(["stream", "--camera", "/nonexistent/video.avi", "-q"]))
    with pytest.raises(ValueError):
        stream_main(_parse(["stream", "synthetic:loop", "--robot", "bad robot", "-q"]))
    with pytest.raises(SystemExit):
        _parse(["stream", "synthetic:loop", "--camera", "0"])
    with pytest.raises(SystemExit):
        _parse(["stream"])
    capsys.readouterr()


def test_stream_depth_registration_is_for_7scenes_datasets_only(tmp_path):
    """`stream --depth-registration on|off` goes to the 7-Scenes player; with another dataset or
    a camera it is a one-line error before anything is sent."""
    from tests.test_datasets import make_sevenscenes, make_tum

    args = _parse(["stream", str(make_sevenscenes(tmp_path)), "--depth-registration", "on"])
    assert args.depth_registration == "on"
    with pytest.raises(DatasetError, match="applies to 7-Scenes only"):
        stream_main(_parse(["stream", str(make_tum(tmp_path)), "--depth-registration", "off", "-q"]))
    with pytest.raises(ValueError, match="--depth-registration"):
        stream_main(_parse(["stream", "--camera", "0", "--depth-registration", "on", "-q"]))


def test_stream_skips_unreadable_frames_like_run(tmp_path, collector, caplog):
    """A corrupt image costs its frame (logged, counted in StreamStats.skipped and the summary
    line), not the stream; skipped frames count towards max_frames."""
    from tests.test_datasets import make_tum

    ds = open_dataset(make_tum(tmp_path))
    (ds.path / "depth/1.038.png").write_bytes(b"\x89PNG garbage" + bytes(range(256)))  # frame 1
    with caplog.at_level(logging.ERROR, logger="mnemoslam.client.streamer"):
        stats = stream_dataset(ds, "bad1", collector.client_settings, prefix=collector.keyspace.prefix,
                               progress=False, wait_for_subscriber=5.0, color="png")
    assert (stats.frames, stats.skipped) == (3, 1)
    assert "1.038.png" in caplog.text and "frame 1 skipped" in caplog.text
    assert "1 unreadable frame(s) skipped" in stats.line()
    got = collector.wait_frames(3)
    assert [decode_frame(p).seq for _, p in got] == [0, 1, 2]  # seq counts frames sent
    assert [decode_frame(p).frame.stamp for _, p in got] == pytest.approx([1.0, 1.066, 1.1])
    short = stream_dataset(ds, "bad2", collector.client_settings, prefix=collector.keyspace.prefix,
                           progress=False, max_frames=2)
    assert (short.frames, short.skipped) == (1, 1)
    clean = stream_dataset(open_dataset("synthetic:loop", max_frames=2), "ok1", collector.client_settings,
                           prefix=collector.keyspace.prefix, progress=False)
    assert clean.skipped == 0 and "unreadable" not in clean.line()


def test_stream_max_frames_must_be_positive(capsys):
    for bad in ("0", "-3", "two"):
        with pytest.raises(SystemExit) as e:
            _parse(["stream", "synthetic:loop", "--max-frames", bad])
        assert e.value.code == 2
        assert "--max-frames" in capsys.readouterr().err
    assert _parse(["stream", "synthetic:loop", "--max-frames", "7"]).max_frames == 7
    assert _parse(["stream", "synthetic:loop"]).max_frames is None  # no option: every frame


def test_stream_main_no_progress_bar_when_stderr_is_not_a_terminal(collector, capsys):
    args = _parse(["stream", "synthetic:loop", "--robot", "pipe-bot", "--connect", endpoint(collector.port),
                   "--prefix", collector.keyspace.prefix, "--max-frames", "3"])  # no -q
    assert args.func(args) == 0
    out, err = capsys.readouterr()  # captured: not a terminal
    assert "streamed 3 frames" in out
    assert err.startswith("stream: ") and len(err.splitlines()) == 1  # the one header line, no bar
    from mnemoslam.client.cliargs import want_progress

    class Tty:
        def isatty(self):
            return True
    assert want_progress(False, Tty()) and not want_progress(True, Tty())
    with open(os.devnull, "w") as devnull:
        assert not want_progress(False, devnull)


def test_stream_without_subscriber_reports_it():
    port = free_port()
    lonely = open_session(ZenohSettings.service([endpoint(port)]))  # nobody subscribes
    try:
        stats = stream_dataset(open_dataset("synthetic:loop", max_frames=2), "alone",
                               ZenohSettings.client([endpoint(port)]),
                               prefix=f"none{uuid.uuid4().hex[:6]}", progress=False, wait_for_subscriber=0.2)
        assert stats.frames == 2 and not stats.subscriber
    finally:
        lonely.close()


def test_process_exits_with_sessions_left_open():
    """zenoh-python runs callbacks on a non-daemon thread: an unclosed session with a callback
    used to hang the interpreter at exit. open_session closes what is left open."""
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    port = free_port()
    code = f"""
import sys; sys.path.insert(0, {str(root)!r})
from mnemoslam.client.transport import ZenohSettings, open_session
from mnemoslam.client.streamer import CameraStreamer
from mnemoslam.client.kernel.frames import Calibration, PinholeCamera
a = open_session(ZenohSettings.service(["tcp/127.0.0.1:{port}"]))
a.declare_subscriber("x/**", lambda s: None)
b = open_session(ZenohSettings.client(["tcp/127.0.0.1:{port}"]))
CameraStreamer(b, "r", Calibration(PinholeCamera(1, 1, 0, 0, 4, 4)))
b.put("x/y", b"1")
print("done")
"""
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=20)
    assert r.returncode == 0 and "done" in r.stdout, r.stderr[-2000:]


def test_stream_synthetic_labels(collector, tmp_path, capsys):
    """--labels sends the synthetic camera's exact labels (lossless, raw or PNG) and the
    ADE20K-32 class table in the camera info; without it nothing of them travels."""
    from mnemoslam.client.kernel.protocol import DEFAULT_CLASSES

    dataset = open_dataset("synthetic:loop", max_frames=4)
    args = _parse(["stream", "synthetic:loop", "--robot", "lab-bot", "--connect", endpoint(collector.port),
                   "--prefix", collector.keyspace.prefix, "--max-frames", "4", "--labels", "--encoding", "jpeg",
                   "--depth-encoding", "png", "--rate", "100", "-q"])
    assert args.labels and args.func(args) == 0
    assert "png+labels" in capsys.readouterr().out
    got = collector.wait_frames(4)
    assert len(got) == 4
    for k, (_, payload) in enumerate(got):
        w = decode_frame(payload)
        assert (w.seq, w.version, w.label_encoding) == (k, 2, "png")
        ref = dataset.frame(k).extras["labels"]
        assert w.frame.extras["labels"].dtype == np.uint8
        np.testing.assert_array_equal(w.frame.extras["labels"], ref)
        assert "instances" not in w.frame.extras
    info = decode_info_message(collector.infos[-1][1])
    assert info.classes == DEFAULT_CLASSES and info.classes[15] == "door"
    # raw labels through stream_dataset; without labels: version 1 frames and no class table
    stats = stream_dataset(dataset, "raw-bot", collector.client_settings, prefix=collector.keyspace.prefix,
                           progress=False, max_frames=2, wait_for_subscriber=5.0, color="raw", depth="raw", rate=100.0,
                           labels=True)
    assert stats.encoding == "raw/raw+labels"
    plain = stream_dataset(dataset, "plain-bot", collector.client_settings, prefix=collector.keyspace.prefix,
                           progress=False, max_frames=2, wait_for_subscriber=5.0, color="raw", depth="raw", rate=100.0)
    assert plain.encoding == "raw/raw"
    got = collector.wait_frames(8)
    by_robot: dict[str, list] = {}
    for key, payload in got:
        by_robot.setdefault(collector.keyspace.robot_of(key), []).append(decode_frame(payload))
    assert [w.label_encoding for w in by_robot["raw-bot"]] == ["raw", "raw"]
    np.testing.assert_array_equal(by_robot["raw-bot"][1].frame.extras["labels"], dataset.frame(1).extras["labels"])
    assert all(w.version == 1 and w.frame.extras == {} for w in by_robot["plain-bot"])
    infos = {collector.keyspace.robot_of(k): decode_info_message(p) for k, p in collector.infos}
    assert infos["raw-bot"].classes == DEFAULT_CLASSES and infos["plain-bot"].classes is None
    # sources without labels: a clear error before any frame is sent
    from tests.test_datasets import make_tum

    with pytest.raises(ValueError, match="carry no labels"):
        stream_dataset(open_dataset(make_tum(tmp_path)), "tum-bot", collector.client_settings,
                       prefix=collector.keyspace.prefix, progress=False, labels=True)
    with pytest.raises(ValueError, match="--labels"):
        stream_main(_parse(["stream", "--camera", "0", "--labels", "-q"]))
    assert not [k for k, _ in collector.frames if collector.keyspace.robot_of(k) == "tum-bot"]
    with pytest.raises(ValueError):
        CameraStreamer(collector.session, "x", dataset.calibration, collector.keyspace, labels="jpeg")
