"""The wire protocol: frame message round trips, limits enforced before decoding, fuzzing
(only ProtocolError, with stable reason codes), JSON messages and the key space."""
from __future__ import annotations

import json
import struct
import time
import tracemalloc

import cv2
import numpy as np
import pytest

from mnemoslam.client.kernel.frames import Calibration, Frame, PinholeCamera
from mnemoslam.client.kernel.protocol import (
    EVENT_KINDS,
    FIXED_HEADER_BYTES,
    PROTOCOL_VERSION,
    KeySpace,
    Limits,
    ProtocolError,
    decode_event,
    decode_frame,
    decode_info,
    decode_info_message,
    decode_pose,
    encode_event,
    encode_frame,
    encode_info,
    encode_pose,
    quantize_depth,
)

# the layout as documented in client/kernel/protocol.py, written out independently here
FIXED = struct.Struct("<4sHHHQdBBBHHBfB")
LENGTHS = struct.Struct("<II")


def _scene(h=48, w=64, seed=0):
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w]
    img = np.stack([(xx * 4) % 256, (yy * 5) % 256, ((xx + yy) * 3) % 256], -1).astype(np.uint8)
    img = cv2.GaussianBlur(img, (5, 5), 0)
    depth = (0.5 + 3.0 * rng.random((h, w))).astype(np.float32)
    depth[rng.random((h, w)) < 0.1] = 0.0
    depth[0, 0], depth[0, 1], depth[0, 2], depth[0, 3] = np.nan, -1.0, np.inf, 80.0  # invalid, invalid, inf, clipped
    return img, depth


def _rgbd(h=48, w=64, seed=0, stamp=1.25):
    img, depth = _scene(h, w, seed)
    return Frame(index=3, stamp=stamp, image=img, depth=depth)


def _expected_depth(depth, scale=1000.0):
    return quantize_depth(depth, scale).astype(np.float32) / np.float32(scale)


# ------------------------------------------------------------------------------------------
# round trips

@pytest.mark.parametrize("color", ["raw", "png", "jpeg"])
@pytest.mark.parametrize("depth", ["raw", "png"])
def test_rgbd_round_trip(color, depth):
    f = _rgbd()
    msg = encode_frame(f, "robot_1", 12345678901234, color=color, depth=depth)
    w = decode_frame(msg)
    assert (w.robot, w.seq, w.kind, w.color_encoding, w.depth_encoding, w.size) == (
        "robot_1", 12345678901234, "rgbd", color, depth, len(msg))
    assert w.frame.stamp == 1.25 and w.frame.index == 12345678901234
    assert w.frame.image.shape == f.image.shape and w.frame.image.dtype == np.uint8
    assert w.frame.depth.dtype == np.float32 and w.frame.right is None
    # depth is exact to the millimetre: q / 1000 of the rounded millimetres
    np.testing.assert_array_equal(w.frame.depth, _expected_depth(f.depth))
    valid = np.isfinite(f.depth) & (f.depth > 0) & (f.depth < 60)
    assert np.abs(w.frame.depth[valid] - f.depth[valid]).max() <= 0.0005 + 1e-6
    assert w.frame.depth[0, 0] == 0 and w.frame.depth[0, 1] == 0 and w.frame.depth[0, 2] == 0
    assert w.frame.depth[0, 3] == pytest.approx(65.535)  # clipped to 65535 mm
    assert np.all(w.frame.depth[f.depth == 0] == 0)
    if color == "jpeg":
        err = np.abs(w.frame.image.astype(int) - f.image.astype(int))
        assert err.mean() < 3.0 and np.percentile(err, 99) < 20
    else:
        np.testing.assert_array_equal(w.frame.image, f.image)
    w.frame.image[0, 0] = 1  # decoded arrays are writable
    w.frame.depth[0, 0] = 1.0


def test_depth_scale_travels():
    f = _rgbd()
    w = decode_frame(encode_frame(f, "r", 0, depth_scale=5000.0, color="png", depth="png"))
    np.testing.assert_array_equal(w.frame.depth, _expected_depth(f.depth, 5000.0))
    valid = np.isfinite(f.depth) & (f.depth > 0) & (f.depth < 13)
    assert np.abs(w.frame.depth[valid] - f.depth[valid]).max() <= 0.0001 + 1e-6


@pytest.mark.parametrize("second", ["raw", "png"])
@pytest.mark.parametrize("color", ["raw", "png", "jpeg"])
def test_stereo_round_trip(color, second):
    img, _ = _scene()
    grey = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    right = np.roll(grey, -3, axis=1)
    f = Frame(index=0, stamp=7.0, image=grey, right=right)
    w = decode_frame(encode_frame(f, "stereo-cam", 9, color=color, depth=second))
    assert w.kind == "stereo" and w.depth_encoding == second and w.frame.depth is None
    np.testing.assert_array_equal(w.frame.right, right)  # right image is lossless (raw / png)
    assert w.frame.image.shape == grey.shape
    if color != "jpeg":
        np.testing.assert_array_equal(w.frame.image, grey)
    # a colour right image travels as grey
    f2 = Frame(index=0, stamp=7.0, image=img, right=img)
    w2 = decode_frame(encode_frame(f2, "s", 1, color="png", depth=second))
    assert w2.frame.image.shape == img.shape
    np.testing.assert_array_equal(w2.frame.right, cv2.cvtColor(img, cv2.COLOR_BGR2GRAY))


@pytest.mark.parametrize("color", ["raw", "png", "jpeg"])
def test_mono_round_trip(color):
    img, _ = _scene()
    for image in (img, cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)):
        w = decode_frame(encode_frame(Frame(index=0, stamp=0.0, image=image), "m", 0, color=color))
        assert w.kind == "mono" and w.depth_encoding == "none"
        assert w.frame.depth is None and w.frame.right is None and w.frame.image.shape == image.shape
        if color != "jpeg":
            np.testing.assert_array_equal(w.frame.image, image)
    # kind="mono" drops the depth of an rgbd frame
    w = decode_frame(encode_frame(_rgbd(), "m", 0, kind="mono"))
    assert w.kind == "mono" and w.frame.depth is None


