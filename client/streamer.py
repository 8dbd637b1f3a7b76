"""The camera client: stream a dataset, a video file or a camera to the service over Zenoh.

    from mnemoslam.client.streamer import CameraStreamer, stream_dataset
    from mnemoslam.client.transport import ZenohSettings, open_session
    from mnemoslam.client.kernel.protocol import KeySpace

    stats = stream_dataset(open_dataset("synthetic:loop"), "robot1", ZenohSettings.client(), rate=15)
    print(stats.line())

    session = open_session(ZenohSettings.client())              # or with your own session
    with CameraStreamer(session, "robot1", dataset.calibration, KeySpace()) as cam:
        for seq, frame in enumerate(dataset):
            cam.send(frame, seq)

What goes on the wire is `mnemoslam.client.kernel.protocol` (frame messages on `<prefix>/<robot>/camera/frame`,
the camera info on `<prefix>/<robot>/camera/info`).

Delivery: the frame publisher uses CongestionControl.BLOCK and reliable transport, so the
client never drops a frame silently: when the network is congested `send` blocks until there
is room. The service answers every frame it processes with a pose message that also says how
many of this robot's frames it dropped because its queue was full (back-pressure the camera can
see: `CameraStreamer.answered_seq` / `service_dropped`). `stream_dataset` without a rate sends
as fast as the service takes frames (at most `window` frames in flight, so none is dropped);
with a rate it paces the frames and, with `adapt`, lowers the rate by 10 % whenever the service
reports new drops. Frames published while no subscriber
matches the key are not stored anywhere: start the service first, or use
`wait_for_subscriber`. The camera info is `put` once at start AND served by a queryable on the
info key, so a service that starts later gets it with `session.get(keyspace.info(robot))`.

Labels: a camera that segments on board sends each frame's per-pixel class ids
(``frame.extras["labels"]``) with the frame (`CameraStreamer(labels="png" | "raw")`,
`stream_dataset(labels=True)`, ``mnemoslam stream ... --labels``), and its class table once in
the camera info (default `protocol.DEFAULT_CLASSES`, ADE20K-32, which the synthetic scene
uses). Without labels nothing changes on the wire (version 1 frame messages, no class table).

CLI (wired in service/cli.py as `mnemoslam stream`): `add_stream_arguments(parser)` defines the
options and sets `stream_main` as the command's `func`.
"""
from __future__ import annotations

import argparse
import itertools
import logging
import math
import sys
import threading
import time
from dataclasses import dataclass

from .kernel.frames import Calibration, DatasetError, Frame
from .kernel.protocol import (
    DEFAULT_CLASSES,
    DEFAULT_PREFIX,
    KINDS,
    LABEL_ENCODINGS,
    KeySpace,
    ProtocolError,
    decode_event,
    decode_pose,
    encode_frame,
    encode_info,
    frame_kind,
)
from .transport import DEFAULT_ENDPOINT, MODES, ZenohSettings, open_session, undeclare_all

log = logging.getLogger(__name__)


