"""EuRoC MAV player (ASL folder layout): `mav0/cam0`, `mav0/cam1` (data.csv, data/*.png,
sensor.yaml), `mav0/imu0/data.csv`, ground truth from `mav0/state_groundtruth_estimate0/data.csv`
or a `*.tum` file next to `mav0/`.

The raw pinhole + radial-tangential stereo pair is rectified once (cv2.stereoRectify, alpha 0,
zero disparity); frames carry the rectified grey left/right images. The frame camera is the
rectified left camera, rotated by R1 from raw cam0; ground truth (body poses) is converted to it.
The images are rectified here, unlike the RGB-D players' (which leave lens distortion to the
service's feature coordinates): stereo matching needs rectified rows, and there is no depth
image registered to the raw pixels to keep; the frame camera has no distortion.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml

from ..kernel.frames import Calibration, DatasetError, Frame
from ..kernel.geometry import invert, quat_to_rot
from ..kernel.trajectory import Trajectory, read_tum
from ._io import check_index, frame_count, numbers, pinhole, read_grey, read_rows, sample_poses
from .base import Dataset


@dataclass(frozen=True)
class EurocCamera:
    """One camera's sensor.yaml: intrinsics, radial-tangential distortion, body<-sensor pose."""

    K: np.ndarray  # 3x3
    dist: np.ndarray  # k1, k2, p1, p2
    T_BS: np.ndarray  # 4x4 body <- sensor
    size: tuple[int, int]  # width, height


def read_sensor_yaml(path: Path) -> EurocCamera:
    """Parse an EuRoC camera sensor.yaml (OpenCV's '%YAML:1.0' header is dropped for PyYAML)."""
    path = Path(path)
    try:
        text = path.read_text()
        if text.startswith("%YAML"):
            text = text.split("\n", 1)[1] if "\n" in text else ""
        d = yaml.safe_load(text)
        fu, fv, cu, cv = (float(v) for v in d["intrinsics"])
        dist = np.array(d["distortion_coefficients"], dtype=np.float64).reshape(-1)
        T_BS = np.array(d["T_BS"]["data"], dtype=np.float64).reshape(4, 4)
        w, h = (int(v) for v in d["resolution"])
        model, dist_model = d.get("camera_model", "pinhole"), d.get("distortion_model", "radial-tangential")
    except OSError as e:
        raise DatasetError(f"{path}: cannot read ({e.strerror})") from None
    except (yaml.YAMLError, KeyError, TypeError, ValueError) as e:
        raise DatasetError(f"{path}: not a valid EuRoC camera sensor.yaml ({type(e).__name__}: {e})") from None
    if model != "pinhole" or dist_model not in ("radial-tangential", "radtan") or len(dist) not in (4, 5):
        raise DatasetError(f"{path}: unsupported camera model {model!r} / {dist_model!r} with {len(dist)} coefficients")
    return EurocCamera(np.array([[fu, 0, cu], [0, fv, cv], [0, 0, 1]]), dist, T_BS, (w, h))


def read_image_list(cam: Path) -> tuple[np.ndarray, np.ndarray]:
    """A camera's data.csv as (int64 ns stamps, image paths)."""
    rows = read_rows(cam / "data.csv", 2)
    ns = numbers(cam / "data.csv", [r[0] for r in rows], np.int64)
    return ns, np.array([str(cam / "data" / r[1]) for r in rows], dtype=object)


def read_groundtruth_csv(path: Path) -> Trajectory:
    """state_groundtruth_estimate0/data.csv: ns, p xyz, q w x y z (body poses T_W_B)."""
    rows = read_rows(path, 8)
    ns = numbers(path, [r[0] for r in rows], np.int64)
    v = numbers(path, [r[1:8] for r in rows]).reshape(-1, 7)
    poses = np.tile(np.eye(4), (len(v), 1, 1))
    poses[:, :3, :3] = quat_to_rot(v[:, [4, 5, 6, 3]])  # w x y z -> x y z w
    poses[:, :3, 3] = v[:, :3]
    order = np.argsort(ns, kind="stable")
    return Trajectory(ns[order] / 1e9, poses[order])


