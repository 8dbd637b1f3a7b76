"""ROS 2 robots over Zenoh (service/ros.py, client/ros_cdr.py): CDR sensor_msgs/Image,
CompressedImage (compressedDepth) and CameraInfo published on zenoh-bridge-ros2dds-style keys
are mapped exactly as the same frames sent natively; poses go out as CDR PoseStamped.

The end-to-end test runs the real service (its own process), a real Zenoh session on loopback
publishing the ROS messages, and a native camera client streaming the same frames."""
import dataclasses
import time

import cv2
import numpy as np
import pytest
import zenoh

from mnemoslam.client import ros_cdr
from mnemoslam.client.datasets import open_dataset
from mnemoslam.client.kernel import protocol
from mnemoslam.client.kernel.protocol import ProtocolError
from mnemoslam.client.streamer import stream_dataset
from mnemoslam.client.transport import ZenohSettings, open_session
from mnemoslam.service.config import ConfigError, load_config
from mnemoslam.service.demo import ServiceProcess, keyframe_trajectory
from mnemoslam.service.ros import compressed_key, parse_robots

from conftest import service_config

FRAMES = 40
RAW = {"robot": "rosraw", "color": "rosraw/camera/color/image_raw",
       "depth": "rosraw/camera/aligned_depth_to_color/image_raw", "info": "rosraw/camera/color/camera_info",
       "pose": "rosraw/mnemoslam/pose"}
# a bridge with a namespace prefix; image_transport's compressed topics
CMP = {"robot": "roscmp", "color": "ns1/roscmp/camera/color/image_raw/compressed",
       "depth": "ns1/roscmp/camera/aligned_depth_to_color/image_raw/compressedDepth",
       "info": "ns1/roscmp/camera/color/camera_info"}


# -- the codec ---------------------------------------------------------------------------
def _images(h=6, w=8, seed=0):
    rng = np.random.default_rng(seed)
    img = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    depth = rng.uniform(0.3, 5.0, (h, w)).astype(np.float32)
    depth[0, 0], depth[1, 1] = 0.0, np.nan
    return img, depth


def test_cdr_images_decode_to_the_native_arrays():
    img, depth = _images()
    ns = 1_700_000_000_123_456_789
    # what a native frame carries
    want_depth = protocol.dequantize_depth(protocol.quantize_depth(depth, 1000.0), 1000.0)
    for enc in ("bgr8", "rgb8"):
        msg = ros_cdr.deserialize(ros_cdr.encode_image(img, enc, ns), ros_cdr.IMAGE)
        assert ros_cdr.stamp_ns(msg) == ns
        assert np.array_equal(ros_cdr.decode_color(msg, (8, 6)), img)
    grey = np.ascontiguousarray(img[..., 1])
    assert np.array_equal(
        ros_cdr.decode_color(ros_cdr.deserialize(ros_cdr.encode_image(grey, "mono8", ns), ros_cdr.IMAGE)), grey)
    d = ros_cdr.decode_depth(ros_cdr.deserialize(ros_cdr.encode_image(depth, "16UC1", ns), ros_cdr.IMAGE), (8, 6))
    assert d.dtype == np.float32 and np.array_equal(d, want_depth)
    d32 = ros_cdr.decode_depth(ros_cdr.deserialize(ros_cdr.encode_image(depth, "32FC1", ns), ros_cdr.IMAGE))
    assert d32[1, 1] == 0.0 and np.array_equal(d32[2:], depth[2:])  # NaN -> 0 (no measurement)
    msg = ros_cdr.deserialize(ros_cdr.encode_compressed(img, ns, "png"), ros_cdr.COMPRESSED)
    assert np.array_equal(ros_cdr.decode_color(msg, (8, 6)), img)
    msg = ros_cdr.deserialize(ros_cdr.encode_compressed_depth(depth, ns), ros_cdr.COMPRESSED)
    assert np.array_equal(ros_cdr.decode_depth(msg, (8, 6)), want_depth)

    # rows padded (step > width × 2) and big-endian 16UC1
    q = protocol.quantize_depth(depth, 1000.0)
    rows = np.zeros((6, 20), np.uint8)
    rows[:, :16] = q.astype(">u2").view(np.uint8).reshape(6, 16)
    T = ros_cdr.typestore().types
    msg = T[ros_cdr.IMAGE](header=ros_cdr._header(ns, "c"), height=6, width=8, encoding="16UC1", is_bigendian=1,
                           step=20, data=rows.reshape(-1))
    assert np.array_equal(
        ros_cdr.decode_depth(ros_cdr.deserialize(ros_cdr.serialize(msg, ros_cdr.IMAGE), ros_cdr.IMAGE)), want_depth)


