"""Microsoft 7-Scenes player: a `seq-XX` folder of `frame-XXXXXX.color.{png,jpg}`,
`frame-XXXXXX.depth.png` (uint16 millimetres, 65535 = invalid) and `frame-XXXXXX.pose.txt`
(4x4 camera-to-world), or a scene folder (its first `seq-XX` in sorted order is played).

There are no timestamps: frame number k is stamped k/30 s. `camera-intrinsics.txt` in the
sequence folder or its parent (default 585, 585, 320, 240: Microsoft's 7-Scenes) holds the
intrinsics the depth images were taken with.

Microsoft's 7-Scenes data (a Kinect v1) is not registered: its depth comes from the depth (IR)
camera, whose intrinsics `camera-intrinsics.txt` holds (585 px), and its ground truth
(KinectFusion) is the depth camera's pose. For that data the player registers each depth image
into the colour camera (`registration.DepthRegistration`) with the Kinect v1's nominal colour
intrinsics (525, 525, 319.5, 239.5) and its colour camera 2.5 cm along the depth camera's +x,
and delivers the colour camera's calibration and the ground truth moved to the colour camera by
the same extrinsic. Fitted without ground truth on this data (depth discontinuities against
colour edges, 20 frames of redkitchen): fx 526, fy 531, baseline 2.52 cm, principal point within
1.4 px.

Which sequences are registered (`register`): by default (`None`) those whose intrinsics are the
Kinect v1 depth camera's (585, 585, 320, 240 at 640 px wide, scaled to the image width, within
1 px) or that have no `camera-intrinsics.txt`, i.e. Microsoft's data; any other sequence in this
layout (another RGB-D sensor, depth already registered to colour, its own
`camera-intrinsics.txt`) plays as given, with its own intrinsics. `register=True` registers
whatever the intrinsics, `register=False` never does (the CLI's `--depth-registration on|off`).
One INFO line says which the player did.
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..kernel.frames import Calibration, DatasetError, Frame
from ..kernel.trajectory import Trajectory
from ._io import check_index, frame_count, image_size, numbers, pinhole, read_color, read_depth, read_rows
from .base import Dataset
from .registration import DepthRegistration

log = logging.getLogger(__name__)

DEPTH_SCALE = 1000.0
INVALID_DEPTH = 65535
FPS = 30.0
KINECT_DEPTH_INTRINSICS = (585.0, 585.0, 320.0, 240.0)  # Microsoft 7-Scenes: the Kinect v1 depth camera, 640×480
DEFAULT_INTRINSICS = KINECT_DEPTH_INTRINSICS
KINECT_COLOUR_INTRINSICS = (525.0, 525.0, 319.5, 239.5)  # Kinect v1 colour camera, nominal
KINECT_COLOUR_OFFSET = (0.025, 0.0, 0.0)  # m, the colour camera's centre in the depth camera's frame


def read_intrinsics(seq: Path) -> tuple[tuple[float, float, float, float], Path | None]:
    """(fx, fy, cx, cy) from camera-intrinsics.txt (a 3x3 matrix) in `seq` or its parent, and
    that file; the 7-Scenes default and None when there is none."""
    for path in (seq / "camera-intrinsics.txt", seq.parent / "camera-intrinsics.txt"):
        if path.is_file():
            K = numbers(path, read_rows(path, 3))
            if K.shape != (3, 3):
                raise DatasetError(f"{path}: expected a 3x3 matrix, got shape {K.shape}")
            return (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])), path
    return DEFAULT_INTRINSICS, None


def is_kinect_depth(intrinsics: tuple[float, float, float, float], width: int) -> bool:
    """Whether (fx, fy, cx, cy) of images `width` pixels wide are the Kinect v1 depth camera's
    of Microsoft's 7-Scenes (585, 585, 320, 240 at 640 px wide, within 1 px there)."""
    at_640 = np.asarray(intrinsics, float) * (640.0 / width)
    return bool(np.allclose(at_640, KINECT_DEPTH_INTRINSICS, rtol=0.0, atol=1.0))


