"""The local occupancy grid of one keyframe, from its depth image (RTAB-Map's LocalGridMaker
with `Grid/Sensor` = depth; written from its description, docs/grid.md).

A local grid lives in a frame L attached to the camera: its z axis is up (perpendicular to the
floor), its origin the floor point under the camera, its x axis the camera's viewing direction
turned horizontal. `T_cam_local` (camera ← L) holds both the up direction and the camera's
height, so the map places the grid with the keyframe's optimised pose alone. Cells are
`cell_size` squares of L's floor plane: 0 unknown, 1 free, 2 occupied, kept as a small uint8
image (`cells`, row = y, column = x) whose (0, 0) cell is (`origin_x`, `origin_y`) in cell units.

Making one (`LocalGridMaker.make`, ~1-3 ms at 640×480 with decimation 4, bench/bench_grid.py):
the depth is decimated and back-projected; the floor is fitted (the lowest horizontal slab with
enough points, refined by least squares); points less than `max_ground_height` above the floor
are free floor, points up to `max_obstacle_height` obstacles, higher ones (the ceiling) ignored;
with ray tracing the cells from the camera to the farthest seen cell of each bearing (0.5° bins)
are free too. Obstacles win over free cells of the same keyframe.

The up direction, in order of preference: the session's accelerometer gravity (the mean of the
keyframes' readings (`accel`, specific force in camera axes, +g along up when still) turned into
the session's odometry frame by their poses: a handheld camera's single reading is off by
several degrees from its motion, their mean over the session is not), the session's floor (the
mean normal of the floors fitted so far, weighted by their points, in the same frame), the
floor fitted in this keyframe's depth, this keyframe's accelerometer reading and the
configured camera mounting (`grid.up`); each is the prior of the next's floor search. The
camera height: the floor found in this keyframe (measured along the session's up), else the
session's lowest floor so far (a plane well above it is a table), else `grid.camera_height`.
"""
from __future__ import annotations

import math
import time
import zlib
from dataclasses import dataclass

import cv2
import numpy as np

from mnemoslam.client.kernel.frames import PinholeCamera

from ..config import GridConfig

UNKNOWN, FREE, OCCUPIED = 0, 1, 2

#: Where a keyframe's up direction came from (stored with its grid).
UP_SOURCES = ("config", "session", "floor", "accelerometer")

#: m; a plane fitted this much above the session's floor is not the floor
FLOOR_TOLERANCE = 0.15
#: keyframes with an accelerometer reading before the session's mean of them leads the up (a
#: handheld camera's accelerations average out over seconds: on fr1/desk the mean is 4° off
#: its final value after 10 keyframes, 1.4° after 20; docs/grid.md); the floor leads before
ACCEL_MIN_READINGS = 15


