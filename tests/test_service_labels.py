"""Labels over the wire into the service: frames streamed with `--labels` reach the pipeline
with the camera's exact class ids (`extras["labels"]`) and its class table
(`extras["label_names"]`); malformed label images are counted drops; the queue counts them.
A real service (`SlamService`, in this process so the test can see what its pipelines get)
on a real Zenoh session on loopback."""
import threading
import time

import numpy as np
import pytest
import zenoh

from mnemoslam.client.datasets import open_dataset
from mnemoslam.client.kernel import protocol
from mnemoslam.client.kernel.frames import Frame
from mnemoslam.client.streamer import CameraStreamer, stream_dataset
from mnemoslam.client.transport import ZenohSettings, open_session
from mnemoslam.service.config import load_config
from mnemoslam.service.server import SlamService
from mnemoslam.service.session import RobotSession
from tests.test_streamer import endpoint, free_port

FRAMES = 6


class RecordingService(SlamService):
    """The service as it is; it also keeps what each processed frame carried (the frame object
    its robot's pipeline was given)."""

    def __init__(self, config):
        super().__init__(config)
        self.seen: dict[str, list[Frame]] = {}

    def _on_result(self, session, frame, result):
        self.seen.setdefault(session.robot, []).append(frame)
        super()._on_result(session, frame, result)


