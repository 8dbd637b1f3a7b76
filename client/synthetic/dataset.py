"""`SyntheticDataset`: the synthetic scene as a camera source (RGB-D + labels + ground truth)."""
from __future__ import annotations

import hashlib
import math
import os
import shutil
from pathlib import Path
from statistics import NormalDist

import cv2
import numpy as np

from ..datasets.base import Dataset
from ..kernel.frames import Calibration, DatasetError, Frame, PinholeCamera
from ..kernel.trajectory import Trajectory
from .blur import motion_blur
from .kinect import add_kinect_noise
from .person import Person, Walk
from .scene import SyntheticScene, get_scene
from .trajectories import TRAJECTORIES
from .trajectories import trajectory as make_path

# Kinect-like depth noise: sigma(z) = A + B (z - Z0)^2 metres
NOISE_A, NOISE_B, NOISE_Z0 = 0.0012, 0.0019, 0.4
MISSING_FRACTION = 0.02  # random missing depth pixels
MAX_INCIDENCE_DEG = 75.0  # no depth on surfaces seen at a more grazing angle
DEPTH_QUANTUM = 0.001  # metres
RGB_SIGMA = 2.0  # grey levels
NOISE_MODELS = ("axial", "kinect")  # noise=True is "axial"
# A folder where the frames rendered are kept and read back (`SyntheticDataset.frame`): set by the
# test suite (tests/conftest.py) for its session, so that the worker processes and the service and
# CLI processes they start render each frame once; unset (the default), every frame is rendered.
CACHE_ENV = "MNEMOSLAM_SYNTHETIC_CACHE"
CACHE_MIN_FREE = 10 << 30  # bytes left free on the cache's disk: no frame is written below that


def depth_sigma(z):
    """Standard deviation (m) of the simulated depth noise at depth z (m)."""
    return NOISE_A + NOISE_B * (np.asarray(z) - NOISE_Z0) ** 2