@dataclass
class LocalGrid:
    """One keyframe's grid (see the module docstring)."""

    cell_size: float
    T_cam_local: np.ndarray  # 4×4 float64, camera ← local grid frame
    origin_x: int  # cell index (in L) of cells[0, 0]
    origin_y: int
    cells: np.ndarray  # (H, W) uint8: 0 unknown, 1 free, 2 occupied
    up_source: str = "config"
    floor_points: int = 0  # depth points of the fitted floor (0: none fitted)
    floor_up: np.ndarray | None = None  # the normal of the floor fitted in this keyframe (camera frame; not stored)

    @property
    def up(self) -> np.ndarray:
        """The up direction in the camera frame."""
        return self.T_cam_local[:3, 2].copy()

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of `cells` (a stored grid: without decompressing them)."""
        return self.cells.shape

    @property
    def camera_height(self) -> float:
        """The camera above the floor (m)."""
        return float(-self.T_cam_local[:3, 3] @ self.T_cam_local[:3, 2])

    def counts(self) -> tuple[int, int]:
        """(free cells, occupied cells)."""
        return int(np.count_nonzero(self.cells == FREE)), int(np.count_nonzero(self.cells == OCCUPIED))

    # -- encoding: the stored row ---------------------------------------------------------------
    def encode_cells(self) -> bytes:
        ok, buf = cv2.imencode(".png", self.cells, [cv2.IMWRITE_PNG_COMPRESSION, 1])
        if not ok:  # pragma: no cover - cv2 encodes any 2-D uint8 array
            raise ValueError("cannot encode a local grid")
        return buf.tobytes()

    @staticmethod
    def decode_cells(blob: bytes) -> np.ndarray:
        cells = cv2.imdecode(np.frombuffer(blob, np.uint8), cv2.IMREAD_UNCHANGED)
        if cells is None or cells.dtype != np.uint8 or cells.ndim != 2:
            raise ValueError("cannot decode a stored local grid")
        return cells


class StoredLocalGrid(LocalGrid):
    """A local grid read from the store, kept small for a map grid that holds every keyframe's:
    its PNG is decoded once and its cells kept zlib-compressed (~0.5 kB instead of ~7 kB
    decoded, smaller than the PNG), decompressed each time they are read (~15 µs against the
    PNG's ~75 µs: re-placing 20k keyframes after a loop closure reads every one)."""

    def __init__(self, rec):
        self.cell_size, self.T_cam_local = float(rec.cell_size), np.asarray(rec.transform, np.float64)
        self.origin_x, self.origin_y = int(rec.origin_x), int(rec.origin_y)
        self.up_source, self.floor_points, self.floor_up = rec.up_source, int(rec.floor_points), None
        cells = LocalGrid.decode_cells(bytes(rec.cells))
        self._shape = cells.shape
        self._packed = zlib.compress(cells.tobytes(), 1)

    @property
    def shape(self) -> tuple[int, int]:
        return self._shape

    @property
    def cells(self) -> np.ndarray:  # type: ignore[override]
        return np.frombuffer(zlib.decompress(self._packed), np.uint8).reshape(self._shape)


def _unit(v) -> np.ndarray:
    v = np.asarray(v, np.float64).reshape(3)
    n = np.linalg.norm(v)
    if not np.isfinite(n) or n < 1e-9:
        raise ValueError(f"not a direction: {v}")
    return v / n


def local_frame(up: np.ndarray, height: float) -> np.ndarray:
    """T_cam_local of the grid frame for an up direction (camera frame) and camera height."""
    ez = _unit(up)
    fwd = np.array([0.0, 0.0, 1.0])  # the viewing direction turned horizontal, else the camera's -y
    ex = fwd - (fwd @ ez) * ez
    if np.linalg.norm(ex) < 0.1:
        alt = np.array([0.0, -1.0, 0.0])
        ex = alt - (alt @ ez) * ez
    ex /= np.linalg.norm(ex)
    ey = np.cross(ez, ex)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2] = ex, ey, ez
    T[:3, 3] = -height * ez
    return T


def angle_deg(a, b) -> float:
    """Angle between two directions in degrees."""
    c = float(np.clip(_unit(a) @ _unit(b), -1.0, 1.0))
    return math.degrees(math.acos(c))


@dataclass
class FloorFit:
    up: np.ndarray  # plane normal in the camera frame, towards the camera
    height: float  # camera above the plane (m)
    points: int  # depth points within the slab
    prior_height: float = 0.0  # camera above the slab measured along the prior up (its median)
    centroid: np.ndarray | None = None  # the mean of the slab's points (camera frame)