def _until(cond, timeout=60.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end and not cond():
        time.sleep(0.05)
    return cond()


@pytest.fixture
def service(tmp_path):
    port = free_port()
    config = load_config(overrides={"zenoh": {"listen": [endpoint(port)]},
                                    "storage": {"path": str(tmp_path / "map.db")},
                                    "loop": {"process": False}, "service": {"queue_size": 1000}})
    svc = RecordingService(config).start()
    svc.endpoint = endpoint(port)
    yield svc
    svc.stop()


def test_streamed_labels_reach_the_pipeline(service):
    settings = ZenohSettings(connect=[service.endpoint])
    ds = open_dataset("synthetic:loop", max_frames=FRAMES)
    stats = stream_dataset(ds, "lab", settings, rate=None, color="jpeg", depth="png", progress=False,
                           wait_for_subscriber=10.0, labels=True)
    plain = stream_dataset(ds, "plain", settings, rate=None, color="raw", depth="raw", progress=False,
                           wait_for_subscriber=10.0)
    assert stats.frames == plain.frames == FRAMES
    assert _until(lambda: all(len(service.seen.get(r, [])) == FRAMES for r in ("lab", "plain")))
    for k, frame in enumerate(service.seen["lab"]):
        assert frame.index == k
        labels = frame.extras["labels"]
        assert labels.dtype == np.uint8 and labels.shape == frame.image.shape[:2]
        np.testing.assert_array_equal(labels, ds.frame(k).extras["labels"])  # identical, pixel for pixel
        assert frame.extras["label_names"] == protocol.DEFAULT_CLASSES  # the camera info's table
    assert all(f.extras == {} for f in service.seen["plain"])  # no labels sent: none made up
    robots = {r["robot"]: r for r in service.robots()}
    assert robots["lab"]["frames_labelled"] == FRAMES and robots["plain"]["frames_labelled"] == 0
    assert robots["lab"]["frames_processed"] == FRAMES and robots["lab"]["frames_rejected"] == {}
    assert service.sessions["lab"].classes == protocol.DEFAULT_CLASSES and service.sessions["plain"].classes is None


def test_bad_label_images_are_counted_drops(service):
    """Corrupt or out-of-table label images are refused with their reason, counted, and the
    robot's good frames still go through."""
    ds = open_dataset("synthetic:loop", max_frames=4)
    z = open_session(ZenohSettings(connect=[service.endpoint]))
    try:
        # a camera whose class table has 2 classes, sending the scene's ids (up to 25)
        with CameraStreamer(z, "small", ds.calibration, labels="png", classes=("floor", "wall")) as cam:
            assert cam.wait_for_subscriber(10.0)
            assert _until(lambda: "small" in service.sessions, 10.0)
            cam.send(ds.frame(0), 0)
            good = ds.frame(1)
            good.extras["labels"] = (good.extras["labels"] > 0).astype(np.uint8)  # ids 0, 1: fine
            cam.send(good, 1)
            # hand-made messages on the robot's key: garbage label PNG, wrong size, wrong dtype
            pub = z.declare_publisher(protocol.KeySpace().frame("small"),
                                      congestion_control=zenoh.CongestionControl.BLOCK)
            f = ds.frame(2)
            f.extras["labels"] = np.zeros((240, 320), np.uint8)  # half size: the encoder refuses it ...
            with pytest.raises(protocol.ProtocolError):
                cam.encode(f, 2)
            f.extras["labels"] = np.zeros(f.image.shape[:2], np.uint8)
            msg = bytearray(cam.encode(f, 2))
            lenc_at = protocol.FIXED_HEADER_BYTES + len("small") + 8
            llen = int.from_bytes(msg[lenc_at + 2:lenc_at + 6], "little")
            garbage = msg[:len(msg) - llen] + bytes(llen)  # ... so corrupt a valid one by hand
            pub.put(bytes(garbage))
            wrong_dtype = bytearray(msg)
            wrong_dtype[lenc_at + 1] = 2  # says uint16, the PNG is 8-bit
            pub.put(bytes(wrong_dtype))
            pub.undeclare()
            f3 = ds.frame(3)
            f3.extras["labels"] = np.ones(f3.image.shape[:2], np.uint8)
            cam.send(f3, 3)
            assert _until(lambda: len(service.seen.get("small", [])) == 2
                          and sum(service.sessions["small"].stats.rejected.values()) == 3, 30.0)
    finally:
        z.close()
    rejected = service.sessions["small"].stats.rejected
    assert rejected == {"bad_labels": 1, "decode_failed": 2}, rejected
    assert service.rejected["bad_labels"] == 1 and service.rejected["decode_failed"] == 2
    assert [f.index for f in service.seen["small"]] == [1, 3]
    assert service.seen["small"][0].extras["label_names"] == ("floor", "wall")
    np.testing.assert_array_equal(service.seen["small"][1].extras["labels"], 1)


class _Blocked:
    """A pipeline that holds its first frame until released (the queue fills behind it)."""

    session_id = 1
    map_progress = (0, 0)

    def __init__(self):
        self.release = threading.Event()
        self.started = threading.Event()

    def process(self, frame):
        self.started.set()
        self.release.wait(10)
        raise RuntimeError("not a real pipeline")

    def close(self, reason):
        pass


def test_queue_memory_counts_label_images():
    cal = open_dataset("synthetic:loop", max_frames=1).calibration
    pipe = _Blocked()
    session = RobotSession("q", load_config(), cal, protocol.Limits(), lambda c: pipe, lambda *a: None)
    try:
        img = np.zeros((480, 640, 3), np.uint8)
        depth = np.zeros((480, 640), np.float32)
        session.submit(0, Frame(0, 0.0, img, depth))
        assert pipe.started.wait(10)
        plain = Frame(1, 1.0, img, depth)
        session.submit(1, plain)
        assert session._queued_bytes == img.nbytes + depth.nbytes == RobotSession.frame_bytes(plain)
        labelled = Frame(2, 2.0, img, depth, extras={"labels": np.zeros((480, 640), np.uint16),
                                                     "label_names": protocol.DEFAULT_CLASSES})
        session.submit(2, labelled)
        assert session._queued_bytes == 2 * (img.nbytes + depth.nbytes) + 480 * 640 * 2
        assert session.stats.labelled == 1 and session.snapshot()["frames_labelled"] == 1
    finally:
        pipe.release.set()
        session.stop()