class SyntheticDataset(Dataset):
    """Frames rendered on demand along a named camera path through the synthetic scene.

    Frame k is at stamp k / rate, from 0 to the path's duration inclusive (so a closed path's
    last frame repeats the first pose). `ground_truth` holds the exact camera-to-world poses.
    Frames carry `extras={"labels": H×W uint8 class ids, "instances": H×W int32 ids}`.
    With `noise=True` (or "axial") depth gets Kinect-like axial noise (see `depth_sigma`), 2 %
    random holes, holes on surfaces seen at > 75° incidence and 1 mm quantisation; with
    `noise="kinect"` the Kinect's disparity model (`kinect.py`: σ_z = 1.5e-3·z², disparity
    steps, holes at depth edges, grazing angles and in blotches, 0.45–5 m). Either way RGB gets
    σ = 2 Gaussian noise, all deterministic by (seed, frame index). `noise=False` (or "none"):
    exact depth and colour.
    With `exposure` > 0 (seconds) the colour image is blurred by the camera's motion over an
    exposure centred on the frame's stamp (`blur.py`); depth, labels and the ground truth are
    those of the stamp (mid-exposure). `noise=None` / `exposure=None` take the trajectory's
    defaults (`PathSpec.noise` / `exposure`: off, except "fastrot": "kinect" and 20 ms).
    With `person=True` a person walks through the scene (`person.py`: a textured box labelled
    `person`, class 13, its own instance id) to and fro along the trajectory's `PathSpec.person`
    walk (the loop has one), or along a `Walk` given as `person`; it is drawn into colour, depth,
    labels and instances before blur and noise. Off by default: the frames are then exactly
    those of the static scene.
    """

    format = "synthetic"

    def __init__(self, trajectory: str = "loop", rate: float = 30.0, width: int = 640, height: int = 480,
                 fx: float = 525.0, noise: bool | str | None = None, seed: int = 0, max_frames: int | None = None,
                 duration: float | None = None, scene: SyntheticScene | None = None, frames: int | None = None,
                 exposure: float | None = None, person: bool | Walk | None = False):
        if not (isinstance(rate, (int, float)) and rate > 0):
            raise DatasetError(f"synthetic: rate must be > 0 Hz, got {rate!r}")
        if int(width) < 8 or int(height) < 8:
            raise DatasetError(f"synthetic: image size {width}x{height} is too small")
        if not fx > 0:
            raise DatasetError(f"synthetic: fx must be > 0, got {fx!r}")
        self.trajectory = str(trajectory)
        self.path = make_path(self.trajectory, duration)  # DatasetError for unknown names
        self.rate = float(rate)
        spec = TRAJECTORIES[self.trajectory]
        self.noise = _noise_model(spec.noise if noise is None else noise)
        self.exposure = float(spec.exposure if exposure is None else exposure)
        if not (math.isfinite(self.exposure) and 0.0 <= self.exposure <= 1.0):
            raise DatasetError(f"synthetic: exposure must be 0..1 s, got {exposure!r}")
        self.seed = int(seed)
        self.scene = scene if scene is not None else get_scene(self.seed)
        self.person = self._person(person, spec.person)
        w, h = int(width), int(height)
        self.camera = PinholeCamera(float(fx), float(fx), (w - 1) / 2.0, (h - 1) / 2.0, w, h)
        self.name = f"synthetic-{self.trajectory}"
        self.calibration = Calibration(self.camera, None, depth_scale=1000.0)
        n = int(math.floor(self.path.duration * self.rate + 1e-9)) + 1
        limit = max_frames if max_frames is not None else frames
        if limit is not None:
            n = max(0, min(n, int(limit)))
        self.stamps = np.arange(n) / self.rate
        self.ground_truth = Trajectory(self.stamps, self.path(self.stamps) if n else np.zeros((0, 4, 4)))
        self._cache_key = None  # the frames' folder name in the CACHE_ENV folder; None: the scene is not the seed's
        if scene is None or scene is get_scene(self.seed):
            walk = None if self.person is None else self.person.walk
            what = (self.trajectory, self.path.duration, self.rate, w, h, float(fx), self.noise, self.exposure,
                    self.seed, walk)
            self._cache_key = hashlib.sha1(repr(what).encode()).hexdigest()[:20]

    def __len__(self) -> int:
        return len(self.ground_truth)

    def __repr__(self) -> str:
        return (f"SyntheticDataset({self.trajectory!r}, {len(self)} frames @ {self.rate:g} Hz, "
                f"{self.camera.width}x{self.camera.height}, noise={self.noise}, exposure={self.exposure:g}, "
                f"seed={self.seed}{', person' if self.person is not None else ''})")

    def pose(self, i: int) -> np.ndarray:
        return self.ground_truth.poses[i]

    def frame(self, i: int) -> Frame:
        if not 0 <= i < len(self):
            raise IndexError(f"{self.name}: frame {i} out of range 0..{len(self) - 1}")
        folder = os.environ.get(CACHE_ENV)
        if not folder or self._cache_key is None:
            return self._render(i)
        path = Path(folder) / self._cache_key / f"{i}.frame"
        f = self._read(path, i)
        if f is not None:
            return f
        f = self._render(i)
        _keep(path, f)
        return f

    def _read(self, path: Path, i: int) -> Frame | None:
        """Frame i as `_keep` wrote it to `path`, or None (not there, or not whole)."""
        try:
            with open(path, "rb") as src:
                buf = bytearray(src.read())
        except OSError:
            return None
        h, w = self.camera.height, self.camera.width
        sizes = (h * w * 3, h * w * 4, h * w)
        wide = len(buf) == sum(sizes) + h * w * 4  # instances as int32, else as uint8
        if len(buf) != sum(sizes) + h * w * (4 if wide else 1):
            return None
        image = np.frombuffer(buf, np.uint8, sizes[0]).reshape(h, w, 3)
        depth = np.frombuffer(buf, np.float32, h * w, sizes[0]).reshape(h, w).copy()  # (aligned)
        labels = np.frombuffer(buf, np.uint8, h * w, sizes[0] + sizes[1]).reshape(h, w)
        at = sum(sizes)
        instances = (np.frombuffer(buf, np.int32, h * w, at).copy() if wide
                     else np.frombuffer(buf, np.uint8, h * w, at).astype(np.int32)).reshape(h, w)
        return Frame(index=i, stamp=float(self.ground_truth.stamps[i]), image=image, depth=depth,
                     source=f"synthetic:{self.trajectory}#{i}", extras={"labels": labels, "instances": instances})

    def _render(self, i: int) -> Frame:
        pose = self.ground_truth.poses[i]
        r = self.scene.render(pose, self.camera, incidence=bool(self.noise))
        if self.person is not None:
            r = self.person.composite(r, pose, self.camera, float(self.ground_truth.stamps[i]))
        rgb, depth = r.rgb, r.depth
        if self.exposure > 0:
            t = float(self.ground_truth.stamps[i])
            start, end = self.path(np.array([t - self.exposure / 2, t + self.exposure / 2]))
            rgb = motion_blur(rgb, depth, self.camera, pose, start, end)
        if self.noise:
            rng = np.random.default_rng([self.seed, i, 0x5EED])
            if self.noise == "kinect":
                depth = add_kinect_noise(depth, r.incidence, rng)
            else:
                depth = add_depth_noise(depth, r.incidence, rng)
            rgb = add_rgb_noise(rgb, rng)
        return Frame(index=i, stamp=float(self.ground_truth.stamps[i]), image=rgb, depth=depth,
                     source=f"synthetic:{self.trajectory}#{i}",
                     extras={"labels": r.labels, "instances": r.instances})

    def _person(self, person, default: Walk | None) -> Person | None:
        """The walking person of `person` (False / None: none; True: the path's walk; a `Walk`)."""
        if person is None or person is False:
            return None
        walk = default if person is True else person
        if walk is None:
            raise DatasetError(f"synthetic: the {self.trajectory!r} path has no person walk; pass person=Walk(...)")
        if not isinstance(walk, Walk):
            raise DatasetError(f"synthetic: person must be true, false or a Walk, got {person!r}")
        walk = Walk(tuple(map(float, walk.start)), tuple(map(float, walk.end)), float(walk.speed), float(walk.phase))
        instance = 1 + max((o.instance_id for o in self.scene.objects), default=0)
        return Person(walk, self.seed, instance, self.scene.quads.detail)