class CameraStreamer:
    """Publishes one robot's camera on a Zenoh session (the session stays the caller's).

    On construction it puts the camera info once and declares a queryable on the info key that
    answers with it; `send` encodes a frame and puts it on the frame key through one publisher
    declared here (CongestionControl.BLOCK: never dropped by the client, see the module
    documentation). `kind` ("rgbd", "stereo", "mono") defaults to the source's: `calibration.kind`
    ("stereo" with a baseline, else "rgbd"); pass "mono" for a camera without depth.
    `depth_scale` (raw depth units per metre on the wire) defaults to `calibration.depth_scale`.
    `labels` "png" / "raw" also sends every frame's ``extras["labels"]`` (a frame without them
    is a ProtocolError "bad_frame") and puts the class table `classes` (default
    `DEFAULT_CLASSES`) in the camera info; None (default) sends neither.
    """

    def __init__(self, session, robot: str, calibration: Calibration, keyspace: KeySpace | None = None, *,
                 color: str = "jpeg", depth: str = "png", depth_scale: float | None = None,
                 kind: str | None = None, jpeg_quality: int = 90, labels: str | None = None,
                 classes: tuple[str, ...] | list[str] | None = None, localize: bool = False):
        import zenoh

        self.session = session
        self.keyspace = keyspace if keyspace is not None else KeySpace()
        self.robot = robot
        self.frame_key = self.keyspace.frame(robot)  # validates the robot id
        self.info_key = self.keyspace.info(robot)
        self.kind = kind if kind is not None else calibration.kind
        if self.kind not in KINDS:
            raise ProtocolError("bad_kind", f"kind must be one of {', '.join(KINDS)}, got {self.kind!r}")
        if color not in ("jpeg", "png", "raw"):
            raise ValueError(f"colour encoding must be jpeg, png or raw, got {color!r}")
        if depth not in ("png", "raw"):
            raise ValueError(f"depth encoding must be png or raw, got {depth!r}")
        if labels is not None and (labels not in LABEL_ENCODINGS or labels == "none"):
            raise ValueError(f"label encoding must be png or raw, got {labels!r}")
        self.color, self.depth, self.jpeg_quality = color, depth, int(jpeg_quality)
        self.labels = labels
        self.depth_scale = float(depth_scale if depth_scale is not None else calibration.depth_scale)
        self.calibration = calibration
        self.classes = None if labels is None else tuple(classes if classes is not None else DEFAULT_CLASSES)
        self.localize = bool(localize)  # ask for localization only (camera info `localize`)
        self.info = encode_info(robot, calibration, self.kind, classes=self.classes, localize=self.localize)
        self.frames_sent = 0
        self.bytes_sent = 0
        self._closed = False
        # what the service says back (its pose messages): the last frame it answered, how many
        # it answered, how many of ours it dropped (back-pressure)
        self.answered_seq: int | None = None
        self.answered = 0
        self.service_dropped = 0
        # ... and its events: frames it refused (frame_rejected: reason -> count, the first
        # reason's detail), sessions it started and ended for this robot (a camera restart)
        self.rejected: dict[str, int] = {}
        self.rejected_detail: dict[str, str] = {}
        self.sessions_started: list[int] = []
        self.sessions_ended: list[tuple[int | None, str]] = []  # (session id, reason)
        self._done_seq = -1  # the newest frame answered or refused
        self._answer = threading.Condition()
        self._publisher = session.declare_publisher(
            self.frame_key, congestion_control=zenoh.CongestionControl.BLOCK,
            reliability=zenoh.Reliability.RELIABLE)
        self._queryable = session.declare_queryable(self.info_key, self._answer_info)
        self._poses = session.declare_subscriber(self.keyspace.pose(robot), self._on_pose)
        self._events = session.declare_subscriber(self.keyspace.events(robot), self._on_event)
        session.put(self.info_key, self.info, congestion_control=zenoh.CongestionControl.BLOCK)

    def _on_event(self, sample) -> None:
        try:
            e = decode_event(sample.payload.to_bytes())
        except ProtocolError as err:
            log.debug("bad event message: %s", err)
            return
        with self._answer:
            if e.kind == "frame_rejected":
                reason = str(e.get("reason") or "unknown")
                self.rejected[reason] = self.rejected.get(reason, 0) + 1
                self.rejected_detail.setdefault(reason, str(e.get("detail") or ""))
                if isinstance(e.get("seq"), int):
                    self._done_seq = max(self._done_seq, e["seq"])
                self._answer.notify_all()
            elif e.kind == "session_started" and isinstance(e.get("session_id"), int):
                self.sessions_started.append(e["session_id"])
            elif e.kind == "session_ended":
                self.sessions_ended.append((e.get("session_id"), str(e.get("reason"))))
                if e.get("reason") == "restarted":
                    log.warning("the service ended session %s of %s (reason restarted: the stamps jumped back, "
                                "taken as a camera restart); a new session starts", e.get("session_id"), self.robot)

    def _on_pose(self, sample) -> None:
        try:
            msg = decode_pose(sample.payload.to_bytes())
        except ProtocolError as e:
            log.debug("bad pose message: %s", e)
            return
        with self._answer:
            self.answered += 1
            self.answered_seq = msg.seq if self.answered_seq is None else max(self.answered_seq, msg.seq)
            if msg.dropped is not None:
                self.service_dropped = max(self.service_dropped, msg.dropped)
            self._done_seq = max(self._done_seq, msg.seq)
            self._answer.notify_all()

    @property
    def rejected_total(self) -> int:
        return sum(self.rejected.values())

    def wait_for_room(self, seq: int, window: int, timeout: float) -> bool:
        """Wait until the service has answered (or refused: frame_rejected) frame `seq - window`
        or a later one, i.e. at most `window` frames are in flight (True), or `timeout` seconds
        passed (False: the service does not answer)."""
        end = time.monotonic() + timeout
        with self._answer:
            while self._done_seq < seq - window:
                left = end - time.monotonic()
                if left <= 0:
                    return False
                self._answer.wait(left)
        return True

    def _answer_info(self, query) -> None:
        try:
            query.reply(self.info_key, self.info)
        except Exception as e:  # a query that went away must not kill zenoh's callback thread
            log.debug("camera info reply failed: %s", e)

    @property
    def has_subscriber(self) -> bool:
        """True when some subscriber on the network matches the frame key."""
        return bool(self._publisher.matching_status.matching)

    def wait_for_subscriber(self, timeout: float, on_wait=None, after: float = 1.0) -> bool:
        """Wait up to `timeout` seconds (math.inf: as long as it takes) for a subscriber of the
        frame key; True if there is one. `on_wait()` is called once when none came within
        `after` seconds. When one had to be waited for, the camera info is put again: the put at
        construction reached nobody, and the service admits a robot when its info arrives."""
        start = time.monotonic()
        end = start + max(0.0, timeout)
        waited = False
        while not self.has_subscriber:
            now = time.monotonic()
            if now >= end:
                return False
            if on_wait is not None and now - start >= after:
                on_wait()
                on_wait = None
            waited = True
            time.sleep(0.01)
        if waited:
            import zenoh

            self.session.put(self.info_key, self.info, congestion_control=zenoh.CongestionControl.BLOCK)
        return True

    def encode(self, frame: Frame, seq: int) -> bytes:
        """The frame message `send` would put (ProtocolError if the frame does not fit the kind)."""
        have = frame_kind(frame)
        if self.kind != "mono" and have != self.kind:
            raise ProtocolError("bad_frame", f"{frame.source or 'frame'}: a {self.kind} camera got a {have} frame")
        return encode_frame(frame, self.robot, seq, depth_scale=self.depth_scale, color=self.color,
                            depth=self.depth, jpeg_quality=self.jpeg_quality, kind=self.kind,
                            labels=self.labels or "none")

    def send(self, frame: Frame, seq: int) -> int:
        """Encode and publish one frame; returns the message size in bytes. Blocks while the
        network / receiver is congested."""
        if self._closed:
            raise RuntimeError("CameraStreamer is closed")
        message = self.encode(frame, seq)
        self._publisher.put(message)
        self.frames_sent += 1
        self.bytes_sent += len(message)
        return len(message)

    def close(self) -> None:
        """Undeclare the publisher and the info queryable (the session stays open)."""
        if self._closed:
            return
        self._closed = True
        undeclare_all((self._publisher, self._queryable, self._poses, self._events))

    def __enter__(self) -> "CameraStreamer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@dataclass