def test_layout_is_as_documented():
    f = _rgbd()
    msg = encode_frame(f, "ab", 5, color="raw", depth="raw")
    fields = FIXED.unpack_from(msg, 0)
    assert fields[0] == b"MSLF" and fields[1] == 1 and PROTOCOL_VERSION == 2  # no labels: a version 1 message
    assert fields[2] == 39 + 2 + 8 == FIXED_HEADER_BYTES + 2 + 8
    assert fields[3:6] == (0, 5, 1.25)
    assert fields[6:13] == (0, 0, 1, 64, 48, 3, 1000.0) and fields[13] == 2
    assert msg[39:41] == b"ab"
    clen, slen = LENGTHS.unpack_from(msg, 41)
    assert (clen, slen) == (64 * 48 * 3, 64 * 48 * 2) and len(msg) == 49 + clen + slen
    assert msg[49:49 + clen] == f.image.tobytes()
    assert msg[49 + clen:] == quantize_depth(f.depth, 1000.0).astype("<u2").tobytes()


def test_encode_rejects_what_cannot_be_sent():
    f = _rgbd()
    cases = [
        (dict(robot="bad robot"), "bad_robot"), (dict(robot=""), "bad_robot"), (dict(robot="x" * 65), "bad_robot"),
        (dict(seq=-1), "bad_seq"), (dict(seq=2**64), "bad_seq"), (dict(seq=1.5), "bad_seq"),
        (dict(color="webp"), "bad_header"), (dict(depth="jpeg"), "bad_header"), (dict(depth_scale=0.0), "bad_header"),
        (dict(depth_scale=float("nan")), "bad_header"), (dict(kind="lidar"), "bad_kind"),
        (dict(kind="stereo"), "bad_frame"),
    ]
    for kw, reason in cases:
        args = dict(robot="r", seq=0)
        args.update(kw)
        robot, seq = args.pop("robot"), args.pop("seq")
        with pytest.raises(ProtocolError) as e:
            encode_frame(f, robot, seq, **args)
        assert e.value.reason == reason, kw
    for stamp in (float("nan"), float("inf"), -1.0):
        with pytest.raises(ProtocolError) as e:
            encode_frame(Frame(0, stamp, f.image, f.depth), "r", 0)
        assert e.value.reason == "bad_stamp"
    for bad in (Frame(0, 0.0, f.image.astype(np.float32)), Frame(0, 0.0, f.image, depth=f.depth[:10]),
                Frame(0, 0.0, f.image[:, :, :2]), Frame(0, 0.0, f.image, right=f.image[:10])):
        with pytest.raises(ProtocolError) as e:
            encode_frame(bad, "r", 0)
        assert e.value.reason == "bad_frame"
    assert issubclass(ProtocolError, ValueError)


# ------------------------------------------------------------------------------------------
# crafted malformed messages

def _craft(*, magic=b"MSLF", version=1, header_len=None, flags=0, seq=1, stamp=0.5, kind=2, cenc=0, senc=0,
           w=4, h=3, c=1, scale=1000.0, robot=b"r", p1=None, p2=b"", clen=None, slen=None, extra=b"", tail=b""):
    if p1 is None:
        p1 = bytes(w * h * c)
    hl = FIXED.size + len(robot) + LENGTHS.size + len(extra) if header_len is None else header_len
    head = FIXED.pack(magic, version, hl, flags, seq, stamp, kind, cenc, senc, w, h, c, scale, len(robot))
    lengths = LENGTHS.pack(len(p1) if clen is None else clen, len(p2) if slen is None else slen)
    return head + robot + lengths + extra + p1 + p2 + tail


def _reason(msg, limits=Limits()):
    with pytest.raises(ProtocolError) as e:
        decode_frame(msg, limits)
    return e.value.reason


def _png(img):
    return cv2.imencode(".png", img)[1].tobytes()