def test_compressed_depth_32fc1_inverse_depth():
    """image_transport's 32FC1 compressedDepth: PNG-16 of quantized inverse depth, depth = A / (q - B)."""
    depth = np.array([[0.5, 1.0, 2.0], [4.0, 0.0, 8.0]], np.float32)
    a, b = 80.0, 2.0  # (q = A / depth + B: whole numbers here)
    q = np.zeros(depth.shape, np.uint16)
    q[depth > 0] = np.rint(a / depth[depth > 0] + b).astype(np.uint16)
    data = ros_cdr._COMPRESSED_DEPTH_HEADER.pack(0, a, b) + cv2.imencode(".png", q)[1].tobytes()
    T = ros_cdr.typestore().types
    msg = T[ros_cdr.COMPRESSED](header=ros_cdr._header(1, "c"), format="32FC1; compressedDepth png",
                                data=np.frombuffer(data, np.uint8))
    out = ros_cdr.decode_depth(ros_cdr.deserialize(ros_cdr.serialize(msg, ros_cdr.COMPRESSED), ros_cdr.COMPRESSED))
    np.testing.assert_allclose(out, depth, rtol=1e-6)
    msg = dataclasses.replace(msg, format="16UC1; compressedDepth rvl")
    with pytest.raises(ProtocolError, match="RVL") as e:
        ros_cdr.decode_depth(msg)
    assert e.value.reason == "bad_encoding"


@pytest.mark.parametrize("make,reason", [
    (lambda: ros_cdr.deserialize(b"garbage payload", ros_cdr.IMAGE), "bad_cdr"),
    (lambda: ros_cdr.deserialize(b"\x00\x01\x00\x00" + b"\xff" * 40, ros_cdr.IMAGE), "bad_cdr"),
    (lambda: ros_cdr.deserialize(b"\x00\x01\x00\x00" + bytes(100), ros_cdr.IMAGE, max_bytes=50), "too_large"),
    (lambda: ros_cdr.decode_color(ros_cdr.deserialize(ros_cdr.encode_image(_images()[0], "bgr8", 1), ros_cdr.IMAGE),
                                  (640, 480)), "size_mismatch"),
    (lambda: ros_cdr.decode_color(ros_cdr.deserialize(ros_cdr.encode_image(_images()[1], "32FC1", 1), ros_cdr.IMAGE)),
     "bad_encoding"),
    (lambda: ros_cdr.decode_depth(ros_cdr.deserialize(ros_cdr.encode_image(_images()[0], "bgr8", 1), ros_cdr.IMAGE)),
     "bad_encoding"),
    (lambda: ros_cdr.decode_color(dataclasses.replace(ros_cdr.deserialize(
        ros_cdr.encode_compressed(_images()[0], 1), ros_cdr.COMPRESSED), data=np.arange(200, dtype=np.uint8))),
     "decode_failed"),
])
def test_malformed_ros_messages_raise_protocol_errors(make, reason):
    with pytest.raises(ProtocolError) as e:
        make()
    assert e.value.reason == reason


def test_camera_info_and_pose_stamped():
    from mnemoslam.client.kernel.frames import Calibration, PinholeCamera

    cal = Calibration(PinholeCamera(525.0, 526.0, 319.5, 239.25, 640, 480), None, 1000.0)
    msg = ros_cdr.deserialize(ros_cdr.encode_camera_info(cal, 7), ros_cdr.CAMERA_INFO)
    assert ros_cdr.calibration(msg) == cal == ros_cdr.calibration(msg, "p")
    with pytest.raises(ProtocolError) as e:
        ros_cdr.calibration(dataclasses.replace(msg, k=np.zeros(9)))
    assert e.value.reason == "bad_info"
    rng = np.random.default_rng(3)
    for v in [rng.normal(size=3) for _ in range(50)] + [np.array([np.pi, 0, 0]), np.array([0, 0, np.pi]), np.zeros(3)]:
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = cv2.Rodrigues(v)[0], rng.normal(size=3)
        p = ros_cdr.decode_pose_stamped(ros_cdr.encode_pose_stamped(T, 12_000_000_345, "map"))
        assert p.ns == 12_000_000_345 and p.frame_id == "map"
        np.testing.assert_allclose(p.pose, T, atol=1e-12)


