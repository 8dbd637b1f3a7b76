"""The main job on the embedded default: start the service as its own process, stream the
synthetic scene into it over Zenoh as a separate client, wait for the map, print the ATE
against the scene's exact ground truth, ask the REST API for the nearest door to the robot
(the camera sends its per-pixel labels; the service fuses them into objects) and compare it with
the scene's true doors, stop the service."""
from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

import numpy as np
import yaml

from mnemoslam.client.datasets import open_dataset
from mnemoslam.client.kernel.trajectory import Trajectory
from mnemoslam.client.planner import ApiError, PlannerClient
from mnemoslam.client.streamer import stream_dataset
from mnemoslam.client.transport import ZenohSettings

from .config import load_config, merge_overrides
from .evaluation import evaluate


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class ServiceProcess:
    """`mnemoslam serve` in a child process with its own ports and database."""

    def __init__(self, db: Path, config: dict | None = None, log_path: Path | None = None):
        self.db, self.overrides = Path(db).resolve(), config or {}
        self.dir = Path(tempfile.mkdtemp(prefix="mnemoslam-svc-"))
        self.config_path = self.dir / "service.yaml"
        self.log_path = log_path or self.dir / "service.log"
        self.proc: subprocess.Popen | None = None
        self._pick_ports()

    def _pick_ports(self) -> None:
        """Free ports for Zenoh and the API, written into the child's config file."""
        self.zenoh_port, self.http_port = free_port(), free_port()
        self.endpoint = f"tcp/127.0.0.1:{self.zenoh_port}"
        # the database's absolute path: the child runs in the checkout, not in the caller's folder
        cfg = {"zenoh": {"listen": [self.endpoint]}, "api": {"port": self.http_port}, "storage": {"path": str(self.db)}}
        cfg = merge_overrides(cfg, self.overrides)  # nested: {"loop": {"enabled": False}}, top-level keys too
        self.config_path.write_text(yaml.safe_dump(cfg))
        self.api = PlannerClient(f"http://127.0.0.1:{self.http_port}")

    def start(self, timeout: float = 60.0, attempts: int = 3) -> "ServiceProcess":
        """Start `serve` and wait until /health answers. A port that another process took
        between `free_port` and the child's bind ("Address already in use") is picked again,
        up to `attempts` times; any other early exit raises with the log's last lines."""
        root = Path(__file__).resolve().parents[1]
        env = dict(os.environ, PYTHONPATH=str(root) + os.pathsep + os.environ.get("PYTHONPATH", ""))
        self._log = open(self.log_path, "w")
        self.proc = subprocess.Popen([sys.executable, "-m", "mnemoslam.service.cli", "serve",
                                      "--config", str(self.config_path)],
                                     stdout=self._log, stderr=subprocess.STDOUT, env=env, cwd=root)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                self._log.close()
                tail = "\n".join(Path(self.log_path).read_text(errors="replace").splitlines()[-5:])
                if attempts > 1 and "in use" in tail.lower():
                    self._pick_ports()
                    return self.start(timeout, attempts - 1)
                raise RuntimeError(f"service exited with {self.proc.returncode}; log: {self.log_path}:\n{tail}")
            try:
                if self.api.health()["status"] == "ok":
                    return self
            except (OSError, ApiError):
                time.sleep(0.2)
        raise RuntimeError(f"service did not become healthy in {timeout:.0f} s; log: {self.log_path}")

    def stop(self, sig=signal.SIGTERM, timeout: float = 30.0) -> int:
        if self.proc is None:
            return 0
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._log.close()
        return self.proc.returncode

    def wait_processed(self, robot: str, frames: int, timeout: float = 300.0) -> dict:
        """Until every frame sent by `robot` was processed, dropped or rejected."""
        def done(r: dict) -> bool:
            seen = (r.get("frames_processed", 0) + r.get("frames_dropped", 0)
                    + sum(r.get("frames_rejected", {}).values()))
            return seen >= frames and r.get("queue_depth", 1) == 0
        return self._wait(robot, done, timeout)

    def wait_mapped(self, robot: str, timeout: float = 300.0) -> dict:
        """Until the map update (behind tracking) has done every keyframe of `robot`."""
        return self._wait(robot, lambda r: r.get("map_backlog", 1) == 0, timeout)

    def _wait(self, robot: str, done: Callable[[dict], bool], timeout: float) -> dict:
        """Poll the robot's status until `done(status)`; its last status."""
        deadline = time.monotonic() + timeout
        r: dict = {}
        while time.monotonic() < deadline:
            try:
                r = self.api.robot(robot)
            except ApiError:
                r = {}
            if r and done(r):
                return r
            time.sleep(0.25)
        raise TimeoutError(f"robot {robot}: {r} after {timeout:.0f} s")

    def session_of(self, robot: str) -> int:
        ids = [s["id"] for s in self.api.sessions() if s["robot"] == robot]
        if not ids:
            raise RuntimeError(f"no session for robot {robot}")
        return ids[-1]