def fit_floor(points: np.ndarray, up_prior: np.ndarray, config: GridConfig,
              normals: np.ndarray | None = None) -> FloorFit | None:
    """The floor in camera-frame points: the lowest horizontal slab with at least
    `floor_min_points`, refined twice by a least-squares plane; None when there is none or its
    normal is more than `max_ground_angle` from `up_prior`. With `normals` (unit, per point)
    the slab is searched along the mean normal of the points facing within `max_ground_angle`
    of the prior (floors and table tops), so a camera tilted far from its mounting finds it, and
    only those points are searched and fitted."""
    if len(points) < config.floor_min_points:
        return None
    prior = _unit(up_prior)
    up = prior
    if normals is not None:
        cos_max = math.cos(math.radians(config.max_ground_angle))
        for cos_lim in (cos_max, math.cos(math.radians(min(10.0, config.max_ground_angle)))):
            w = (normals @ up.astype(np.float32) > cos_lim).astype(np.float32)
            if w.sum() < config.floor_min_points:
                return None
            up = _unit(w @ normals)  # (a matrix product: 10x faster than a masked sum)
        points = points[normals @ up.astype(np.float32) > cos_max]  # the horizontal surfaces only
        if len(points) < config.floor_min_points:
            return None
    band = config.floor_band
    h = points @ up  # heights relative to the camera (negative below)
    lo = float(h.min())
    nbins = int(math.ceil((float(h.max()) - lo) / band)) + 1
    counts = np.bincount(((h - lo) / band).astype(np.int64), minlength=nbins)
    # a slab of two bins (±band) around each bin centre
    slab = counts + np.concatenate([counts[1:], [0]])
    ok = np.flatnonzero(slab >= config.floor_min_points)
    if len(ok) == 0:
        return None
    level = lo + (ok[0] + 1.0) * band  # centre of the lowest dense slab
    if level > -0.2:  # a "floor" at or above the camera: not one
        return None
    normal, d = up, -level
    for _ in range(2):  # (twice: `sel` is the band about the refined plane after it)
        sel = np.abs(points @ normal + d) < band
        if np.count_nonzero(sel) < config.floor_min_points:
            return None
        P = points[sel]
        c = P.sum(axis=0) / len(P)
        C = P.T @ P - len(P) * np.outer(c, c)  # scatter about the centroid
        n = np.linalg.eigh(C)[1][:, 0]  # the direction of least spread
        if n @ up < 0:
            n = -n
        normal, d = n, -float(n @ c)
    if angle_deg(normal, prior) > config.max_ground_angle or d < 0.2:
        return None
    hp = points[sel] @ prior
    return FloorFit(normal, float(d), int(np.count_nonzero(sel)), float(-np.median(hp)), c)