def test_ros_config_is_checked():
    assert load_config().ros.enabled is False and load_config().ros.robots == []
    robots = parse_robots(load_config(None, {"ros": {"robots": [RAW, CMP]}}).ros)
    assert [r.robot for r in robots] == ["rosraw", "roscmp"] and robots[1].pose is None and robots[0].intrinsics == "k"
    for entry, match in [({"robot": "r1", "color": "a", "depth": "b"}, "info"),
                         ({"robot": "r1", "color": "a", "info": "b"}, "depth"),
                         ({**RAW, "colour": "a"}, "unknown key 'colour'"),
                         ({**RAW, "robot": "r 1"}, "robot id"), ({**RAW, "depth": "/r1/depth"}, "Zenoh key"),
                         ({**RAW, "pose": "r1/*/pose"}, "wildcards"), ({**RAW, "intrinsics": "q"}, "k or p"),
                         ("r1", "mapping")]:
        with pytest.raises(ConfigError, match=match):
            parse_robots(load_config(None, {"ros": {"robots": [entry]}}).ros)
    with pytest.raises(ConfigError, match="twice"):
        parse_robots(load_config(None, {"ros": {"robots": [RAW, RAW]}}).ros)
    assert compressed_key(CMP["color"], CMP["color"]) and compressed_key(CMP["depth"], CMP["depth"])
    assert not compressed_key(RAW["color"], RAW["color"])
    # rmw_zenoh keys name the type: <domain>/<topic>/<type>/<hash>
    assert compressed_key("0/r1/image/compressed/*/*",
                          "0/r1/image/compressed/sensor_msgs::msg::dds_::CompressedImage_/RIHS01_x")
    assert not compressed_key("0/r1/image/*/*", "0/r1/image/sensor_msgs::msg::dds_::Image_/RIHS01_x")


class _Sample:
    def __init__(self, key, payload):
        self.key_expr, self._payload = key, payload

    @property
    def payload(self):
        return self

    def to_bytes(self):
        return self._payload


class _Service:
    """What RosIngest calls of the service, recorded (the pairing alone, no Zenoh)."""

    def __init__(self, config):
        self.config, self.sessions, self.limits = config, {}, protocol.Limits()
        self.rejected, self.frames = [], []

    def count_reject(self, reason, key, err):
        self.rejected.append(reason)

    def ingest(self, robot, key, pair, decode=None, ask_info=True):
        self.frames.append((pair.seq, pair.ns, ros_cdr.stamp_ns(pair.color), ros_cdr.stamp_ns(pair.depth)))


def _pairing(config):
    """A RosIngest for robot RAW on a recording service stub, and send(kind, t_ms): one raw
    colour ("c") or depth ("d") image stamped t milliseconds through its callback."""
    from mnemoslam.service.ros import RosIngest

    svc = _Service(config)
    ros = RosIngest(svc, config.ros)
    st = ros.robots["rosraw"]
    img, depth = _images()

    def send(kind, t):
        key = RAW["color" if kind == "c" else "depth"]
        ns = t * 1_000_000
        payload = ros_cdr.encode_image(img, "bgr8", ns) if kind == "c" else ros_cdr.encode_image(depth, "16UC1", ns)
        ros._on_image(st, _Sample(key, payload), kind == "d")

    return svc, ros, st, send