def keyframe_trajectory(api: PlannerClient, session_id: int) -> Trajectory:
    poses = api.trajectory(session_id)["poses"]
    return Trajectory(np.array([p["stamp"] for p in poses]),
                      np.array([p["pose"] for p in poses]).reshape(-1, 4, 4))


_ERROR_LINE = re.compile(r"\b(ERROR|CRITICAL)\b|^Traceback \(most recent call last\)")

# Keys the demo sets itself for the service it starts (its own ports, database, REST on).
DEMO_KEYS = ("zenoh.listen", "api.enabled", "api.host", "api.port", "storage.path")


def log_errors(path: str | Path) -> list[str]:
    """The lines of a service log that report an error: ERROR / CRITICAL log records and
    the first line of each traceback. [] when the log is missing."""
    try:
        with open(path, errors="replace") as f:
            return [line.rstrip("\n") for line in f if _ERROR_LINE.search(line)]
    except OSError:
        return []


def log_report(path: str | Path) -> str | None:
    """The demo's line about errors in the service log (None when there are none)."""
    errors = log_errors(path)
    if not errors:
        return None
    n = len(errors)
    first = errors[0] if len(errors[0]) <= 160 else errors[0][:157] + "..."
    return f"demo: the service log has {n} error line{'s' if n > 1 else ''} ({path}); first: {first}"


def _check_overrides(overrides: dict) -> None:
    """Validate the service's --set overrides here (ConfigError: unknown key, wrong type),
    and refuse the keys the demo sets itself."""
    load_config(None, overrides)
    for key in DEMO_KEYS:
        section, name = key.split(".")
        if name in (overrides.get(section) or {}):
            raise ValueError(f"--set {key}: the demo sets it for the service it starts "
                             "(use `mnemoslam serve` and `mnemoslam stream` for your own)")


def true_doors_in_map_frame(dataset) -> np.ndarray:
    """The synthetic scene's door centres in the map's frame (the first camera pose is the origin)."""
    first = dataset.ground_truth.poses[0]
    doors = np.array([o.center for o in dataset.scene.objects if o.class_name == "door"], float)
    return (np.linalg.inv(first) @ np.c_[doors, np.ones(len(doors))].T).T[:, :3]


def _nearest_door(api: PlannerClient, dataset, robot: str, timeout: float = 30.0) -> dict | None:
    """Ask for the door nearest `robot` (the semantic worker stores its objects shortly after
    the map update) and print it next to the scene's true nearest door."""
    deadline, answer = time.monotonic() + timeout, None
    while answer is None:
        try:
            answer = api.nearest_object("door", robot=robot)
        except ApiError as e:
            if time.monotonic() > deadline or api.last_semantics == "off":
                print(f"demo: REST GET /objects/nearest?label=door&robot={robot} -> {e}")
                return None
            time.sleep(0.5)
    at = np.array(api.robot(robot)["position"])
    doors = true_doors_in_map_frame(dataset)
    truth = doors[np.argmin(np.linalg.norm(doors - at, axis=1))]
    pos = np.array(answer["object"]["position"])
    print(f"demo: REST GET /objects/nearest?label=door&robot={robot} -> door {answer['object']['id']} at "
          f"({pos[0]:.2f}, {pos[1]:.2f}, {pos[2]:.2f}), {answer['distance']:.2f} m from the robot; "
          f"the scene's true nearest door is {np.linalg.norm(pos - truth):.2f} m from it")
    return answer