def read_poses(paths: list[Path]) -> tuple[np.ndarray, np.ndarray]:
    """4x4 pose files as (poses (N, 4, 4), valid (N,)); a missing file or one with non-finite
    values is invalid (7-Scenes has some -inf poses), a malformed one raises."""
    rows = []
    for path in paths:
        try:
            fields = path.read_text().split()
        except FileNotFoundError:
            fields = ["nan"] * 16
        except (OSError, UnicodeDecodeError) as e:
            raise DatasetError(f"{path}: cannot read pose ({e})") from None
        if len(fields) != 16:
            raise DatasetError(f"{path}: expected 16 numbers (a 4x4 pose), got {len(fields)}")
        rows.append(numbers(path, fields))
    poses = np.array(rows).reshape(-1, 4, 4)
    return poses, np.isfinite(poses).all(axis=(1, 2))


class SevenScenesDataset(Dataset):
    """One 7-Scenes sequence."""

    format = "7scenes"

    def __init__(self, path: Path, *, max_frames: int | None = None, register: bool | None = None):
        path = Path(path)
        seq = path
        if not any(path.glob("frame-*.color.*")):
            seqs = sorted(p for p in path.glob("seq-*") if p.is_dir())
            if not seqs:
                raise DatasetError(f"{path}: no frame-*.color.* images and no seq-XX folders")
            seq = seqs[0]
            log.info("%s: playing %s (first of %d sequences)", path, seq.name, len(seqs))
        self.path, self.name = seq, f"{seq.resolve().parent.name}/{seq.name}"
        colour = sorted(p for p in seq.glob("frame-*.color.*") if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
        n = frame_count(len(colour), max_frames, seq)
        self._colour = colour[:n]
        stems = [p.name.split(".")[0] for p in self._colour]  # frame-XXXXXX
        self._depth = [seq / f"{s}.depth.png" for s in stems]
        self.stamps = numbers(seq, [s[len("frame-"):] for s in stems]) / FPS
        w, h = image_size(self._colour[0])
        self._shape = (h, w)
        intrinsics, source = read_intrinsics(seq)
        depth_camera = pinhole(*intrinsics, w, h)
        given = (f"{source.name} {tuple(round(v, 3) for v in intrinsics)}" if source else
                 f"no camera-intrinsics.txt (the 7-Scenes default {intrinsics})")
        if register is None:  # Microsoft's 7-Scenes data only
            register = source is None or is_kinect_depth(intrinsics, w)
            why = (f"{given}: the Kinect v1 depth camera's (Microsoft 7-Scenes; --depth-registration off plays it "
                   "as given)" if register else f"{given}: not the Kinect v1 depth camera's (585 px), so played as "
                   "given (--depth-registration on registers it)")
        else:
            why = f"{given}; depth registration {'on' if register else 'off'} as asked"
        self.registration = None
        if register:
            T_colour_depth = np.eye(4)
            T_colour_depth[:3, 3] = -np.asarray(KINECT_COLOUR_OFFSET)
            colour_camera = pinhole(*KINECT_COLOUR_INTRINSICS, 640, 480).scaled(w / 640)  # nominal at 640×480
            self.registration = DepthRegistration(depth_camera, colour_camera, T_colour_depth)
            log.info("%s: depth registered into the Kinect v1 colour camera (fx %.1f px, %.1f cm baseline); %s",
                     seq, colour_camera.fx, 100 * KINECT_COLOUR_OFFSET[0], why)
        else:
            log.info("%s: colour and depth as registered, with their own intrinsics; %s", seq, why)
        camera = self.registration.colour_camera if register else depth_camera
        self.calibration = Calibration(camera, None, DEPTH_SCALE)
        poses, valid = read_poses([seq / f"{s}.pose.txt" for s in stems])
        if not valid.all():
            log.info("%s: %d of %d poses missing or non-finite, left out of the ground truth", seq, (~valid).sum(), n)
        if register:
            poses[valid] = self.registration.colour_from_depth_poses(poses[valid])
        self.ground_truth = Trajectory(self.stamps[valid], poses[valid])

    def __len__(self) -> int:
        return len(self.stamps)

    def frame(self, i: int) -> Frame:
        i = check_index(i, len(self))
        colour, depth = self._colour[i], self._depth[i]
        d = read_depth(depth, DEPTH_SCALE, INVALID_DEPTH, self._shape)
        if self.registration is not None:
            d = self.registration.register(d)
        return Frame(i, float(self.stamps[i]), read_color(colour, self._shape), depth=d, source=f"{colour}, {depth}")