class LocalGridMaker:
    """Makes the local grids of one session's keyframes (one per `KeyframeWriter`), keeping the
    session's up direction and floor in its odometry frame between keyframes (reset when a new
    tracking segment starts: its frame is another)."""

    def __init__(self, camera: PinholeCamera, config: GridConfig):
        self.camera, self.config = camera, config
        self._rays_key: tuple[tuple[int, int], int] | None = None
        self._rays: tuple[np.ndarray, np.ndarray] | None = None
        self._segment: int | None = None
        self._up_sum = np.zeros(3)  # Σ fitted up (world) × points
        self._acc_sum = np.zeros(3)  # Σ unit accelerometer readings (world)
        self._acc_n = 0
        self._floors = np.zeros((0, 3))  # the centre of each fitted floor's points (world), rows [:_n_floors]
        self._n_floors = 0
        self.last_ms = 0.0

    # -- the session's estimate -------------------------------------------------------------------
    def reset(self) -> None:
        self._up_sum = np.zeros(3)
        self._acc_sum = np.zeros(3)
        self._acc_n = 0
        self._n_floors = 0

    @property
    def floor_up(self) -> np.ndarray | None:
        """The session's floor: the mean normal of its fitted floors (odometry frame)."""
        n = np.linalg.norm(self._up_sum)
        return self._up_sum / n if n > 0 else None

    @property
    def gravity_up(self) -> np.ndarray | None:
        """The session's accelerometer gravity: the mean of its keyframes' readings (odometry frame)."""
        n = np.linalg.norm(self._acc_sum)
        return self._acc_sum / n if n > 0 else None

    @property
    def session_up(self) -> np.ndarray | None:
        """The session's up (odometry frame): its accelerometer gravity once it has
        `ACCEL_MIN_READINGS` readings, else its floor, else the gravity of its few readings."""
        if self._acc_n >= ACCEL_MIN_READINGS or self.floor_up is None:
            return self.gravity_up
        return self.floor_up

    def _floor_level(self, up: np.ndarray) -> float | None:
        """The session's lowest floor along `up` (up · x of it), from the floor points kept:
        measured along today's up, so an up refined since (the accelerometer's mean of a few
        readings at first) moves no floor."""
        return float(np.min(self._floors[:self._n_floors] @ up)) if self._n_floors else None

    def _add_floor(self, p: np.ndarray) -> None:
        if self._n_floors == len(self._floors):  # grown by doubling: ~50 µs a look at 20k floors
            self._floors = np.concatenate([self._floors, np.zeros((max(16, len(self._floors)), 3))])
        self._floors[self._n_floors] = p
        self._n_floors += 1

    def _rays_for(self, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        d = max(1, int(self.config.depth_decimation))
        key = (shape, d)
        if self._rays is None or self._rays_key != key:
            cam = self.camera
            h, w = shape
            if cam.distorted and (h, w) == (cam.height, cam.width):  # the undistorted ray of each raw pixel
                r = cam.pixel_rays()[::d, ::d]
                self._rays = (r[..., 0], r[..., 1])
            else:
                v, u = np.mgrid[0:h:d, 0:w:d].astype(np.float32)
                self._rays = ((u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy)
            self._rays_key = key
        return self._rays

    def points(self, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The decimated depth as camera-frame points (N, 3) within the range limits, and the
        surface normal at each (unit, facing the camera; 0 where a neighbour is missing or
        jumps), from the cross product of the steps to the next point right and down."""
        cfg = self.config
        d = max(1, int(cfg.depth_decimation))
        z = depth[::d, ::d].astype(np.float32)
        z[~np.isfinite(z)] = 0
        rx, ry = self._rays_for(depth.shape)
        X, Y = rx * z, ry * z
        ax, ay, az = X[:-1, 1:] - X[:-1, :-1], Y[:-1, 1:] - Y[:-1, :-1], z[:-1, 1:] - z[:-1, :-1]
        bx, by, bz = X[1:, :-1] - X[:-1, :-1], Y[1:, :-1] - Y[:-1, :-1], z[1:, :-1] - z[:-1, :-1]
        nx, ny, nz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
        zc = z[:-1, :-1]
        jump = 0.05 * zc + 0.01
        norm = np.sqrt(nx * nx + ny * ny + nz * nz)
        okn = (zc > 0) & (z[:-1, 1:] > 0) & (z[1:, :-1] > 0) & (np.abs(az) < jump) & (np.abs(bz) < jump) & (norm > 0)
        # unit, towards the camera (n · p < 0), 0 where not valid
        inv = np.where(okn, -np.sign(nx * X[:-1, :-1] + ny * Y[:-1, :-1] + nz * zc) / np.where(okn, norm, 1), 0)
        ok = z > 0
        r2 = X * X + Y * Y + z * z
        ok &= (r2 <= cfg.range_max ** 2) & (r2 >= cfg.range_min ** 2)
        okc = ok[:-1, :-1]
        P = np.column_stack([X[ok], Y[ok], z[ok]]).astype(np.float64)
        N = np.zeros((len(P), 3), np.float32)
        # the normals live on the (h-1, w-1) corner: map them onto the points of `ok`
        idx = np.cumsum(ok.ravel()) - 1
        corner = np.zeros_like(ok)
        corner[:-1, :-1] = okc
        at = idx[corner.ravel()]
        N[at, 0], N[at, 1], N[at, 2] = (nx * inv)[okc], (ny * inv)[okc], (nz * inv)[okc]
        return P, N

    def make(self, depth: np.ndarray, pose: np.ndarray | None = None, segment: int | None = None,
             accel=None) -> LocalGrid | None:
        """The local grid of a keyframe: its depth (metres, 0 / non-finite invalid), its
        odometry pose (camera-to-world, for the session's estimate), its tracking segment and
        its accelerometer reading (camera axes, m/s²) when it has one. None without depth."""
        t0 = time.perf_counter()
        if depth is None:
            return None
        cfg = self.config
        if segment != self._segment:
            self.reset()
            self._segment = segment
        R = None if pose is None else np.asarray(pose, np.float64)[:3, :3]
        c = None if pose is None else np.asarray(pose, np.float64)[:3, 3]
        P, N = self.points(depth)
        source = "config"
        prior = _unit(cfg.up)
        if accel is not None and np.all(np.isfinite(accel)) and np.linalg.norm(accel) > 1.0:
            prior, source = _unit(accel), "accelerometer"
            if R is not None:
                self._acc_sum += R @ prior
                self._acc_n += 1
        session = False  # the up is the session's estimate: a floor fitted here gives the height only
        gravity, floor = self.gravity_up, self.floor_up
        if R is not None and gravity is not None and self._acc_n >= ACCEL_MIN_READINGS:
            prior, source, session = R.T @ gravity, "accelerometer", True
        elif R is not None and floor is not None:
            prior, source, session = R.T @ floor, "session", True
        elif R is not None and gravity is not None:  # a few readings: a floor fitted here leads
            prior, source = R.T @ gravity, "accelerometer"
        fit = fit_floor(P, prior, cfg, N) if len(P) else None
        su = self.session_up
        level = None if su is None else self._floor_level(su)
        if fit is not None and R is not None and su is not None and level is not None:
            # a plane well above the session's floor is a table or a bed, not the floor (one
            # well below it is: the floor is the lowest plane)
            if float(su @ c) - fit.prior_height > level + FLOOR_TOLERANCE:
                fit = None
        up, height, floor_points = prior, None, 0
        if fit is not None:
            floor_points = fit.points
            if not session:
                up, source, height = fit.up, "floor", fit.height
            else:  # the session's mean up stays (steadier than one fit): the slab gives the height
                height = fit.prior_height
            if R is not None:  # the session's estimate, in its odometry frame
                self._up_sum += (R @ fit.up) * fit.points
                assert fit.centroid is not None  # (fit_floor sets it)
                self._add_floor(c + R @ fit.centroid)
        if height is None:
            su = self.session_up
            level = None if su is None else self._floor_level(su)
            if R is not None and level is not None and su is not None:
                height = float(su @ c) - level
            else:
                height = cfg.camera_height
        T = local_frame(up, height)
        grid = self._cells(P, T)
        grid.up_source, grid.floor_points = source, floor_points
        grid.floor_up = None if fit is None else fit.up
        self.last_ms = (time.perf_counter() - t0) * 1e3
        return grid

    def _cells(self, P: np.ndarray, T: np.ndarray) -> LocalGrid:
        cfg = self.config
        cs = float(cfg.cell_size)
        L = (P - T[:3, 3]) @ T[:3, :3]  # points in the local frame (z = height above the floor)
        hz = L[:, 2]
        ground = hz <= cfg.max_ground_height
        seen = hz <= cfg.max_obstacle_height
        if not np.any(seen):
            return LocalGrid(cs, T, 0, 0, np.zeros((1, 1), np.uint8))
        ix = np.floor(L[seen, 0] / cs).astype(np.int64)
        iy = np.floor(L[seen, 1] / cs).astype(np.int64)
        ground = ground[seen]
        x0, x1 = min(int(ix.min()), 0), max(int(ix.max()), 0)
        y0, y1 = min(int(iy.min()), 0), max(int(iy.max()), 0)
        W, H = x1 - x0 + 1, y1 - y0 + 1
        flat = (iy - y0) * W + (ix - x0)
        cells = np.zeros(H * W, np.uint8)
        cells[flat[ground]] = FREE
        cells[flat[~ground]] = OCCUPIED
        img = cells.reshape(H, W)
        if cfg.ray_tracing:
            self._ray_trace(img, x0, y0)
        return LocalGrid(cs, T, x0, y0, img)

    @staticmethod
    def _ray_trace(img: np.ndarray, x0: int, y0: int) -> None:
        """Free the cells from the camera (L's origin) to the farthest seen cell of each 0.5°
        bearing (the polygon of the camera and those cells in bearing order, filled), keeping
        the seen cells' own states."""
        r, c = np.nonzero(img)
        dx, dy = c + x0 + 0.5, r + y0 + 0.5  # cell centres, in cells, from the camera's foot
        b = np.floor(np.degrees(np.arctan2(dy, dx)) * 2.0)
        r2 = dx * dx + dy * dy
        order = np.argsort(b * 1e6 - r2, kind="stable")  # per bin, farthest first (r2 < 1e6 cells²)
        bs = b[order]
        first = np.ones(len(order), bool)
        first[1:] = bs[1:] != bs[:-1]
        far = order[first]  # bins ascending: the polygon's vertices in bearing order
        poly = np.empty((len(far) + 1, 2), np.int32)
        poly[0] = (-x0, -y0)
        poly[1:, 0] = c[far]
        poly[1:, 1] = r[far]
        seen = img.copy()
        cv2.fillPoly(img, [poly], FREE)
        np.copyto(img, seen, where=seen > 0)