def _has_noise(trajectory: str) -> bool:
    """Whether the synthetic path comes with a noise model of its own (an unknown name: no;
    open_dataset then says it is unknown)."""
    from mnemoslam.client.synthetic import TRAJECTORIES

    spec = TRAJECTORIES.get(trajectory)
    return spec is not None and spec.noise not in (None, False, "none")


def run_demo(trajectory: str = "loop", rate: float = 15.0, noise: bool = True, out: str = "out/demo",
             progress: bool = True, overrides: dict | None = None, frames: int | None = None) -> int:
    """The demo; `overrides` (nested config keys, `mnemoslam demo --set`) go to the service.
    Prints a short report (and the error lines of the service's log, if any); progress bar
    when `progress`. `out` (made with its parents when missing) holds the database and the
    service's log, relative to the current folder; `frames`: stream only the path's first
    frames (default: all of it)."""
    # semantics from the synthetic camera's labels (the default source, auto, takes them), unless
    # the caller says otherwise
    service_config = dict(overrides or {})
    _check_overrides(service_config)
    semantics = load_config(None, service_config).semantics
    labels = semantics.enabled and semantics.source in ("camera", "auto")
    prefix = load_config(None, service_config).zenoh.prefix
    out_dir = Path(out).resolve()
    out_dir.mkdir(parents=True, exist_ok=True)
    db = out_dir / "map.db"
    for p in (db, db.with_name("map.db-wal"), db.with_name("map.db-shm")):
        p.unlink(missing_ok=True)
    # noise: the path's own sensor model where it has one (fastrot: Kinect disparity noise and
    # blur), else the axial model; none with --no-noise
    dataset = open_dataset(f"synthetic:{trajectory}", rate=rate,
                           noise=None if noise and _has_noise(trajectory) else noise,
                           **({"max_frames": frames} if frames else {}))
    print(f"demo: starting the service (database {db})")
    log_path = out_dir / "service.log"
    svc = ServiceProcess(db, service_config, log_path=log_path)
    try:
        svc.start()
    except RuntimeError:
        svc.stop()
        print(log_report(log_path) or f"demo: the service did not start; see its log {log_path}")
        raise
    ev = None
    try:
        print(f"demo: streaming {dataset.name} ({len(dataset)} frames) over Zenoh to {svc.endpoint} as robot 'demo'")
        stats = stream_dataset(dataset, "demo", ZenohSettings(connect=[svc.endpoint]), rate=None,
                               prefix=prefix, progress=progress, wait_for_subscriber=10.0, labels=labels)
        robot = svc.wait_processed("demo", stats.frames)
        svc.wait_mapped("demo")  # the loop closures of the last keyframes, before the map is read
        print(f"demo: service processed {robot['frames_processed']} frames "
              f"({robot['tracked']} tracked, {robot['keyframes']} keyframes, {robot['frames_dropped']} dropped, "
              f"{robot['fps']:.1f} frames/s); client sent {stats.mbps:.0f} Mbit/s ({stats.encoding})")
        session_id = svc.session_of("demo")
        keyframes = keyframe_trajectory(svc.api, session_id)
        ev = evaluate(dataset.ground_truth, keyframes)
        print(f"demo: keyframe ATE RMSE {ev.ate_rmse * 100:.2f} cm over {ev.matched} keyframes "
              f"({ev.path_length:.1f} m path)")
        start = keyframes.positions[0]
        box = (tuple(start - 1.0), tuple(start + 1.0))
        answer = svc.api.nodes(session_id, bbox=box, limit=3)
        print(f"demo: REST GET /sessions/{session_id}/nodes?bbox=<1 m around the start> -> "
              f"{answer['total']} keyframes, first ids {[n['id'] for n in answer['nodes']]}")
        _nearest_door(svc.api, dataset, "demo")
    finally:
        code = svc.stop()
        print(f"demo: service stopped (exit {code}); map in {db}")
        errors = log_report(log_path)  # also when the demo failed: the log may say why
        if errors:
            print(errors)
    return 0 if ev is not None and ev.matched > 0 and code == 0 else 1