class StreamStats:
    """What `stream_dataset` sent. `mbps` is megabits per second of frame messages."""

    frames: int
    bytes: int
    seconds: float
    fps: float
    mbps: float
    subscriber: bool = True  # a subscriber matched the frame key when streaming ended
    encoding: str = ""  # colour/depth encodings used, e.g. "raw/raw"
    answered: int = 0  # frames the service answered with a pose
    dropped: int = 0  # frames the service reported dropping (its queue was full)
    rate: float | None = None  # the rate in the end (lower than asked when adapted to drops)
    skipped: int = 0  # frames whose files could not be read (DatasetError), logged and not sent
    rejected: dict | None = None  # reason -> frames the service refused (its frame_rejected events)
    rejected_detail: dict | None = None  # reason -> the service's detail of the first such frame
    sessions: list | None = None  # the service's sessions of the robot started while streaming
    restarts: int = 0  # of those ended meanwhile, the ones ended "restarted" (a camera restart)

    @property
    def rejected_total(self) -> int:
        return sum((self.rejected or {}).values())

    def line(self) -> str:
        rejected = self.rejected_total
        return (f"streamed {self.frames} frames, {self.bytes / 1e6:.1f} MB in {self.seconds:.2f} s "
                f"({self.fps:.1f} fps, {self.mbps:.1f} Mbit/s, {self.encoding}); the service answered "
                f"{self.answered} and dropped {self.dropped}"
                + (f", rejected {rejected} ({self.reasons()})" if rejected else "")
                + (f"; {self.skipped} unreadable frame(s) skipped" if self.skipped else "")
                + (f"; it took {self.restarts} camera restart(s): new session(s) "
                   f"{', '.join(map(str, (self.sessions or [])[-self.restarts:]))}" if self.restarts else "")
                + ("" if self.subscriber else "; no subscriber was listening"))

    def reasons(self) -> str:
        """"stamp_order: 20, size_mismatch: 1", most frequent first."""
        return ", ".join(f"{r}: {n}" for r, n in sorted((self.rejected or {}).items(), key=lambda kv: -kv[1]))