class EurocDataset(Dataset):
    """An EuRoC sequence: the folder holding mav0/, or mav0 itself."""

    format = "euroc"

    def __init__(self, path: Path, *, max_frames: int | None = None):
        path = Path(path)
        is_mav = path.name == "mav0" and (path / "cam0").is_dir()
        mav, root = (path, path.parent) if is_mav else (path / "mav0", path)
        if not mav.is_dir():
            raise DatasetError(f"{path}: no mav0/ folder")
        self.path, self.name = root, root.resolve().name
        c0, c1 = (read_sensor_yaml(mav / c / "sensor.yaml") for c in ("cam0", "cam1"))
        if c0.size != c1.size:
            raise DatasetError(f"{mav}: cam0 is {c0.size}, cam1 is {c1.size}")

        ns0, files0 = read_image_list(mav / "cam0")
        ns1, files1 = read_image_list(mav / "cam1")
        ns, i0, i1 = np.intersect1d(ns0, ns1, return_indices=True)  # stereo pairs: same stamp
        n = frame_count(len(ns), max_frames, mav / "cam0" / "data.csv")
        self.stamps = ns[:n] / 1e9
        self._files = files0[i0[:n]], files1[i1[:n]]

        T_c1_c0 = invert(c1.T_BS) @ c0.T_BS
        R1, R2, P1, P2, *_ = cv2.stereoRectify(c0.K, c0.dist, c1.K, c1.dist, c0.size, T_c1_c0[:3, :3],
                                               T_c1_c0[:3, 3], flags=cv2.CALIB_ZERO_DISPARITY, alpha=0)
        if P2[0, 3] >= 0:
            raise DatasetError(f"{mav}: cam1 is not to the right of cam0 (rectified P2 = {P2[0].tolist()})")
        self._maps = [cv2.initUndistortRectifyMap(c.K, c.dist, R, P, c.size, cv2.CV_16SC2)
                      for c, R, P in ((c0, R1, P1), (c1, R2, P2))]
        self._shape = c0.size[::-1]
        camera = pinhole(P1[0, 0], P1[1, 1], P1[0, 2], P1[1, 2], *c0.size)
        self.calibration = Calibration(camera, float(np.linalg.norm(T_c1_c0[:3, 3])), depth_scale=1.0)
        T_c0_rect = np.eye(4)
        T_c0_rect[:3, :3] = R1.T
        self.T_B_cam = c0.T_BS @ T_c0_rect  # body <- frame (rectified left) camera

        imu = mav / "imu0" / "data.csv"
        if imu.is_file():
            rows = read_rows(imu, 7)
            v = numbers(imu, [r[:7] for r in rows]).reshape(-1, 7)
            v[:, 0] = numbers(imu, [r[0] for r in rows], np.int64) / 1e9  # exact ns before scaling
            self.imu = v
        else:
            self.imu = np.zeros((0, 7))  # t [s], gyro xyz [rad/s], accel xyz [m/s^2]

        gt_csv = mav / "state_groundtruth_estimate0" / "data.csv"
        tums = sorted(root.glob("*.tum"))
        body = read_groundtruth_csv(gt_csv) if gt_csv.is_file() else read_tum(tums[0]) if tums else None
        if body is not None:
            body = sample_poses(body.transformed(T_right=self.T_B_cam), self.stamps)
        self.ground_truth = body

    def __len__(self) -> int:
        return len(self.stamps)

    def frame(self, i: int) -> Frame:
        i = check_index(i, len(self))
        left, right = (cv2.remap(read_grey(f[i], self._shape), m1, m2, cv2.INTER_LINEAR)
                       for f, (m1, m2) in zip(self._files, self._maps))
        return Frame(i, float(self.stamps[i]), left, right=right, source=f"{self._files[0][i]}, {self._files[1][i]}")