def test_a_stream_whose_callbacks_lag_still_pairs_within_the_sync_window():
    """Bursts: one key's callbacks can run many images behind the other's. With the defaults
    (sync_window 0.5 s, sync_queue 16) twelve colour images wait for depth images that come
    after all of them and every pair is made; images still unpaired when their own stream is
    0.5 s past them are dropped and counted."""
    config = load_config(None, {"ros": {"enabled": True, "robots": [RAW]}})
    assert config.ros.sync_window == 0.5 and config.ros.sync_queue == 16
    svc, _, _, send = _pairing(config)
    ms = 1_000_000

    stamps = [33 * k for k in range(12)]  # 0.36 s of colour, the depth stream 12 images behind
    for t in stamps:
        send("c", t)
    for t in stamps:
        send("d", t + 1)
    assert [f[1] // ms for f in svc.frames] == stamps and svc.rejected == []
    send("c", 400), send("c", 433)  # their depth never comes ...
    send("c", 920)  # ... and the colour stream is 0.5 s past the first of them
    assert svc.rejected == ["unpaired"]
    send("c", 1000)
    assert svc.rejected == ["unpaired"] * 2  # 433 too; 920 and 1000 still wait


def test_colour_and_depth_pair_by_nearest_stamp_within_the_tolerance():
    config = load_config(None, {"ros": {"enabled": True, "robots": [RAW], "sync_tolerance": 0.015, "sync_queue": 2}})
    svc, ros, st, send = _pairing(config)
    ms = 1_000_000

    send("c", 100)
    send("d", 120)  # 20 ms: not a pair, both wait
    send("d", 101)  # the nearest colour: a pair
    assert svc.frames == [(0, 100 * ms, 100 * ms, 101 * ms)] and svc.rejected == []
    send("c", 133)  # 13 ms from the waiting depth: a pair (its stamp is the colour's)
    assert svc.frames[-1] == (1, 133 * ms, 133 * ms, 120 * ms)
    send("c", 200), send("c", 233), send("c", 266)  # no depth: the oldest is pushed out of the buffer (2)
    assert svc.rejected == ["unpaired"]
    send("d", 267)  # pairs with 266; 233 is older than the pair: its depth is gone
    assert svc.frames[-1] == (2, 266 * ms, 266 * ms, 267 * ms) and svc.rejected == ["unpaired"] * 2
    ros._on_image(st, _Sample(RAW["color"], b"\x00\x01\x00\x00junk"), False)
    assert svc.rejected[-1] == "bad_cdr" and len(svc.frames) == 3 and not st.colors and not st.depths


def test_imu_key_gives_frames_their_accelerometer_reading():
    """A robot with an `imu` key: its Imu messages (here in a body-axes frame, rotated into
    the camera's; then with imu_axes configured) give each decoded frame the reading at its
    stamp (interpolated) as extras["accel"]; none farther than 50 ms, none without a reading
    (covariance[0] = -1), a bad message is counted, not raised."""
    from types import SimpleNamespace

    from mnemoslam.client.imu import BODY_TO_OPTICAL, IMU, parse_axes
    from mnemoslam.service.ros import RosPair

    ts = ros_cdr.typestore()
    T = ts.types

    def imu_msg(ns, v, frame="imu_link", cov0=0.0):
        v3 = T["geometry_msgs/msg/Vector3"]
        stamp = T["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
        return ros_cdr.serialize(T["sensor_msgs/msg/Imu"](
            header=T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame),
            orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=np.zeros(9), angular_velocity=v3(x=0.0, y=0.0, z=0.0),
            angular_velocity_covariance=np.zeros(9), linear_acceleration=v3(x=v[0], y=v[1], z=v[2]),
            linear_acceleration_covariance=np.r_[cov0, np.zeros(8)]), IMU)

    img, depth = _images()
    session = SimpleNamespace(robot="rosraw", limits=SimpleNamespace(size=None, max_width=64, max_height=64))
    ms = 1_000_000
    for axes, R in ((None, BODY_TO_OPTICAL), ("x:-z:y", parse_axes("x:-z:y"))):
        entry = {**RAW, "imu": "rosraw/imu"} | ({"imu_axes": axes} if axes else {})
        config = load_config(None, {"ros": {"enabled": True, "robots": [entry]}})
        svc = _Service(config)
        from mnemoslam.service.ros import RosIngest

        ros = RosIngest(svc, config.ros)
        st = ros.robots["rosraw"]
        for t in (1000, 1010, 1020):
            ros._on_imu(st, _Sample("rosraw/imu", imu_msg(t * ms, [0.1 * t, 9.8, -0.5])))
        ros._on_imu(st, _Sample("rosraw/imu", imu_msg(1030 * ms, [99.0, 0.0, 0.0], cov0=-1.0)))  # no reading: skipped
        ros._on_imu(st, _Sample("rosraw/imu", b"\x00\x01\x00\x00junk"))
        assert svc.rejected == ["bad_cdr"]

        def frame(t, ros=ros):
            pair = RosPair(0, t * ms, ros_cdr.deserialize(ros_cdr.encode_image(img, "bgr8", t * ms), ros_cdr.IMAGE),
                           ros_cdr.deserialize(ros_cdr.encode_image(depth, "16UC1", t * ms), ros_cdr.IMAGE), 0)
            return ros.decode(pair, session)[1]

        np.testing.assert_allclose(frame(1015).extras["accel"], R @ [101.5, 9.8, -0.5], atol=1e-9)
        np.testing.assert_allclose(frame(1040).extras["accel"], R @ [102.0, 9.8, -0.5], atol=1e-9)  # 20 ms past
        assert "accel" not in frame(1080).extras  # 60 ms past the last reading
    with pytest.raises(ConfigError, match="imu_axes"):
        parse_robots(load_config(None, {"ros": {"robots": [{**RAW, "imu": "a", "imu_axes": "up"}]}}).ros)
    robots = parse_robots(load_config(None, {"ros": {"robots": [RAW]}}).ros)
    assert robots[0].imu is None


# -- the service ---------------------------------------------------------------------------
class _Frames(list):
    """Frames with a calibration: what stream_dataset needs of a dataset."""

    def __init__(self, frames, calibration):
        super().__init__(frames)
        self.calibration, self.name = calibration, "synthetic:loop"


def _wait(what, cond, timeout=60.0):
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            raise TimeoutError(what)
        time.sleep(0.05)


def test_ros_robots_map_exactly_as_the_native_robot(tmp_path):
    ds = open_dataset("synthetic:loop", max_frames=FRAMES)
    # stamps whole nanoseconds (a ROS stamp is sec + nanosec), the same for every robot
    stamps_ns = [1_700_000_000 * 10**9 + int(round(float(t) * 1e9)) for t in ds.stamps[:FRAMES]]
    # every depth image taken 1 ms after its colour image: its stamp travels in the depth message's
    # header (ROS) and in the frame message's sensor fields (native), and each robot's tracker
    # moves the depth by the motion over that millisecond, the same way
    depth_ns = [ns + 1_000_000 for ns in stamps_ns]
    frames = [dataclasses.replace(ds.frame(i), stamp=ns / 1e9, extras={"depth_stamp": depth_ns[i] / 1e9})
              for i, ns in enumerate(stamps_ns)]
    # loop closure and rehearsal off: they would link the three robots' identical keyframes in the one map.
    # Each frame's images go out once the last frame's pairs were received, as a camera's would at its
    # rate: callbacks of two keys are not ordered, and a depth image arriving after the next frame's pair
    # is dropped with its colour image (the pairing's rule, tested above; CI once lost a frame so when
    # the frames were sent unpaced)
    svc = ServiceProcess(tmp_path / "map.db", service_config({
        "ros": {"enabled": True, "robots": [RAW, CMP]}, "loop": {"enabled": False},
        "memory": {"rehearsal": False},
        "service": {"queue_size": 1000, "queue_mb": 1024.0, "idle_timeout": 3600.0}})).start()
    z = None
    try:
        settings = ZenohSettings(connect=[svc.endpoint])
        z = open_session(settings)
        got = {"ros": [], "native": [], "rosraw_json": []}
        subs = [z.declare_subscriber(RAW["pose"], lambda s: got["ros"].append(s.payload.to_bytes())),
                z.declare_subscriber("mnemoslam/native/pose", lambda s: got["native"].append(s.payload.to_bytes())),
                z.declare_subscriber("mnemoslam/rosraw/pose",
                                     lambda s: got["rosraw_json"].append(s.payload.to_bytes()))]
        pubs = {k: z.declare_publisher(k, congestion_control=zenoh.CongestionControl.BLOCK)
                for r in (RAW, CMP) for k in (r["color"], r["depth"], r["info"])}
        _wait("the service's ROS subscribers", lambda: all(p.matching_status.matching for p in pubs.values()))
        info = {ns: ros_cdr.encode_camera_info(ds.calibration, ns) for ns in stamps_ns}

        def put(key, payload):
            pubs[key].put(payload)

        def raw(i):  # rgb8 + 16UC1 millimetres; depth (stamped 1 ms after the colour) sent first every other frame
            ns = stamps_ns[i]
            c = (RAW["color"], ros_cdr.encode_image(frames[i].image, "rgb8", ns))
            d = (RAW["depth"], ros_cdr.encode_image(frames[i].depth, "16UC1", depth_ns[i]))
            put(RAW["info"], info[ns])
            for key, payload in ((d, c) if i % 2 else (c, d)):
                put(key, payload)

        def compressed(i):  # PNG colour, compressedDepth PNG
            ns = stamps_ns[i]
            if i >= 2:  # (frames 0 and 1 beat the robot's first camera info: held, then mapped)
                put(CMP["info"], info[ns])
            put(CMP["color"], ros_cdr.encode_compressed(frames[i].image, ns, "png"))
            put(CMP["depth"], ros_cdr.encode_compressed_depth(frames[i].depth, depth_ns[i]))

        def received(robot, n):
            return any(r["robot"] == robot and r["frames_received"] >= n for r in svc.api.robots())

        for i in range(FRAMES):
            raw(i)
            compressed(i)
            if i == 1:  # its info, and its slot before the next frame (callbacks of two keys are not ordered)
                put(CMP["info"], info[stamps_ns[1]])
                _wait("roscmp admitted", lambda: received("roscmp", 0))
            _wait(f"frame {i} paired", lambda i=i: received("rosraw", i + 1) and (i < 1 or received("roscmp", i + 1)))
        stats = stream_dataset(_Frames(frames, ds.calibration), "native", settings, rate=None, color="png",
                               depth="png", progress=False, wait_for_subscriber=10.0)
        assert stats.frames == FRAMES

        robots = {r: svc.wait_processed(r, FRAMES, timeout=120) for r in ("native", "rosraw", "roscmp")}
        for r, status in robots.items():
            assert status["frames_processed"] == FRAMES and status["frames_dropped"] == 0, (
                r, status["frames_processed"], status["frames_dropped"], status.get("frames_rejected"))
            assert status["frames_rejected"] == {}, (r, status)
        native = keyframe_trajectory(svc.api, svc.session_of("native"))
        assert len(native) >= 3
        for r in ("rosraw", "roscmp"):
            traj = keyframe_trajectory(svc.api, svc.session_of(r))
            assert np.array_equal(traj.stamps, native.stamps), r
            np.testing.assert_allclose(traj.poses, native.poses, rtol=0, atol=1e-9, err_msg=r)
        assert [s["robot"] for s in svc.api.sessions()].count("rosraw") == 1

        # PoseStamped on the configured key: every tracked frame, its image's exact stamp,
        # the pose the native robot got for the same frame
        tracked = robots["rosraw"]["tracked"]
        assert tracked == robots["native"]["tracked"] >= FRAMES - 2
        _wait("the PoseStamped poses", lambda: len(got["ros"]) >= tracked and len(got["native"]) >= FRAMES)
        native_poses = {m.stamp: m.pose for m in map(protocol.decode_pose, got["native"])}
        ros_poses = [ros_cdr.decode_pose_stamped(p) for p in got["ros"]]
        assert len(ros_poses) == tracked and {p.frame_id for p in ros_poses} == {"map"}
        assert {p.ns for p in ros_poses} <= set(stamps_ns)
        for p in ros_poses:
            np.testing.assert_allclose(p.pose, native_poses[p.ns / 1e9], rtol=0, atol=1e-9)
        assert len(got["rosraw_json"]) >= FRAMES  # the native JSON pose too, as for every robot

        # garbage on an image key and a frame of the wrong size: counted, ignored
        put(RAW["color"], b"garbage, not CDR")
        late = stamps_ns[-1] + 10**9
        put(RAW["color"], ros_cdr.encode_image(frames[0].image[:240, :320], "bgr8", late))
        put(RAW["depth"], ros_cdr.encode_image(frames[0].depth[:240, :320], "16UC1", late))
        _wait("the rejects", lambda: sum(svc.api.robot("rosraw")["frames_rejected"].values()) >= 2)
        r = svc.api.robot("rosraw")
        assert r["frames_rejected"] == {"bad_cdr": 1, "size_mismatch": 1} and r["frames_processed"] == FRAMES
        rejected = svc.api.stats()["service"]["rejected"]
        assert rejected.get("bad_cdr") == 1 and rejected.get("size_mismatch") == 1
        for s in subs:
            s.undeclare()
    finally:
        if z is not None:
            z.close()
        assert svc.stop() == 0
    assert "Traceback" not in svc.log_path.read_text()