def _length(dataset) -> int | None:
    try:
        return len(dataset)
    except TypeError:
        return None


def resolve_encodings(color: str, depth: str, settings: ZenohSettings) -> tuple[str, str]:
    """"auto" encodings: raw frames to a service on this host (no encode / decode CPU on either
    side; 640×480 RGB-D is 1.5 MB, ~44 MB/s at 30 Hz), JPEG colour and PNG depth over a network."""
    local = settings.local
    return (("raw" if local else "jpeg") if color == "auto" else color,
            ("raw" if local else "png") if depth == "auto" else depth)


def _frames(dataset):
    """The frames of `dataset` in order; a frame that cannot be read comes as its
    DatasetError instead of ending the stream (as `service.runner` skips it). A `Dataset`
    with the default iteration is read by index (`frame(i)`), so one bad file costs one
    frame; other iterables (CaptureSource: in order from the device) are iterated, and a
    generator that raised ends there."""
    from .datasets import Dataset

    if isinstance(dataset, Dataset) and type(dataset).__iter__ is Dataset.__iter__:
        for i in range(len(dataset)):
            try:
                yield dataset.frame(i)
            except DatasetError as e:
                yield e
        return
    frames = iter(dataset)
    while True:
        try:
            yield next(frames)
        except StopIteration:
            return
        except DatasetError as e:
            yield e