def test_crafted_messages_have_their_reason():
    grey = np.arange(12, dtype=np.uint8).reshape(3, 4)
    assert decode_frame(_craft()).kind == "mono"  # the baseline is valid
    assert decode_frame(_craft(extra=b"\x00" * 5)).kind == "mono"  # extension bytes are skipped
    assert decode_frame(_craft(flags=0xFFFC)).kind == "mono"  # reserved flags bits are ignored
    png16 = _png(np.zeros((3, 4), np.uint16))
    cases = {
        "too_large": [(_craft(w=40, h=40), Limits(max_message_bytes=1000))],
        "truncated": [(b"", None), (b"MSL", None), (b"MSLF\x01", None), (_craft()[:38], None), (_craft()[:-1], None),
                      (_craft(header_len=200), None), (_craft(clen=13), None)],
        "bad_length": [(_craft(tail=b"\x00"), None), (_craft(clen=11, p1=bytes(12)), None)],
        "bad_magic": [(_craft(magic=b"MSLG"), None), (b"\x89PNG\r\n\x1a\n" + bytes(100), None), (b"GARB", None)],
        "bad_version": [(_craft(version=0), None), (_craft(version=3), None), (_craft(version=0xFFFF), None),
                        (b"MSLF\x03\x00", None)],
        "bad_header": [(_craft(header_len=10), None),
                       (_craft(version=2), None),  # a version 1 layout is too short for version 2
                       (_craft(header_len=2000, p1=bytes(2000)), None),
                       (_craft(kind=3), None), (_craft(cenc=3), None), (_craft(senc=3, kind=0), None),
                       (_craft(c=2), None), (_craft(c=0), None), (_craft(c=4), None),
                       (_craft(kind=2, senc=1, p2=bytes(12)), None),  # mono with a second image
                       (_craft(kind=0, senc=0), None),  # rgbd without depth
                       (_craft(kind=1, senc=0), None),  # stereo without right image
                       (_craft(kind=0, senc=1, p2=bytes(24), scale=float("nan")), None),
                       (_craft(kind=0, senc=1, p2=bytes(24), scale=0.0), None),
                       (_craft(kind=0, senc=1, p2=bytes(24), scale=-1.0), None),
                       (_craft(kind=0, senc=1, p2=bytes(24), scale=1e-30), None),
                       (_craft(kind=0, senc=1, p2=bytes(24), scale=1e30), None),
                       (_craft(kind=2, scale=float("inf")), None)],
        "bad_size": [(_craft(w=0, p1=b""), None), (_craft(h=0, p1=b""), None), (_craft(w=5000, p1=b"x"), None),
                     (_craft(h=4097, p1=b"x"), None), (_craft(w=64, h=64, p1=bytes(64 * 64)), Limits(max_width=32)),
                     (_craft(p1=bytes(11)), None), (_craft(c=3, p1=bytes(12)), None),
                     (_craft(kind=0, senc=1, p2=bytes(12)), None),  # raw depth is 2 bytes per pixel
                     (_craft(kind=1, senc=1, p2=bytes(24)), None),  # raw right image is 1 byte per pixel
                     (_craft(cenc=1, p1=b""), None), (_craft(cenc=2, p1=b""), None),
                     (_craft(kind=0, senc=2, p2=b""), None)],
        "bad_robot": [(_craft(robot=b"a b"), None), (_craft(robot=b""), None), (_craft(robot=b"\xff\xfe"), None),
                      (_craft(robot=b"x" * 65), None), (_craft(robot="é".encode()), None),
                      (_craft(robot=b"a/b"), None)],
        "bad_stamp": [(_craft(stamp=float("nan")), None), (_craft(stamp=float("inf")), None),
                      (_craft(stamp=float("-inf")), None), (_craft(stamp=-0.001), None)],
        "decode_failed": [(_craft(cenc=1, p1=b"not a png at all" * 3), None),
                          (_craft(cenc=2, p1=_png(grey)), None),  # PNG where JPEG is announced
                          (_craft(cenc=1, p1=cv2.imencode(".jpg", grey)[1].tobytes()), None),
                          (_craft(cenc=1, p1=cv2.imencode(".bmp", grey)[1].tobytes()), None),
                          (_craft(cenc=1, p1=_png(grey)[:40]), None),  # IHDR fine, data missing
                          (_craft(cenc=1, p1=png16), None),  # 16-bit where 8-bit is expected
                          (_craft(cenc=1, c=3, p1=_png(grey)), None),  # grey PNG for a colour image
                          (_craft(kind=0, senc=2, p2=_png(grey)), None),  # 8-bit depth PNG
                          (_craft(cenc=2, c=3, p1=cv2.imencode(".jpg", grey)[1].tobytes()), None),
                          (_craft(cenc=2, p1=b"\xff\xd8\xff\xe0\x00\x10JFIF\x00" + bytes(40)), None)],
        "size_mismatch": [(_craft(cenc=1, p1=_png(np.zeros((4, 3), np.uint8))), None),
                          (_craft(cenc=2, p1=cv2.imencode(".jpg", np.zeros((4, 3), np.uint8))[1].tobytes()), None),
                          (_craft(kind=0, senc=2, p2=_png(np.zeros((3, 5), np.uint16))), None)],
    }
    for reason, items in cases.items():
        for msg, limits in items:
            got = _reason(msg, limits or Limits())
            assert got == reason, (reason, got, msg[:60])
    # a decoded image whose shape differs although its PNG header agrees: an RGBA PNG for a 4×3 image
    rgba = _png(np.zeros((3, 4, 4), np.uint8))
    assert _reason(_craft(cenc=1, c=3, p1=rgba)) == "decode_failed"  # colour type 6 refused before decoding
    for bad_input in (None, 12, "MSLF", [1, 2], object()):
        assert _reason(bad_input) == "bad_type"
    # bytearray and memoryview inputs are fine
    msg = _craft()
    assert decode_frame(bytearray(msg)).seq == 1 and decode_frame(memoryview(msg)).seq == 1


def test_limits_checked_before_allocating():
    """Headers announcing huge images are refused from the header alone."""
    huge = [
        _craft(w=65535, h=65535, c=3, p1=bytes(10)),  # above the default 4096 limit
        _craft(w=65535, h=65535, c=3, cenc=1, p1=_png(np.zeros((2, 2), np.uint8))),
    ]
    relaxed = Limits(max_width=65535, max_height=65535)
    # the PNG inside claims 100000 × 100000 pixels while the message header says 64 × 48
    bomb = bytearray(_png(np.zeros((48, 64), np.uint8)))
    struct.pack_into(">II", bomb, 16, 100000, 100000)
    tracemalloc.start()
    try:
        t0 = time.perf_counter()
        assert _reason(huge[0]) == "bad_size"
        assert _reason(huge[1]) == "bad_size"
        assert _reason(huge[0], relaxed) == "bad_size"  # 12 GB raw image announced, 10 bytes present
        assert _reason(_craft(w=65535, h=65535, c=3, cenc=1, p1=bytes(bomb)), relaxed) == "size_mismatch"
        assert _reason(_craft(w=64, h=48, cenc=1, p1=bytes(bomb))) == "size_mismatch"
        jpeg = bytearray(cv2.imencode(".jpg", np.zeros((48, 64), np.uint8))[1].tobytes())
        sof = jpeg.find(b"\xff\xc0")
        struct.pack_into(">HH", jpeg, sof + 5, 60000, 60000)
        assert _reason(_craft(w=64, h=48, cenc=2, p1=bytes(jpeg))) == "size_mismatch"
        assert _reason(_craft(w=4, h=3, p1=bytes(12)), Limits(max_message_bytes=20)) == "too_large"
        elapsed = time.perf_counter() - t0
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 2_000_000, peak
    assert elapsed < 0.5


# ------------------------------------------------------------------------------------------
# fuzzing