def _keep(path: Path, f: Frame) -> None:
    """Write frame `f` to the cache file `path` (colour, depth, labels, instance ids as uint8
    when they fit, else int32: raw, one after the other) whole or not at all: a file of its own,
    renamed into place (concurrent writers of the same frame write the same bytes). Nothing when
    the disk has less than CACHE_MIN_FREE bytes free, or on any error (the frame is rendered again)."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        if shutil.disk_usage(path.parent).free < CACHE_MIN_FREE:
            return
        instances = f.extras["instances"]
        if instances.size and 0 <= instances.min() and instances.max() < 256:
            instances = instances.astype(np.uint8)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        with open(tmp, "wb") as out:
            for a in (f.image, f.depth, f.extras["labels"], instances):
                out.write(np.ascontiguousarray(a).tobytes())
        os.replace(tmp, path)
    except OSError:
        pass


def _noise_model(noise) -> str | bool:
    """False (no noise) or the name of a noise model: True means "axial"."""
    if noise is False or noise is None or noise == "none":
        return False
    if noise is True or noise == "axial":
        return "axial"
    if noise in NOISE_MODELS:
        return noise
    raise DatasetError(f"synthetic: unknown noise {noise!r}; known: none, {', '.join(NOISE_MODELS)} (true = axial)")


def add_depth_noise(depth: np.ndarray, cos_incidence: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Kinect-like degradation of a clean depth image (metres, 0 = invalid)."""
    z = depth.astype(np.float32)
    valid = z > 0
    sigma = (NOISE_A + NOISE_B * (z - NOISE_Z0) ** 2).astype(np.float32)
    out = z + rng.standard_normal(z.shape, dtype=np.float32) * sigma
    out = np.round(out / DEPTH_QUANTUM) * DEPTH_QUANTUM
    drop = ~valid | (out <= 0)
    drop |= rng.random(z.shape, dtype=np.float32) < MISSING_FRACTION
    drop |= cos_incidence < math.cos(math.radians(MAX_INCIDENCE_DEG))
    out[drop] = 0.0
    return out.astype(np.float32)


_GAUSS_TABLES: dict = {}


def _gauss_table(sigma: float) -> np.ndarray:
    """round(sigma * N(0,1)) by inverse CDF over 256 equiprobable bins (int16)."""
    t = _GAUSS_TABLES.get(sigma)
    if t is None:
        nd = NormalDist(0.0, sigma)
        t = _GAUSS_TABLES[sigma] = np.array([round(nd.inv_cdf((k + 0.5) / 256)) for k in range(256)], np.int16)
    return t


def add_rgb_noise(rgb: np.ndarray, rng: np.random.Generator, sigma: float = RGB_SIGMA) -> np.ndarray:
    """Additive Gaussian noise (sigma grey levels, integer-rounded, tails cut at ±2.7 sigma)."""
    idx = np.frombuffer(rng.bytes(rgb.size), np.uint8).reshape(rgb.shape)
    noise = np.take(_gauss_table(float(sigma)), idx)
    return cv2.add(rgb, noise, dtype=cv2.CV_8U)