def stream_dataset(dataset, robot: str, settings: ZenohSettings | None = None, *, rate: float | None = None,
                   color: str = "auto", depth: str = "auto", prefix: str = DEFAULT_PREFIX, progress: bool = True,
                   max_frames: int | None = None, wait_for_subscriber: float = 0.0,
                   kind: str | None = None, session=None, window: int = 4, adapt: bool = False,
                   answer_timeout: float = 2.0, labels: bool = False,
                   classes: tuple[str, ...] | list[str] | None = None, require_subscriber: bool = False,
                   on_wait=None, localize: bool = False) -> StreamStats:
    """Stream every frame of `dataset` (any `Dataset`, incl. `CaptureSource`) as `robot`.

    Opens a session with `settings` (default `ZenohSettings.client()`), unless an open
    `session` is given (then it is left open). `rate` None sends as fast as the service takes
    the frames: frame k waits until the service answered frame k - `window` (or
    `answer_timeout` seconds passed: a rejected frame is never answered). A rate sends frame k
    at k / rate seconds after the first (real time at that rate; late frames are sent at once,
    never skipped); with `adapt`, each time the service reports new drops the rate is lowered by
    10 %. `color` / `depth` "auto": raw to a service on this host, JPEG / PNG otherwise
    (`resolve_encodings`). At the end it waits up to `answer_timeout` for the last answer.
    `wait_for_subscriber` seconds: wait
    that long for a subscriber on the frame key before the first frame (then stream anyway).
    seq counts frames from 0. `kind` defaults to the dataset's `kind` attribute if it has one
    (CaptureSource: "mono"), else its calibration's.

    `require_subscriber`: no subscriber within `wait_for_subscriber` seconds (math.inf: wait as
    long as it takes), at the start or whenever it goes away while streaming, is a
    `NoServiceError` naming the address, instead of streaming into the void; `on_wait()` is
    called once when a wait lasts more than a second (e.g. to say that it waits).

    The service refuses frames it cannot take (a stamp that does not increase, a wrong image
    size, ...) with a frame_rejected event on the robot's events key: counted by reason in
    `StreamStats.rejected`, and such a frame does not hold up the window.

    A frame whose files cannot be read (DatasetError) is logged, counted in
    `StreamStats.skipped` and not sent (seq counts the frames sent), as `mnemoslam run` skips
    it; it counts towards `max_frames` (frames taken from the dataset).

    `labels` also sends each frame's ``extras["labels"]`` (encoded like the depth: raw or PNG,
    both lossless) and the class table `classes` (default: the dataset's ``class_names`` if it
    has them, else `DEFAULT_CLASSES`) in the camera info. A dataset whose first frame carries no
    labels is a ValueError before any frame is sent.

    `localize` asks the service for localization only for this robot (camera info `localize`):
    it relocalizes in the stored map and writes nothing to it.
    """
    if rate is not None and not (isinstance(rate, (int, float)) and math.isfinite(rate) and rate > 0):
        raise ValueError(f"rate must be a positive number of frames per second, got {rate!r}")
    if max_frames is not None and (isinstance(max_frames, bool) or not isinstance(max_frames, int) or max_frames < 1):
        raise ValueError(f"max_frames must be a positive integer, got {max_frames!r}")
    keyspace = KeySpace(prefix)
    settings = settings if settings is not None else ZenohSettings.client()
    color, depth = resolve_encodings(color, depth, settings)
    kind = kind if kind is not None else getattr(dataset, "kind", None)
    total = _length(dataset)
    if max_frames is not None:
        total = max_frames if total is None else min(total, max_frames)
    frames = _frames(dataset)
    if labels:  # before the camera is announced: a service would admit the robot and wait for its frames
        ahead = []
        for item in frames:
            ahead.append(item)
            if not isinstance(item, DatasetError):
                if "labels" not in item.extras:
                    raise ValueError(f"--labels: the frames of {getattr(dataset, 'name', 'the dataset')} carry no "
                                     f"labels (frame.extras['labels']; synthetic datasets have them)")
                break
            if max_frames is not None and len(ahead) >= max_frames:
                break
        frames = itertools.chain(ahead, frames)
    own = session is None
    if own:
        session = open_session(settings)
    bar = None
    try:
        if labels and classes is None:
            classes = getattr(dataset, "class_names", None)
        streamer = CameraStreamer(session, robot, dataset.calibration, keyspace, color=color, depth=depth, kind=kind,
                                  labels=depth if labels else None, classes=classes, localize=localize)
        try:
            if wait_for_subscriber > 0 and not streamer.wait_for_subscriber(wait_for_subscriber, on_wait):
                if require_subscriber:
                    raise NoServiceError(_no_service(settings, session, streamer, wait_for_subscriber))
                log.warning("no subscriber on %s after %.1f s; streaming anyway", streamer.frame_key,
                            wait_for_subscriber)
            if progress:
                from tqdm import tqdm

                bar = tqdm(total=total, unit="frame", desc=f"{robot} -> {streamer.frame_key}", dynamic_ncols=True)
            t0 = time.perf_counter()
            sent = skipped = 0
            next_at, dropped = t0, 0  # when the next frame is due at `rate`; drops seen so far
            for frame in frames:
                if max_frames is not None and sent + skipped >= max_frames:
                    break
                if isinstance(frame, DatasetError):
                    log.error("frame %d skipped: %s", sent + skipped, frame)
                    skipped += 1
                    if bar is not None:
                        bar.update(1)
                    continue
                if require_subscriber and not streamer.has_subscriber \
                        and not streamer.wait_for_subscriber(wait_for_subscriber, on_wait):  # the service went away
                    raise NoServiceError(_no_service(settings, session, streamer, wait_for_subscriber, sent))
                if rate is None:
                    streamer.wait_for_room(sent, window, answer_timeout)
                else:
                    if adapt and streamer.service_dropped > dropped:
                        dropped = streamer.service_dropped
                        rate *= 0.9
                        log.warning("the service dropped %d frames: rate lowered to %.1f frames/s", dropped, rate)
                    delay = next_at - time.perf_counter()
                    if delay > 0:
                        time.sleep(delay)
                    next_at += 1.0 / rate  # late frames go at once (real time at that rate)
                streamer.send(frame, sent)
                sent += 1
                if bar is not None:
                    bar.update(1)
                    if sent % 10 == 0:
                        mbit = streamer.bytes_sent * 8 / 1e6 / max(time.perf_counter() - t0, 1e-9)
                        bar.set_postfix_str(f"{mbit:.0f} Mbit/s")
            seconds = time.perf_counter() - t0
            matched = streamer.has_subscriber
            if sent and matched:
                streamer.wait_for_room(sent - 1, 0, answer_timeout)
        finally:
            streamer.close()
    finally:
        if bar is not None:
            bar.close()
        if own:
            session.close()
    secs = max(seconds, 1e-9)
    return StreamStats(sent, streamer.bytes_sent, seconds, sent / secs, streamer.bytes_sent * 8 / 1e6 / secs, matched,
                       f"{color}/{depth}" + ("+labels" if labels else ""), streamer.answered,
                       streamer.service_dropped, rate, skipped, dict(streamer.rejected),
                       dict(streamer.rejected_detail), list(streamer.sessions_started),
                       sum(reason == "restarted" for _, reason in streamer.sessions_ended))