def _valid_messages():
    f = _rgbd(24, 32, seed=1)
    grey = cv2.cvtColor(f.image, cv2.COLOR_BGR2GRAY)
    out = []
    for color in ("raw", "png", "jpeg"):
        for depth in ("raw", "png"):
            out.append(encode_frame(f, "fuzz", 42, color=color, depth=depth))
    out.append(encode_frame(Frame(0, 2.0, grey, right=np.roll(grey, 2, 1)), "fuzz", 1, color="png", depth="png"))
    out.append(encode_frame(Frame(0, 2.0, grey, right=grey), "fuzz", 1, color="jpeg", depth="raw"))
    out.append(encode_frame(Frame(0, 2.0, f.image), "fuzz", 1, color="jpeg"))
    out.append(encode_frame(Frame(0, 2.0, grey), "fuzz", 1, color="png"))
    labels = (np.arange(24 * 32).reshape(24, 32) // 40).astype(np.uint8)
    out.append(encode_frame(Frame(0, 2.0, f.image, f.depth, extras={"labels": labels}), "fuzz", 1, color="png",
                            depth="png", labels="png"))
    out.append(encode_frame(Frame(0, 2.0, grey, extras={"labels": labels.astype(np.uint16) * 300}), "fuzz", 1,
                            color="raw", labels="raw"))
    return out


def _outcome(msg, limits=Limits(max_message_bytes=1 << 20, max_width=256, max_height=256)):
    """'ok' or the ProtocolError reason; any other exception fails the test."""
    try:
        decode_frame(msg, limits)
        return "ok"
    except ProtocolError as e:
        assert isinstance(e.reason, str) and e.reason
        return e.reason


def test_fuzz_frames_raise_only_protocol_errors():
    rng = np.random.default_rng(1234)
    valid = _valid_messages()
    for m in valid:
        assert _outcome(m) == "ok"
    malformed = 0
    reasons: dict[str, int] = {}

    def count(reason):
        nonlocal malformed
        reasons[reason] = reasons.get(reason, 0) + 1
        malformed += reason != "ok"

    # 1. random bytes, with and without a valid magic / version in front
    for k in range(600):
        n = int(rng.integers(0, 300))
        junk = rng.bytes(n)
        if k % 3 == 1:
            junk = b"MSLF" + junk
        elif k % 3 == 2:
            junk = b"MSLF\x01\x00" + junk
        r = _outcome(junk)
        assert r != "ok"
        count(r)
    # 2. every truncation of three valid messages
    for m in (valid[1], valid[5], valid[6]):
        for cut in range(len(m)):
            r = _outcome(m[:cut])
            assert r == "truncated", (cut, r)
            count(r)
    # 3. bit flips (1..4 bits) anywhere, and in the header region specifically
    for k in range(1500):
        m = bytearray(valid[k % len(valid)])
        region = len(m) if k % 2 else min(len(m), 60)
        for _ in range(int(rng.integers(1, 5))):
            pos = int(rng.integers(0, region))
            m[pos] ^= 1 << int(rng.integers(0, 8))
        count(_outcome(bytes(m)))
    # 4. random header fields over valid payloads
    for k in range(400):
        m = bytearray(valid[k % len(valid)])
        pos = int(rng.integers(4, 47))
        m[pos] = int(rng.integers(0, 256))
        count(_outcome(bytes(m)))
    # 5. NaN / inf / negative stamps, wrong versions, oversize
    for m in valid:
        for stamp in (float("nan"), float("inf"), -float("inf"), -1e-9, -5.0):
            b = bytearray(m)
            struct.pack_into("<d", b, 18, stamp)
            r = _outcome(bytes(b))
            assert r == "bad_stamp"
            count(r)
        for version in (0, 3, 255, 65535):
            b = bytearray(m)
            struct.pack_into("<H", b, 4, version)
            r = _outcome(bytes(b))
            assert r == "bad_version"
            count(r)
        r = _outcome(m, Limits(max_message_bytes=len(m) - 1))
        assert r == "too_large"
        count(r)
    assert malformed >= 2000, (malformed, reasons)
    assert {"truncated", "bad_magic", "bad_version", "bad_stamp", "too_large", "bad_header"} <= set(reasons)


# ------------------------------------------------------------------------------------------
# camera info, pose, events

CAL = Calibration(PinholeCamera(525.0, 524.5, 319.5, 239.5, 640, 480), None, 5000.0)
STEREO = Calibration(PinholeCamera(458.0, 457.0, 367.2, 248.4, 752, 480), 0.11, 1000.0)


def test_info_round_trip():
    robot, cal = decode_info(encode_info("bot", CAL))
    assert robot == "bot" and cal == CAL
    info = decode_info_message(encode_info("bot", STEREO))
    assert info.kind == "stereo" and info.calibration == STEREO
    info = decode_info_message(encode_info("cam", CAL, kind="mono"))
    assert info.kind == "mono" and info.calibration == CAL
    obj = json.loads(encode_info("bot", CAL))
    assert obj == {"version": 1, "robot": "bot", "kind": "rgbd", "fx": 525.0, "fy": 524.5, "cx": 319.5, "cy": 239.5,
                   "width": 640, "height": 480, "baseline": None, "depth_scale": 5000.0}
    obj["future_field"] = [1, 2]  # unknown fields are ignored
    assert decode_info(json.dumps(obj).encode())[1] == CAL


def test_info_validation():
    base = json.loads(encode_info("bot", CAL))
    cases = [
        ({"fx": 0}, "bad_field"), ({"fy": -1.0}, "bad_field"), ({"fx": "525"}, "bad_json"), ({"fx": True}, "bad_json"),
        ({"cx": None}, "bad_json"), ({"width": 0}, "bad_field"), ({"height": 70000}, "bad_field"),
        ({"width": 640.5}, "bad_json"), ({"depth_scale": 0}, "bad_field"), ({"baseline": 0.1}, "bad_field"),
        ({"kind": "stereo"}, "bad_field"), ({"kind": "lidar"}, "bad_kind"), ({"version": 2}, "bad_version"),
        ({"version": True}, "bad_version"), ({"robot": "a b"}, "bad_robot"), ({"robot": None}, "bad_robot"),
    ]
    for change, reason in cases:
        obj = dict(base, **change)
        with pytest.raises(ProtocolError) as e:
            decode_info(json.dumps(obj).encode())
        assert e.value.reason == reason, change
    for raw, reason in [(json.dumps(dict(base, fx=12345.0)).replace("12345.0", "1e400").encode(), "bad_field"),
                        (b"", "bad_json"), (b"[1,2]", "bad_json"), (b"\xff\xfe", "bad_json"), (b"{", "bad_json"),
                        (json.dumps(dict(base, fx=1.0)).replace("1.0", "NaN").encode(), "bad_json"),
                        (b"[" * 100000 + b"]" * 100000, "bad_json"), (b" " * (2 << 20), "too_large"),
                        (None, "bad_type")]:
        with pytest.raises(ProtocolError) as e:
            decode_info(raw)
        assert e.value.reason == reason, raw[:20] if raw else raw
    with pytest.raises(ProtocolError):
        encode_info("bad robot", CAL)
    with pytest.raises(ProtocolError):
        encode_info("r", Calibration(PinholeCamera(float("nan"), 1, 0, 0, 10, 10)))


def test_pose_round_trip_and_validation():
    pose = np.eye(4)
    pose[:3, 3] = [1.0, -2.5, 0.1234567890123]
    pose[:3, :3] = cv2.Rodrigues(np.array([0.1, -0.2, 0.3]))[0]
    m = decode_pose(encode_pose("r1", 17, 3.5, "ok", pose, True, 2, 99))
    assert (m.robot, m.seq, m.stamp, m.status, m.keyframe, m.segment, m.node_id) == ("r1", 17, 3.5, "ok", True, 2, 99)
    np.testing.assert_array_equal(m.pose, pose)  # exact: JSON carries repr(float)
    m = decode_pose(encode_pose("r1", 18, 3.6, "lost", None, False, 0, None))
    assert m.pose is None and m.node_id is None and m.keyframe is False
    bad_pose = pose.copy()
    bad_pose[3, 0] = 1
    for kw, reason in [(dict(pose=np.eye(3)), "bad_field"), (dict(pose=bad_pose), "bad_field"),
                       (dict(pose=np.full((4, 4), np.nan)), "bad_field"), (dict(status="OK!"), "bad_field"),
                       (dict(seq=-1), "bad_seq"), (dict(stamp=float("nan")), "bad_stamp"),
                       (dict(segment=-1), "bad_field"), (dict(node_id=-3), "bad_field")]:
        args = dict(robot="r", seq=1, stamp=1.0, status="ok", pose=pose, keyframe=False, segment=0, node_id=None)
        args.update(kw)
        with pytest.raises(ProtocolError) as e:
            encode_pose(**args)
        assert e.value.reason == reason, kw
    base = json.loads(encode_pose("r1", 17, 3.5, "ok", pose, True, 2, 99))
    for change, reason in [({"seq": -1}, "bad_seq"), ({"seq": "1"}, "bad_json"), ({"stamp": -1}, "bad_stamp"),
                           ({"stamp": None}, "bad_json"), ({"pose": [[1, 2], [3, 4]]}, "bad_field"),
                           ({"pose": "eye"}, "bad_json"), ({"pose": [[1, 0, 0, 0]] * 3 + [["a", 0, 0, 1]]}, "bad_json"),
                           ({"keyframe": 1}, "bad_json"), ({"segment": 1.5}, "bad_json"),
                           ({"node_id": -1}, "bad_field"), ({"status": ""}, "bad_field"),
                           ({"version": 0}, "bad_version")]:
        with pytest.raises(ProtocolError) as e:
            decode_pose(json.dumps(dict(base, **change)).encode())
        assert e.value.reason == reason, change


def test_event_round_trip_and_validation():
    for kind in EVENT_KINDS:
        e = decode_event(encode_event("r1", kind, node=np.int64(4), score=np.float32(0.5), ids=np.arange(3), ok=True))
        assert (e.robot, e.kind) == ("r1", kind)
        assert e.data == {"node": 4, "score": 0.5, "ids": [0, 1, 2], "ok": True}
    e = decode_event(encode_event("r1", "keyframe_added", node_id=7, stamp=1.5))
    assert (e["kind"], e["robot"], e["node_id"], e.get("missing", 3), "stamp" in e, "x" in e) == (
        "keyframe_added", "r1", 7, 3, True, False)
    assert e.as_dict() == {"robot": "r1", "kind": "keyframe_added", "node_id": 7, "stamp": 1.5}
    with pytest.raises(KeyError):
        e["missing"]
    assert json.loads(encode_event("r1", "keyframe_added", node_id=7)) == {
        "version": 1, "robot": "r1", "kind": "keyframe_added", "data": {"node_id": 7}}
    assert decode_event(encode_event("r1", "session_started")).data == {}
    # data keys named like the positional arguments do not collide with them
    e = decode_event(encode_event("r1", "loop_closed", **{"kind": "x", "robot": "y", "from": 1}))
    assert (e.robot, e.kind, e.data) == ("r1", "loop_closed", {"kind": "x", "robot": "y", "from": 1})
    with pytest.raises(ProtocolError) as err:
        encode_event("r1", "exploded")
    assert err.value.reason == "bad_kind"
    with pytest.raises(ProtocolError) as err:
        encode_event("r1", "loop_closed", x=object())
    assert err.value.reason == "bad_json"
    with pytest.raises(ProtocolError) as err:
        encode_event("r1", "loop_closed", x=float("nan"))
    assert err.value.reason == "bad_json"
    for raw, reason in [(b'{"version":1,"robot":"r","kind":"nope","data":{}}', "bad_kind"),
                        (b'{"version":1,"robot":"r","kind":"loop_closed","data":[]}', "bad_json"),
                        (b'{"version":1,"kind":"loop_closed"}', "bad_robot")]:
        with pytest.raises(ProtocolError) as err:
            decode_event(raw)
        assert err.value.reason == reason


def test_fuzz_json_decoders():
    rng = np.random.default_rng(7)
    valid = [encode_info("bot", CAL), encode_info("s", STEREO), encode_pose("r", 1, 1.0, "ok", np.eye(4), True, 0, 3),
             encode_event("r", "loop_closed", a=1, b=[1.5, 2])]
    n = 0
    for k in range(800):
        m = bytearray(valid[k % len(valid)])
        if k % 4 == 0:
            m = bytearray(rng.bytes(int(rng.integers(0, 100))))
        elif k % 4 == 1:
            m = m[: int(rng.integers(0, len(m)))]
        else:
            for _ in range(int(rng.integers(1, 4))):
                m[int(rng.integers(0, len(m)))] = int(rng.integers(0, 256))
        for decoder in (decode_info, decode_pose, decode_event):
            try:
                decoder(bytes(m))
            except ProtocolError:
                n += 1
    assert n > 1500


# ------------------------------------------------------------------------------------------
# key space

def test_keyspace():
    ks = KeySpace()
    assert ks.prefix == "mnemoslam"
    assert ks.frame("r1") == "mnemoslam/r1/camera/frame"
    assert ks.info("r1") == "mnemoslam/r1/camera/info"
    assert ks.pose("r1") == "mnemoslam/r1/pose"
    assert ks.events("r1") == "mnemoslam/r1/events"
    assert ks.frames_wildcard() == "mnemoslam/*/camera/frame"
    assert ks.info_wildcard() == "mnemoslam/*/camera/info"
    for key in (ks.frame("A-b_9"), ks.info("A-b_9"), ks.pose("A-b_9"), ks.events("A-b_9")):
        assert ks.robot_of(key) == "A-b_9"
    assert ks.parse("mnemoslam/r1/camera/frame") == ("r1", "camera/frame")
    for key in ("mnemoslam/r1/camera", "mnemoslam/*/camera/frame", "other/r1/pose", "mnemoslam/r 1/pose",
                "mnemoslam/r1/pose/extra", "mnemoslam", "", "mnemoslam/r1/camera/depth", "mnemoslamx/r1/pose"):
        assert ks.robot_of(key) is None, key
    deep = KeySpace("site.a/fleet-2")
    assert deep.frame("r") == "site.a/fleet-2/r/camera/frame"
    assert deep.robot_of("site.a/fleet-2/r/pose") == "r" and deep.robot_of("site.a/r/pose") is None
    assert deep.frames_wildcard() == "site.a/fleet-2/*/camera/frame"
    for bad in ("bad robot", "", "a/b", "*", "x" * 65, "é"):
        with pytest.raises(ProtocolError) as e:
            ks.frame(bad)
        assert e.value.reason == "bad_robot"
    assert ks.frame("x" * 64).endswith("/camera/frame")
    for bad_prefix in ("", "a//b", "/a", "a/", "a/*", "a/**", "a b", "$x"):
        with pytest.raises(ProtocolError):
            KeySpace(bad_prefix)


def test_keyspace_accepts_zenoh_keyexpr():
    import zenoh

    ks = KeySpace("p")
    assert ks.robot_of(zenoh.KeyExpr("p/r7/camera/frame")) == "r7"


# ------------------------------------------------------------------------------------------
# label images (version 2) and the class table

from mnemoslam.client.kernel.protocol import DEFAULT_CLASSES, MAX_CLASSES  # noqa: E402

LABEL_FIELDS = struct.Struct("<BBI")  # label_enc, label_bytes, label_len (v2, after the lengths)


def _labels(h=48, w=64, dtype=np.uint8, top=32, seed=0):
    rng = np.random.default_rng(seed)
    lab = np.repeat(np.repeat(rng.integers(0, top, (h // 8 + 1, w // 8 + 1)), 8, 0), 8, 1)[:h, :w]
    return lab.astype(dtype)


@pytest.mark.parametrize("encoding", ["raw", "png"])
@pytest.mark.parametrize("dtype,top", [(np.uint8, 32), (np.uint8, 256), (np.uint16, 65536)])
@pytest.mark.parametrize("kind", ["rgbd", "stereo", "mono"])
def test_label_round_trip(encoding, dtype, top, kind):
    img, depth = _scene()
    grey = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    lab = _labels(dtype=dtype, top=top)
    f = {"rgbd": Frame(7, 1.5, img, depth=depth), "stereo": Frame(7, 1.5, grey, right=grey),
         "mono": Frame(7, 1.5, img)}[kind]
    f.extras.update(labels=lab, instances=np.zeros(lab.shape, np.int32))
    msg = encode_frame(f, "lab", 7, color="png", depth="png", labels=encoding)
    w = decode_frame(msg)
    assert (w.version, w.label_encoding, w.kind, w.size) == (2, encoding, kind, len(msg))
    got = w.frame.extras["labels"]
    assert got.dtype == dtype and got.shape == lab.shape
    np.testing.assert_array_equal(got, lab)  # lossless
    assert set(w.frame.extras) == {"labels"}  # only the labels travel; names only when given
    names = tuple(f"c{i}" for i in range(300))
    w = decode_frame(msg, label_names=names)
    assert w.frame.extras["label_names"] == names and isinstance(w.frame.extras["label_names"], tuple)
    if kind == "rgbd":
        np.testing.assert_array_equal(w.frame.depth, _expected_depth(depth))


def test_label_layout_is_as_documented():
    f = _rgbd()
    lab = _labels()
    f.extras["labels"] = lab
    msg = encode_frame(f, "ab", 5, color="raw", depth="raw", labels="raw")
    fields = FIXED.unpack_from(msg, 0)
    assert fields[1] == 2 and fields[2] == 39 + 2 + 8 + 6
    clen, slen = LENGTHS.unpack_from(msg, 41)
    lenc, lbytes, llen = LABEL_FIELDS.unpack_from(msg, 49)
    assert (lenc, lbytes, llen) == (1, 1, 64 * 48)
    assert len(msg) == 55 + clen + slen + llen and msg[55 + clen + slen:] == lab.tobytes()
    f.extras["labels"] = lab.astype(np.uint16) + 1000
    msg16 = encode_frame(f, "ab", 5, color="raw", depth="raw", labels="raw")
    assert LABEL_FIELDS.unpack_from(msg16, 49) == (1, 2, 64 * 48 * 2)
    assert msg16[55 + clen + slen:] == (lab.astype("<u2") + np.uint16(1000)).tobytes()  # little-endian uint16
    png = encode_frame(f, "ab", 5, color="raw", depth="raw", labels="png")
    lenc, lbytes, llen = LABEL_FIELDS.unpack_from(png, 49)
    assert (lenc, lbytes) == (2, 2)
    p3 = png[55 + clen + slen:]
    assert len(p3) == llen and p3[:8] == b"\x89PNG\r\n\x1a\n"
    np.testing.assert_array_equal(cv2.imdecode(np.frombuffer(p3, np.uint8), cv2.IMREAD_UNCHANGED),
                                  lab.astype(np.uint16) + 1000)


def test_old_format_without_labels_is_unchanged():
    """No labels asked: a version 1 message, byte for byte what a frame without extras gives
    (old services read it); a version 1 message decodes without labels as before."""
    f = _rgbd()
    plain = encode_frame(f, "r", 3, color="png", depth="png")
    f.extras["labels"] = _labels()
    assert encode_frame(f, "r", 3, color="png", depth="png") == plain
    assert encode_frame(f, "r", 3, color="png", depth="png", labels="none") == plain
    w = decode_frame(plain)
    assert (w.version, w.label_encoding, w.frame.extras) == (1, "none", {})
    assert decode_frame(plain, label_names=DEFAULT_CLASSES).frame.extras == {}  # names only with labels
    assert decode_frame(_craft(), Limits(classes=2)).frame.extras == {}
    # a version 2 message may carry no label image (encoding none, 0 bytes)
    v2 = _craft(version=2, extra=LABEL_FIELDS.pack(0, 0, 0))
    assert decode_frame(v2).version == 2 and decode_frame(v2).frame.extras == {}
    # version 2 readers skip extension bytes after the label fields, as version 1 readers do
    lab = np.arange(12, dtype=np.uint8).reshape(3, 4)
    ext = _craft(version=2, extra=LABEL_FIELDS.pack(1, 1, 12) + b"\x00" * 7, tail=lab.tobytes())
    np.testing.assert_array_equal(decode_frame(ext).frame.extras["labels"], lab)


def _craft2(lenc=1, lbytes=1, llen=None, p3=None, **kw):
    """A 4×3 mono frame with a label payload (version 2)."""
    if p3 is None:
        p3 = bytes(12 * lbytes)
    return _craft(version=2, extra=LABEL_FIELDS.pack(lenc, lbytes, len(p3) if llen is None else llen),
                  tail=p3, **kw)


def test_malformed_label_images_have_their_reason():
    lab8 = np.arange(12, dtype=np.uint8).reshape(3, 4)
    assert decode_frame(_craft2(p3=lab8.tobytes())).frame.extras["labels"].tolist() == lab8.tolist()
    assert decode_frame(_craft2(lenc=2, p3=_png(lab8))).frame.extras["labels"].dtype == np.uint8
    assert decode_frame(_craft2(lenc=2, lbytes=2, p3=_png(lab8.astype(np.uint16)))).frame.extras["labels"].dtype \
        == np.uint16
    huge_png = bytearray(_png(lab8))
    struct.pack_into(">II", huge_png, 16, 65535, 65535)  # IHDR claims 65535×65535
    cases = {
        "bad_header": [_craft2(lenc=3), _craft2(lenc=0, lbytes=1, p3=b""), _craft2(lenc=0, lbytes=0, p3=bytes(12)),
                       _craft2(lbytes=0), _craft2(lbytes=4, p3=bytes(48)),  # int32 labels: not a wire dtype
                       _craft2(lbytes=3, p3=bytes(36))],
        "bad_size": [_craft2(p3=bytes(11)), _craft2(p3=bytes(13)), _craft2(lbytes=2, p3=bytes(12)),  # uint16 needs 24
                     _craft2(lenc=2, p3=b"")],
        "truncated": [_craft2(p3=bytes(12))[:-1], _craft2(llen=13, p3=bytes(12))],
        "bad_length": [_craft2(llen=11, p3=bytes(12))],
        "decode_failed": [_craft2(lenc=2, p3=b"garbage, not a PNG" * 4),
                          _craft2(lenc=2, p3=_png(lab8)[:45]),  # IHDR fine, data cut
                          _craft2(lenc=2, p3=_png(lab8)[:-20] + bytes(20)),  # corrupt data
                          _craft2(lenc=2, lbytes=2, p3=_png(lab8)),  # 8-bit PNG, header says uint16
                          _craft2(lenc=2, lbytes=1, p3=_png(lab8.astype(np.uint16))),  # and the reverse
                          _craft2(lenc=2, p3=_png(np.dstack([lab8] * 3))),  # colour PNG
                          _craft2(lenc=2, p3=cv2.imencode(".jpg", lab8)[1].tobytes())],
        "size_mismatch": [_craft2(lenc=2, p3=_png(np.zeros((4, 3), np.uint8))),  # wrong size
                          _craft2(lenc=2, p3=_png(np.zeros((3, 5), np.uint8))),
                          _craft2(lenc=2, p3=bytes(huge_png))],  # oversize: refused from the PNG header
    }
    for reason, msgs in cases.items():
        for msg in msgs:
            assert _reason(msg) == reason, (reason, msg[40:70])
    # oversize messages: the label payload counts towards the message limit
    assert _reason(_craft2(p3=bytes(12)), Limits(max_message_bytes=len(_craft2()) - 1)) == "too_large"
    # ids beyond the camera's class table
    assert _reason(_craft2(p3=lab8.tobytes()), Limits(classes=11)) == "bad_labels"
    assert decode_frame(_craft2(p3=lab8.tobytes()), Limits(classes=12)).frame.extras["labels"].max() == 11
    # a big label PNG allocates nothing before its header is checked against the image size
    tracemalloc.start()
    try:
        _reason(_craft2(lenc=2, p3=bytes(huge_png)))
        assert tracemalloc.get_traced_memory()[1] < 1 << 20
    finally:
        tracemalloc.stop()


def test_encode_rejects_labels_that_cannot_be_sent():
    f = _rgbd()
    def reason(labels, encoding="png"):
        g = Frame(f.index, f.stamp, f.image, f.depth)
        if labels is not None:
            g.extras["labels"] = labels
        with pytest.raises(ProtocolError) as e:
            encode_frame(g, "r", 0, labels=encoding)
        return e.value.reason
    assert reason(_labels(), "jpeg") == "bad_header"
    assert reason(None) == "bad_frame"  # nothing to send
    assert reason(_labels(24, 32)) == "bad_frame"  # wrong size
    assert reason(_labels()[..., None]) == "bad_frame"  # H×W×1
    assert reason(_labels().astype(np.float32)) == "bad_frame"
    assert reason(_labels().astype(bool)) == "bad_frame"
    assert reason(_labels().astype(np.int32) - 1) == "bad_frame"  # negative ids
    assert reason(_labels().astype(np.int64) + 65536) == "bad_frame"  # beyond uint16
    assert reason([[0] * 64] * 48) == "bad_frame"  # not an array
    # other integer arrays travel as the smallest wire dtype that holds them
    for src, want in ((np.int32, np.uint8), (np.int64, np.uint8)):
        g = Frame(0, 0.0, f.image, f.depth, extras={"labels": _labels().astype(src)})
        assert decode_frame(encode_frame(g, "r", 0, labels="png")).frame.extras["labels"].dtype == want
    g = Frame(0, 0.0, f.image, f.depth, extras={"labels": _labels().astype(np.int32) * 300})
    got = decode_frame(encode_frame(g, "r", 0, labels="raw")).frame.extras["labels"]
    assert got.dtype == np.uint16 and np.array_equal(got, _labels().astype(np.int32) * 300)


def test_info_class_table():
    assert len(DEFAULT_CLASSES) == 32 and DEFAULT_CLASSES[15] == "door" and DEFAULT_CLASSES[31] == "armchair"
    info = decode_info_message(encode_info("bot", CAL))
    assert info.classes is None and info.class_count == 32  # absent: the default table
    assert "classes" not in json.loads(encode_info("bot", CAL))  # and not sent (old readers see the same)
    info = decode_info_message(encode_info("bot", CAL, classes=DEFAULT_CLASSES))
    assert info.classes == DEFAULT_CLASSES and info.calibration == CAL
    assert json.loads(encode_info("bot", CAL, classes=["a", "b"]))["classes"] == ["a", "b"]
    big = [f"class {i}" for i in range(MAX_CLASSES)]
    assert decode_info_message(encode_info("bot", CAL, classes=big)).class_count == MAX_CLASSES
    base = json.loads(encode_info("bot", CAL))
    cases = [("door", "bad_json"), ({"0": "door"}, "bad_json"), (3, "bad_json"), ([], "bad_field"),
             (["a", 1], "bad_json"), (["a", None], "bad_json"), (["a", ""], "bad_field"),
             (["a", "x" * 65], "bad_field"),
             (["a", "b\n"], "bad_field"), (["a", "b", "a"], "bad_field"), (big + ["one more"], "bad_field")]
    for classes, why in cases:
        with pytest.raises(ProtocolError) as e:
            decode_info_message(json.dumps(dict(base, classes=classes)).encode())
        assert e.value.reason == why, classes
        if isinstance(classes, list):
            with pytest.raises(ProtocolError):
                encode_info("bot", CAL, classes=classes)
    assert decode_info_message(json.dumps(dict(base, classes=None)).encode()).classes is None  # null = absent


# ------------------------------------------------------------------------------------------
# sensor fields: the depth image's stamp and the accelerometer (flags bits 0 and 1)

def test_sensor_fields_round_trip_and_layout():
    """A frame's depth stamp and accelerometer reading travel exactly in the header's
    extension bytes, in flags-bit order after the version's fields, in both versions; a frame
    without them is byte for byte as before; a reader that ignores flags (an older one) skips
    them and still decodes the images."""
    f = _rgbd()
    plain = encode_frame(f, "ab", 5, color="raw", depth="raw")
    f.extras.update(depth_stamp=1.2371, accel=np.array([0.31, -9.62, 1.75]))
    msg = encode_frame(f, "ab", 5, color="raw", depth="raw")
    fields = FIXED.unpack_from(msg, 0)
    assert fields[1] == 1 and fields[3] == 0b11 and fields[2] == 49 + 8 + 24  # header_len covers them
    assert struct.unpack_from("<d3d", msg, 49) == (1.2371, 0.31, -9.62, 1.75)
    assert msg[49 + 32:] == plain[49:]  # then the payloads, unchanged
    w = decode_frame(msg)
    assert w.frame.extras["depth_stamp"] == 1.2371
    np.testing.assert_array_equal(w.frame.extras["accel"], [0.31, -9.62, 1.75])
    np.testing.assert_array_equal(w.frame.depth, decode_frame(plain).frame.depth)
    older = bytearray(msg)
    struct.pack_into("<H", older, 8, 0)  # what a reader that ignores flags sees
    assert decode_frame(bytes(older)).frame.extras == {} and decode_frame(bytes(older)).seq == 5
    # each alone, and after a version 2 message's label fields
    only_accel = dict(f.extras)
    del only_accel["depth_stamp"]
    g = Frame(index=3, stamp=1.25, image=f.image, depth=f.depth, extras=only_accel)
    m = encode_frame(g, "ab", 5, color="raw", depth="raw")
    assert FIXED.unpack_from(m, 0)[3] == 0b10 and set(decode_frame(m).frame.extras) == {"accel"}
    g.extras = {"depth_stamp": 3.5, "labels": np.zeros((48, 64), np.uint8)}
    m = encode_frame(g, "ab", 5, color="raw", depth="raw", labels="raw")
    w = decode_frame(m)
    assert w.version == 2 and w.frame.extras["depth_stamp"] == 3.5 and w.frame.extras["labels"].shape == (48, 64)
    # the depth stamp belongs to depth: a mono message of the same frame has none
    assert "depth_stamp" not in decode_frame(encode_frame(g, "ab", 5, color="raw", kind="mono")).frame.extras


def test_malformed_sensor_fields_have_their_reason():
    stamp = struct.pack("<d", 2.0)
    accel = struct.pack("<3d", 0.0, -9.8, 0.0)
    rgbd = dict(kind=0, senc=1, p2=bytes(24))
    assert decode_frame(_craft(flags=1, extra=stamp, **rgbd)).frame.extras == {"depth_stamp": 2.0}
    assert decode_frame(_craft(flags=2, extra=accel)).frame.extras["accel"].tolist() == [0.0, -9.8, 0.0]
    assert _reason(_craft(flags=1, extra=stamp[:4], **rgbd)) == "bad_header"  # header too short for it
    assert _reason(_craft(flags=3, extra=stamp, **rgbd)) == "bad_header"
    assert _reason(_craft(flags=1, extra=stamp)) == "bad_header"  # a depth stamp without depth
    for bad in (float("nan"), float("inf"), -1.0):
        assert _reason(_craft(flags=1, extra=struct.pack("<d", bad), **rgbd)) == "bad_stamp"
    for bad in ((float("nan"), 0, 0), (0, float("inf"), 0), (2000.0, 0, 0)):
        assert _reason(_craft(flags=2, extra=struct.pack("<3d", *bad))) == "bad_header"
    # what cannot be sent
    f = _rgbd()
    for extras, reason in (({"depth_stamp": float("nan")}, "bad_stamp"), ({"depth_stamp": "x"}, "bad_stamp"),
                           ({"accel": [1.0, 2.0]}, "bad_frame"), ({"accel": [0, 0, float("nan")]}, "bad_frame"),
                           ({"accel": [0, 0, 5000.0]}, "bad_frame")):
        f.extras = extras
        with pytest.raises(ProtocolError) as e:
            encode_frame(f, "r", 1, color="raw", depth="raw")
        assert e.value.reason == reason, extras
