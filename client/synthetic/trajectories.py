"""Camera paths through the synthetic scene (handheld-like: ~1.5 m high, 0.3–0.6 m/s).

`trajectory(name, duration=None)` returns a `CameraPath`: call it with a time (or an array of
times) in seconds to get 4×4 camera-to-world poses. Paths are uniform cubic B-splines through
hand-placed control points in the free space of the scene (see `scene.py` for the layout),
walked at a speed that drops in curves; the camera looks along the walking direction
(smoothed like a hand would) plus a per-path offset, with a slight downward pitch, small
roll, sway and a 1 cm walking bob. Closed paths ("loop", "figure8") return exactly to their
start pose at t = duration: every periodic term has a whole number of cycles.

`duration` rescales time: the same path is walked faster or slower.

"fastrot" is not a walk but a handheld look-around (issue 12): the camera drifts slowly
(0.11 m/s) round a small loop in the middle of the living room while it is swung about yaw,
pitch and roll with sinusoidal angle rates (`PathSpec.spin`), its mean heading making one full
turn in 30 s. The Euler-angle peaks (52, 54, 35.5°/s) are set so that the angular velocity
about each of the camera's own axes (x: pitch, y: yaw, z: roll) peaks at 60°/s; the three
together reach 81°/s (mean 53°/s). Its frames come with motion blur and the Kinect
disparity noise model by default (`PathSpec.noise` / `exposure`, see `dataset.py`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..kernel.frames import DatasetError
from ..kernel.geometry import look_at, make_pose
from .person import Walk

EYE_HEIGHT = 1.5


@dataclass(frozen=True)
class PathSpec:
    points: tuple  # control points (x, y)
    duration: float  # seconds (default)
    closed: bool
    yaw_offset: float = 0.0  # degrees added to the walking direction
    pitch: float = -6.0  # degrees (negative = looking down)
    sway: float = 4.0  # degrees of slow yaw sway
    description: str = ""
    # Handheld fast rotation instead of looking along the walking direction: for yaw, pitch
    # and roll, (peak angular velocity in deg/s, whole cycles over the path). Each angle's
    # rate is peak·sin(2π·cycles·t/duration) (0 at the start and the end), swinging round
    # `pitch`, 0 (roll) and the mean heading, which starts at yaw_offset and makes
    # `spin_turns` full turns (its rate counts in the yaw peak).
    spin: tuple = ()
    spin_turns: float = 0.0
    # what the dataset gives its frames unless told otherwise (SyntheticDataset noise / exposure)
    noise: bool | str = False
    exposure: float = 0.0  # s; > 0: colour images blurred by the motion during the exposure
    # where the walking person (`SyntheticDataset(person=True)`, `person.py`) walks on this path:
    # in view for much of it, never nearer than 1 m to the camera; None: the path has none
    person: Walk | None = None


# Doorway centres: living<->office (6.05, 2.5), living<->hall (2.6, 5.05), office<->hall (8.6, 5.05).
_FIG8_LAP = (
    (6.05, 2.5), (6.6, 2.75), (7.3, 3.45), (8.3, 3.95), (9.6, 3.85), (10.25, 3.0), (10.25, 1.4), (9.5, 0.6),
    (8.0, 0.6), (7.05, 1.5), (6.6, 2.25),
    (6.05, 2.5), (5.5, 2.75), (4.8, 3.5), (3.8, 3.95), (2.85, 3.45), (2.75, 2.4), (3.2, 1.45), (4.3, 1.25),
    (5.05, 1.75), (5.5, 2.25),
)


def _second_lap(points, amp=0.08):
    """The same control points nudged a little (a person never walks the same line twice)."""
    out = []
    for k, (x, y) in enumerate(points):
        if k in (0, 11):  # keep the doorway crossings exact
            out.append((x, y))
        else:
            out.append((x + amp * math.sin(1.7 * k), y + amp * math.cos(2.3 * k)))
    return tuple(out)


TRAJECTORIES: dict[str, PathSpec] = {
    "loop": PathSpec(
        points=((3.6, 2.5), (4.8, 2.5), (5.5, 2.5), (6.05, 2.5), (6.6, 2.5), (7.2, 1.9), (7.6, 0.8), (9.0, 0.6),
                (10.0, 0.9), (10.05, 2.2), (9.9, 3.75), (9.1, 4.2), (8.6, 4.55), (8.6, 5.05), (8.6, 5.55),
                (8.1, 6.25), (7.0, 6.25), (5.0, 6.25), (3.4, 6.2), (2.6, 5.6), (2.6, 5.05), (2.6, 4.5),
                (2.9, 3.2)),
        duration=60.0, closed=True,
        description="living room -> office (around the dining table) -> hall -> living room, back to the start pose",
        # across the office behind the dining table's north chairs, seen through the doorway from the
        # start (every frame of the first 6 s) and again from the office: ~50 of 300 frames at 5 Hz
        person=Walk((6.6, 3.45), (9.9, 3.45), speed=0.5, phase=11.0)),
    "figure8": PathSpec(
        points=_FIG8_LAP + _second_lap(_FIG8_LAP), duration=90.0, closed=True,
        description="two laps of a figure eight: around the living room and around the dining table, "
                    "crossing in the living/office doorway"),
    "walk_a": PathSpec(
        points=((1.6, 3.4), (2.8, 3.5), (4.2, 3.3), (5.2, 2.6), (5.6, 2.5), (6.05, 2.5), (6.5, 2.5), (7.2, 3.3),
                (7.9, 4.05), (8.6, 4.5), (8.6, 5.05), (8.6, 5.6), (8.1, 6.25), (7.0, 6.3), (5.8, 6.3)),
        duration=36.0, closed=False,
        description="living room (west) -> office (north side) -> hall, walking west"),
    "walk_b": PathSpec(
        points=((1.0, 6.3), (2.0, 6.3), (2.6, 5.7), (2.6, 5.05), (2.6, 4.4), (3.2, 3.2), (4.3, 2.6), (5.5, 2.5),
                (6.05, 2.5), (6.6, 2.5), (7.2, 1.6), (7.8, 0.8), (9.2, 0.65), (10.0, 1.1), (10.1, 2.3)),
        duration=38.0, closed=False,
        description="hall (west end) -> living room -> office (south side)"),
    "straight": PathSpec(
        points=((1.0, 6.1), (4.0, 6.1), (7.0, 6.1), (10.0, 6.1)),
        duration=24.0, closed=False, yaw_offset=55.0, pitch=-3.0, sway=2.0,
        description="straight along the hall's north wall and its six identical posters, no revisit"),
    "fastrot": PathSpec(
        points=((3.0, 2.3), (3.6, 2.35), (3.85, 2.85), (3.4, 3.25), (2.85, 2.95)),
        duration=30.0, closed=True, yaw_offset=-90.0, pitch=-5.0, sway=0.0,
        spin=((52.0, 8), (54.0, 11), (35.5, 14)), spin_turns=1.0, noise="kinect", exposure=0.02,
        description="handheld look-around in the living room: roll, pitch and yaw swung at up to 60 deg/s each, "
                    "one full turn, slow drift round a 0.9 m loop; motion blur and Kinect depth noise"),
}


def _bspline(points: np.ndarray, closed: bool, per_seg: int = 200) -> np.ndarray:
    """Dense samples of a uniform cubic B-spline (clamped ends when open)."""
    P = np.asarray(points, float)
    if closed:
        ext = np.concatenate([P[-1:], P, P[:2]])  # segments i: P[i-1..i+2], i = 0..n-1
        nseg = len(P)
    else:
        ext = np.concatenate([P[:1], P[:1], P, P[-1:], P[-1:]])
        nseg = len(P) + 1
    t = np.linspace(0, 1, per_seg, endpoint=False)
    b0 = (1 - t) ** 3 / 6
    b1 = (3 * t ** 3 - 6 * t ** 2 + 4) / 6
    b2 = (-3 * t ** 3 + 3 * t ** 2 + 3 * t + 1) / 6
    b3 = t ** 3 / 6
    segs = [b0[:, None] * ext[i] + b1[:, None] * ext[i + 1] + b2[:, None] * ext[i + 2] + b3[:, None] * ext[i + 3]
            for i in range(nseg)]
    out = np.concatenate(segs)
    end = ext[0] / 6 + 4 * ext[1] / 6 + ext[2] / 6 if closed else ext[-1]
    return np.concatenate([out, end[None]])


def _gauss_smooth(x: np.ndarray, sigma: float, periodic: bool) -> np.ndarray:
    if sigma <= 0:
        return x
    r = int(4 * sigma) + 1
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
    k /= k.sum()
    if periodic:
        xp = np.concatenate([x[-r - 1:-1], x, x[1:r + 1]])  # x[0] == x[-1] (same instant)
    else:
        xp = np.concatenate([np.full(r, x[0]), x, np.full(r, x[-1])])
    return np.convolve(xp, k, mode="valid")


@dataclass
class CameraPath:
    """Camera-to-world poses as a function of time (seconds, 0..duration)."""

    name: str
    duration: float
    closed: bool
    description: str = ""
    _t: np.ndarray = field(default=None, repr=False)
    _xyz: np.ndarray = field(default=None, repr=False)
    _ypr: np.ndarray = field(default=None, repr=False)

    def __call__(self, t):
        """Pose(s) at time(s) t: (4, 4) for a scalar, (N, 4, 4) for an array. Times are
        clamped to [0, duration] (the camera rests at the ends)."""
        ts = np.asarray(t, float)
        scalar = ts.ndim == 0
        ts = np.clip(ts.reshape(-1), 0.0, self.duration)
        xyz = np.stack([np.interp(ts, self._t, self._xyz[:, k]) for k in range(3)], 1)
        ypr = np.stack([np.interp(ts, self._t, self._ypr[:, k]) for k in range(3)], 1)
        poses = np.stack([_pose(p, a) for p, a in zip(xyz, ypr)])
        return poses[0] if scalar else poses

    pose = __call__

    def positions(self, t) -> np.ndarray:
        """Camera centres (N, 3) at times t (cheaper than full poses)."""
        ts = np.clip(np.asarray(t, float).reshape(-1), 0.0, self.duration)
        return np.stack([np.interp(ts, self._t, self._xyz[:, k]) for k in range(3)], 1)


def _pose(p, ypr) -> np.ndarray:
    yaw, pitch, roll = ypr
    f = np.array([math.cos(yaw) * math.cos(pitch), math.sin(yaw) * math.cos(pitch), math.sin(pitch)])
    T = look_at(p, p + f)
    if roll:
        c, s = math.cos(roll), math.sin(roll)
        Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        T = make_pose(T[:3, :3] @ Rz, p)
    return T


def _build(name: str, spec: PathSpec, duration: float, hz: float = 200.0) -> CameraPath:
    closed = spec.closed
    xy = _bspline(np.array(spec.points), closed)
    seg = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    L = s[-1]
    # curvature -> slower in curves
    if closed:  # periodic central differences: the end tangent equals the start tangent
        q = xy[:-1]
        d1 = np.roll(q, -1, 0) - np.roll(q, 1, 0)
        d1 = np.concatenate([d1, d1[:1]])
    else:
        d1 = np.gradient(xy, s, axis=0)
    heading_s = np.unwrap(np.arctan2(d1[:, 1], d1[:, 0]))
    kappa = np.abs(np.gradient(heading_s, s))
    kappa = _gauss_smooth(kappa, 20, closed)
    v = 1.0 / (1.0 + 0.7 * kappa)
    if not closed:  # start and stop at rest, accelerating gently
        a = 0.35 / 0.45
        v = np.minimum(v, np.sqrt(0.02 + 2 * a * s))
        v = np.minimum(v, np.sqrt(0.02 + 2 * a * (L - s)))
    dt = seg / (0.5 * (v[1:] + v[:-1]))
    tt = np.concatenate([[0.0], np.cumsum(dt)])
    tt *= duration / tt[-1]
    # uniform time grid
    n = int(round(duration * hz)) + 1
    t = np.linspace(0.0, duration, n)
    st = np.interp(t, tt, s)
    x = np.interp(st, s, xy[:, 0])
    y = np.interp(st, s, xy[:, 1])
    yaw = np.interp(st, s, heading_s)
    # a hand follows the walking direction with some lag/smoothing
    if closed:
        turns = yaw[-1] - yaw[0]
        trend = turns * t / duration
        yaw = _gauss_smooth(yaw - trend, 0.35 * hz, True) + trend
    else:
        yaw = _gauss_smooth(yaw, 0.35 * hz, False)

    def periodic(freq_hz):  # the nearest frequency with whole cycles over the path (closed)
        return max(1, round(freq_hz * duration)) / duration if closed else freq_hz

    f_sway, f_pitch, f_roll, f_step = periodic(0.11), periodic(0.07), periodic(0.13), periodic(1.8)
    if spec.spin:
        yaw, pitch, roll = _spin(spec, t, duration)
        z = EYE_HEIGHT + 0.01 * np.sin(2 * np.pi * f_step * t) + 0.02 * np.sin(2 * np.pi * f_pitch * t)
        if closed:
            x[-1], y[-1] = x[0], y[0]
        return CameraPath(name, float(duration), closed, spec.description, t,
                          np.stack([x, y, z], 1), np.stack([yaw, pitch, roll], 1))
    yaw = yaw + math.radians(spec.yaw_offset) + math.radians(spec.sway) * np.sin(2 * np.pi * f_sway * t)
    pitch = math.radians(spec.pitch) + math.radians(2.0) * np.sin(2 * np.pi * f_pitch * t + 0.5)
    roll = math.radians(1.2) * np.sin(2 * np.pi * f_roll * t + 1.0)
    z = EYE_HEIGHT + 0.01 * np.sin(2 * np.pi * f_step * t) + 0.02 * np.sin(2 * np.pi * f_pitch * t)
    if not closed:  # the bob fades in/out with the walking speed
        speed = np.gradient(st, t)
        z = EYE_HEIGHT + (z - EYE_HEIGHT) * np.clip(speed / 0.3, 0, 1)
    if closed:  # exact closure (interp / float noise)
        x[-1], y[-1] = x[0], y[0]
    return CameraPath(name, float(duration), closed, spec.description, t,
                      np.stack([x, y, z], 1), np.stack([yaw, pitch, roll], 1))


def _spin(spec: PathSpec, t: np.ndarray, duration: float):
    """Yaw, pitch, roll (radians) of a `spin` path: each angle's rate is
    peak·sin(2π·f·t) with f = cycles / duration, so the angle swings round its base as
    base − peak/(2πf)·cos 2πft, at rest at an extreme at both ends; the heading's full
    turns take part of the yaw peak (the swing's amplitude is what is left of it)."""
    base_rate = 360.0 * spec.spin_turns / duration  # deg/s
    base = (np.radians(spec.yaw_offset + base_rate * t), np.full_like(t, math.radians(spec.pitch)), np.zeros_like(t))
    out = []
    for k, ((peak, cycles), b) in enumerate(zip(spec.spin, base)):
        if k == 0:
            peak = peak - abs(base_rate)
        f = cycles / duration
        out.append(b - math.radians(peak) / (2 * np.pi * f) * np.cos(2 * np.pi * f * t))
    return out


_CACHE: dict = {}


def trajectory(name: str, duration: float | None = None) -> CameraPath:
    """The named camera path (see TRAJECTORIES), walked in `duration` seconds (default: its own)."""
    spec = TRAJECTORIES.get(name)
    if spec is None:
        raise DatasetError(f"unknown synthetic trajectory {name!r}; known: {', '.join(TRAJECTORIES)}")
    d = float(spec.duration if duration is None else duration)
    if not d > 0:
        raise DatasetError(f"synthetic trajectory duration must be > 0 seconds, got {duration!r}")
    key = (name, d)
    if key not in _CACHE:
        if len(_CACHE) > 16:
            _CACHE.clear()
        _CACHE[key] = _build(name, spec, d)
    return _CACHE[key]