class NoServiceError(ConnectionError):
    """No service subscribes to the camera's frames (nothing listens at the address, or a
    service with another key prefix): `stream_dataset(require_subscriber=True)`."""


def _no_service(settings: ZenohSettings, session, streamer: CameraStreamer, waited: float, sent: int = 0) -> str:
    """Why no frame can reach a service: nothing listens at the address(es), or a peer is there
    but does not subscribe to the frame key."""
    where = ", ".join(settings.connect) or "the network (no --connect endpoint)"
    try:
        peers = list(session.info.peers_zid()) + list(session.info.routers_zid())
    except Exception:  # the session is closing
        peers = []
    if peers:
        why = (f"a Zenoh peer is connected at {where} but nothing subscribes to {streamer.frame_key} "
               f"(a service with another zenoh.prefix?)")
    else:
        why = f"nothing listens at {where}"
    when = f"after {sent} frame(s) the service went away: " if sent else ""
    return (f"{when}{why} (waited {waited:g} s); start `mnemoslam serve` first (or fix --connect / --prefix), "
            f"or pass --wait to wait for the service")


# ------------------------------------------------------------------------------------------
# CLI

def add_stream_arguments(parser):
    """Define the `mnemoslam stream` options on `parser` (an argparse (sub)parser) and set
    `func=stream_main`. Returns the parser."""
    from .cliargs import (
        DEPTH_REGISTRATION,
        DEPTH_REGISTRATION_HELP,
        FRAMES_HELP,
        TOPICS_HELP,
        frame_range_arg,
        positive_int,
    )
    from .datasets import FORMATS

    src = parser.add_mutually_exclusive_group(required=True)
    src.add_argument("dataset", nargs="?", help="dataset folder (TUM, EuRoC, KITTI, 7-Scenes), ROS bag (rosbag2 "
                                                "folder, .db3, .mcap, ROS 1 .bag) or synthetic[:loop|...]")
    src.add_argument("--camera", metavar="DEVICE_OR_VIDEO",
                     help="stream a camera device (index, e.g. 0) or a video file instead")
    parser.add_argument("--format", choices=list(FORMATS), help="override dataset layout detection")
    parser.add_argument("--topics", action="append", metavar="ROLE=TOPIC,...", help=TOPICS_HELP)
    parser.add_argument("--depth-registration", choices=list(DEPTH_REGISTRATION), default="auto",
                        help=DEPTH_REGISTRATION_HELP)
    parser.add_argument("--robot", default="robot1", help="robot id, [A-Za-z0-9_-]{1,64} (default robot1)")
    parser.add_argument("--rate", type=float, help="frames per second (default: as fast as the service takes them: "
                                                   "at most --window frames in flight, none dropped)")
    parser.add_argument("--window", type=int, default=4, help="frames in flight without --rate (default 4)")
    parser.add_argument("--adapt", action="store_true",
                        help="with --rate: lower the rate by 10%% each time the service reports dropped frames")
    parser.add_argument("--encoding", choices=["auto", "jpeg", "png", "raw"], default="auto",
                        help="colour image encoding (default auto: raw to a service on this host, else jpeg)")
    parser.add_argument("--depth-encoding", choices=["auto", "png", "raw"], default="auto",
                        help="depth (or stereo right image) encoding, both lossless (default auto: raw to a service "
                             "on this host, else png)")
    parser.add_argument("--labels", action="store_true",
                        help="also send each frame's per-pixel class ids (synthetic datasets: their exact ADE20K-32 "
                             "labels) and the class table in the camera info; a service with the default "
                             "semantics.source (auto) uses them instead of its model; labels travel lossless like the "
                             "depth (--depth-encoding). "
                             "An error for sources without labels (real datasets, --camera)")
    parser.add_argument("--localize", action="store_true",
                        help="localization only for this robot: the service relocalizes it in its stored map and "
                             "publishes its poses in the map's frame once it has, writing nothing to the map "
                             "(camera info `localize`; the service's memory.incremental: false does it for every "
                             "robot)")
    parser.add_argument("--connect", action="append", metavar="ENDPOINT",
                        help=f"zenoh endpoint of the service, repeatable (default {DEFAULT_ENDPOINT})")
    parser.add_argument("--mode", choices=list(MODES), default="peer", help="zenoh session mode (default peer)")
    parser.add_argument("--prefix", default=DEFAULT_PREFIX, help=f"key expression prefix (default {DEFAULT_PREFIX})")
    parser.add_argument("--max-frames", type=positive_int, metavar="N",
                        help="stop after this many frames (a positive integer; default: all)")
    parser.add_argument("--frames", type=frame_range_arg, metavar="START:END", help=FRAMES_HELP)
    parser.add_argument("--wait", type=_wait_seconds, nargs="?", const=math.inf, default=5.0, metavar="SECONDS",
                        help="wait for the service: without SECONDS as long as it takes (a camera started before "
                             "the service), else that long; without --wait 5 s, then `stream` fails naming the "
                             "address (also when the service goes away while streaming); 0: stream even with "
                             "nobody listening")
    parser.add_argument("--max-rejected", type=_share, default=0.5, metavar="SHARE",
                        help="exit 1 when the service refused at least this share of the frames sent, naming its "
                             "reason (default 0.5; 1: only when it refused them all)")
    parser.add_argument("-q", "--quiet", action="store_true",
                        help="no progress bar (there is one only when stderr is a terminal)")
    parser.set_defaults(func=stream_main)
    return parser


