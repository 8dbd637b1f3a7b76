"""The map's coloured point cloud (rtabmap-export's cloud): each keyframe's stored depth and
colour, decimated, back-projected, placed at the keyframe's optimised pose, then voxel-filtered
(one point per voxel: the mean position and colour of the points in it), written as binary
PLY. Keyframes without stored images (merged by rehearsal, storage.keep_images false) add
nothing."""
from __future__ import annotations

import hashlib
import threading

import numpy as np

from mnemoslam.client.kernel.frames import PinholeCamera
from mnemoslam.storage import GridStore

from ..memory.keyframes import decode_images


def keyframe_points(color: np.ndarray | None, depth: np.ndarray, camera: PinholeCamera, decimation: int = 4,
                    max_depth: float = 5.0) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points (N, 3) float32 and their colours (N, 3) uint8 RGB (grey when no colour)."""
    d = max(1, int(decimation))
    z = depth[::d, ::d]
    v, u = np.mgrid[0:depth.shape[0]:d, 0:depth.shape[1]:d]
    ok = np.isfinite(z) & (z > 0) & (z <= max_depth)
    zz = z[ok].astype(np.float32)
    if camera.distorted and depth.shape[:2] == (camera.height, camera.width):  # undistorted rays of the raw pixels
        r = camera.pixel_rays()[::d, ::d][ok]
        P = np.column_stack([r[:, 0] * zz, r[:, 1] * zz, zz])
    else:
        P = np.column_stack([(u[ok] - camera.cx) / camera.fx * zz, (v[ok] - camera.cy) / camera.fy * zz, zz])
    if color is None:
        C = np.full((len(P), 3), 200, np.uint8)
    else:
        c = color[::d, ::d] if color.shape[:2] == depth.shape[:2] else None
        if c is None:
            C = np.full((len(P), 3), 200, np.uint8)
        elif c.ndim == 2:
            C = np.repeat(c[ok][:, None], 3, axis=1)
        else:
            C = c[ok][:, ::-1]  # BGR -> RGB
    return P.astype(np.float32), np.ascontiguousarray(C, np.uint8)


def voxel_filter(P: np.ndarray, C: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """One point per voxel: the mean of its points and colours, voxels in the order of their
    keys (one sort of the keys, then sums over each run of equal keys)."""
    if len(P) == 0 or voxel <= 0:
        return P, C
    key = np.floor(P / voxel).astype(np.int64)
    key -= key.min(axis=0)
    dims = key.max(axis=0) + 1
    flat = (key[:, 0] * dims[1] + key[:, 1]) * dims[2] + key[:, 2]
    order = np.argsort(flat, kind="stable")
    flat = flat[order]
    start = np.flatnonzero(np.concatenate(([True], flat[1:] != flat[:-1])))
    counts = np.diff(np.append(start, len(flat)))[:, None]
    out_p = np.add.reduceat(P[order].astype(np.float64), start) / counts
    out_c = np.add.reduceat(C[order].astype(np.float64), start) / counts
    return out_p.astype(np.float32), np.rint(out_c).astype(np.uint8)


class CloudCache:
    """What `map_cloud` keeps between requests, within `max_bytes`: each keyframe's
    voxel-filtered points in the map frame, by (node, voxel) with the pose they were placed
    at (a keyframe that moved is made again), and the last whole cloud by voxel with the
    keyframes and poses it was made of. A full cache admits no more keyframes (those it holds
    stay hits; a least-recently-used cache would keep none of a map larger than it, read in
    the same order at every request); a keyframe made again at a new pose takes its old
    entry's place."""

    def __init__(self, max_bytes: int):
        self.max_bytes = int(max_bytes)
        self._lock = threading.Lock()
        self._kf: dict[tuple, tuple[bytes, np.ndarray, np.ndarray]] = {}  # (node, params) -> (pose, P, C)
        self._whole: dict[tuple, tuple[bytes, np.ndarray, np.ndarray]] = {}  # params -> (key, P, C)
        self.bytes = 0
        self.hits = self.misses = 0

    @staticmethod
    def _size(P: np.ndarray, C: np.ndarray) -> int:
        return P.nbytes + C.nbytes + 200

    def get(self, node: int, params: tuple, pose: np.ndarray):
        with self._lock:
            e = self._kf.get((node, params))
            if e is not None and e[0] == pose.tobytes():
                self.hits += 1
                return e[1], e[2]
            self.misses += 1
            return None

    def put(self, node: int, params: tuple, pose: np.ndarray, P: np.ndarray, C: np.ndarray) -> None:
        with self._lock:
            old = self._kf.pop((node, params), None)
            if old is not None:
                self.bytes -= self._size(old[1], old[2])
            size = self._size(P, C)
            P.setflags(write=False)  # (shared by the requests that get them)
            C.setflags(write=False)
            if self.bytes + size <= self.max_bytes:
                self._kf[(node, params)] = (pose.tobytes(), P, C)
                self.bytes += size

    def whole(self, params: tuple, key: bytes):
        with self._lock:
            e = self._whole.get(params)
            return (e[1], e[2]) if e is not None and e[0] == key else None

    def put_whole(self, params: tuple, key: bytes, P: np.ndarray, C: np.ndarray) -> None:
        with self._lock:
            for v in list(self._whole):  # the last two whole clouds (of different voxel sizes)
                if v != params and len(self._whole) >= 2:
                    self.bytes -= self._size(*self._whole.pop(v)[1:])
            old = self._whole.pop(params, None)
            if old is not None:
                self.bytes -= self._size(old[1], old[2])
            size = self._size(P, C)
            P.setflags(write=False)
            C.setflags(write=False)
            if size <= self.max_bytes // 2:  # (the keyframes keep at least half)
                self._whole[params] = (key, P, C)
                self.bytes += size