def _wait_seconds(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected seconds, got {text!r} (--wait alone waits as long as it "
                                         f"takes: put it after the dataset)") from None
    if not v >= 0:
        raise argparse.ArgumentTypeError(f"expected seconds >= 0, got {text!r}")
    return v


def _share(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if not 0 < v <= 1:
        raise argparse.ArgumentTypeError(f"expected a share in (0, 1], got {text!r}")
    return v


# what a refused frame's reason means for the one streaming it
_REJECT_HINTS = {
    "stamp_order": "stream under another --robot, or once the robot's slot is freed (service.idle_timeout)",
    "size_mismatch": "the images are not the size of the robot's calibration (its first camera info)",
    "no_calibration": "the service has no camera info of the robot (all its robot slots taken, or the info "
                      "did not arrive)",
}


def stream_main(args) -> int:
    """`mnemoslam stream`: returns 0 when all frames were sent, a subscriber was there and the
    service refused less than --max-rejected of them; 1 when nobody subscribed (--wait 0) or it
    refused that many (the reason on stderr). No service within --wait seconds is a
    NoServiceError (an OSError). DatasetError / ValueError / OSError propagate for the CLI.
    Frames that cannot be read are skipped (counted in the summary line)."""
    from .cliargs import want_progress

    camera = getattr(args, "camera", None)
    dataset_spec = getattr(args, "dataset", None)
    if (camera is None) == (dataset_spec is None):
        raise ValueError("give either a dataset or --camera (not both)")
    max_frames = getattr(args, "max_frames", None)
    if max_frames is not None and max_frames < 1:
        raise ValueError(f"--max-frames must be >= 1, got {max_frames}")
    labels = bool(getattr(args, "labels", False))
    if camera is not None:
        if getattr(args, "topics", None):
            raise ValueError("--topics applies to ROS bags only, not to --camera")
        if getattr(args, "frames", None) is not None:
            raise ValueError("--frames applies to datasets, not to --camera")
        if getattr(args, "depth_registration", None) not in (None, "auto"):
            raise ValueError("--depth-registration applies to 7-Scenes datasets, not to --camera")
        if labels:
            raise ValueError("--labels: a camera device / video file has no labels (only synthetic datasets do)")
        from .capture import CaptureSource

        dataset = CaptureSource(camera, max_frames=max_frames)
    else:
        from .cliargs import dataset_options
        from .datasets import open_dataset
        from .datasets.subrange import frame_range

        frames = getattr(args, "frames", None)
        dataset = frame_range(open_dataset(dataset_spec, getattr(args, "format", None), **dataset_options(args)),
                              frames, max_frames)
    connect = getattr(args, "connect", None) or [DEFAULT_ENDPOINT]
    settings = ZenohSettings(mode=getattr(args, "mode", "peer") or "peer", connect=list(connect))
    quiet = bool(getattr(args, "quiet", False))
    robot = getattr(args, "robot", "robot1")
    prefix = getattr(args, "prefix", DEFAULT_PREFIX)
    KeySpace(prefix).frame(robot)  # bad robot id / prefix: one-line error before connecting
    if not quiet:
        total = _length(dataset)
        print(f"stream: {dataset.name} ({total if total is not None else 'live'} frames) as {robot} "
              f"to {', '.join(connect)} on {KeySpace(prefix).frame(robot)}", file=sys.stderr)
    wait = getattr(args, "wait", 5.0)
    wait = 5.0 if wait is None else float(wait)
    key = KeySpace(prefix).frame(robot)

    def say_waiting() -> None:
        print(f"stream: waiting for the service at {', '.join(connect)} (nothing subscribes to {key} yet"
              + ("" if math.isinf(wait) else f"; up to {wait:g} s") + ")", file=sys.stderr, flush=True)

    try:
        stats = stream_dataset(dataset, robot, settings, rate=getattr(args, "rate", None),
                               color=getattr(args, "encoding", "auto"), depth=getattr(args, "depth_encoding", "auto"),
                               prefix=prefix, progress=want_progress(quiet), max_frames=max_frames,
                               wait_for_subscriber=wait, require_subscriber=wait > 0,
                               on_wait=say_waiting if wait > 5.0 else None,
                               window=max(1, int(getattr(args, "window", 4))),
                               adapt=bool(getattr(args, "adapt", False)),
                               labels=labels, localize=bool(getattr(args, "localize", False)))
    finally:
        close = getattr(dataset, "release", None)
        if close is not None:
            close()
    print(stats.line())
    if not stats.subscriber:
        return 1
    share = float(getattr(args, "max_rejected", 0.5) or 0.5)
    refused = stats.rejected_total
    if stats.frames and refused and refused >= share * stats.frames:
        top = max(stats.rejected, key=stats.rejected.get)
        detail = (stats.rejected_detail or {}).get(top) or ""
        hint = _REJECT_HINTS.get(top, "")
        print(f"stream: error: the service refused {refused} of {stats.frames} frames ({stats.reasons()}): "
              f"{top}" + (f": {detail}" if detail else "") + (f"; {hint}" if hint else ""), file=sys.stderr)
        return 1
    return 0


__all__ = ["CameraStreamer", "StreamStats", "NoServiceError", "stream_dataset", "add_stream_arguments", "stream_main"]