def map_cloud(store: GridStore, node_ids, poses, voxel: float = 0.02, decimation: int = 4,
              max_depth: float = 5.0, cache: CloudCache | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The cloud of these keyframes at these poses (map frame), voxel-filtered. Keyframes are
    filtered one by one as they come (bounded memory), then once more together. With a
    `cache`, keyframes it holds at the same pose and voxel are not read nor decoded again,
    and the same keyframes at the same poses give the last cloud at once."""
    voxel = float(voxel)
    poses = np.asarray(poses, np.float64).reshape(-1, 4, 4)
    ids = np.asarray(node_ids, np.int64).reshape(-1)
    params, key = (voxel, int(decimation), float(max_depth)), b""
    if cache is not None:
        key = hashlib.blake2b(ids.tobytes() + poses.tobytes(), digest_size=16).digest()
        hit = cache.whole(params, key)
        if hit is not None:
            return hit
    cams: dict[int, PinholeCamera] = {}
    sessions: dict[int, int] | None = None
    parts_p, parts_c = [], []
    for n, pose in zip(ids.tolist(), poses):
        got = cache.get(n, params, pose) if cache is not None else None
        if got is None:
            color_b, depth_b = store.load_images(n)
            if depth_b is None:
                got = (np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8))
            else:
                if sessions is None:
                    sessions = {k.id: k.session_id for k in store.get_nodes(ids.tolist())}
                sid = sessions[n]  # (a node with stored images has a row)
                if sid not in cams:
                    cams[sid] = store.calibration(sid).camera
                color, depth = decode_images(color_b, depth_b)
                assert depth is not None  # (decoded from depth_b, or it raised)
                P, C = keyframe_points(color, depth, cams[sid], decimation, max_depth)
                P = P @ pose[:3, :3].T.astype(np.float32) + pose[:3, 3].astype(np.float32)
                got = voxel_filter(P, C, voxel)
            if cache is not None:
                cache.put(n, params, pose, *got)
        if len(got[0]):
            parts_p.append(got[0])
            parts_c.append(got[1])
    if not parts_p:
        out = np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)
    else:
        out = voxel_filter(np.concatenate(parts_p), np.concatenate(parts_c), voxel)
    if cache is not None:
        cache.put_whole(params, key, *out)
    return out


def ply_bytes(P: np.ndarray, C: np.ndarray) -> bytes:
    """Binary little-endian PLY with x, y, z (float32) and red, green, blue (uint8)."""
    n = len(P)
    header = ("ply\nformat binary_little_endian 1.0\ncomment mnemoslam map cloud (map frame, metres)\n"
              f"element vertex {n}\nproperty float x\nproperty float y\nproperty float z\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n").encode()
    rec = np.zeros(n, dtype=[("p", "<f4", 3), ("c", "u1", 3)])
    rec["p"], rec["c"] = P, C
    return header + rec.tobytes()


def read_ply(data: bytes) -> tuple[np.ndarray, np.ndarray]:
    """A PLY of `ply_bytes` read back (tests, tools)."""
    end = data.index(b"end_header\n") + len(b"end_header\n")
    n = int(next(line.split()[2] for line in data[:end].decode().splitlines() if line.startswith("element vertex")))
    rec = np.frombuffer(data[end:], dtype=[("p", "<f4", 3), ("c", "u1", 3)], count=n)
    return rec["p"].copy(), rec["c"].copy()
