"""Child process of tests/test_memory_crash.py: one robot session mapped into a real SQLite
map with a small working memory, killed by the test with SIGKILL.

    python tests/memory_crash_child.py DB FRAMES.npz CONFIG_JSON [--hold transfer|retrieve N before|after]

Once its imports are done it prints IMPORTED and waits for a line on stdin before it reads
the frames and opens the database (so the test can start it while it still renders the
frames or recovers the previous child's map); then it plays the pre-rendered frames of
FRAMES.npz (`save_frames`) through the pipeline
`service.builder.build_pipeline` assembles, the map update on its own thread (tracking keeps
committing keyframes while the map update runs, as in the service), and writes one line per
event to stdout, flushed at once so the test sees it before the kill:

    IMPORTED
    READY <session id>
    K <node id>                 the keyframe is committed (add_keyframe returned)
    T <node id> <n>             the map update starts the n-th transfer (WM -> LTM) ...
    R <node id> <n>             ... or the n-th retrieval (LTM -> WM)
    HOLD <kind> <node id> <n> <point>
    DONE                        every frame processed, the session ended normally

With `--hold KIND N POINT` the map update stops in the N-th transfer (or retrieval): at its
start (`before`: nothing of it done) or once `Memory._transfer` / `_retrieve` has moved the
node's words and features but the working memory's bookkeeping has not recorded it yet
(`after`). It prints HOLD and waits there for the kill, tracking going on meanwhile.
Nothing is mocked: the memory moves are the real ones, only announced (and held) around.
"""
from __future__ import annotations

import json
import os
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

_out_lock = threading.Lock()


def emit(*words) -> None:
    """One line to stdout in one write (the tracking and the mapper thread both print)."""
    line = (" ".join(str(w) for w in words) + "\n").encode()
    with _out_lock:
        os.write(1, line)


def save_frames(path, frames, calibration) -> None:
    """Frames (image, depth, stamp) and the camera of a pinhole RGB-D calibration, for `load_frames`."""
    c = calibration.camera
    np.savez(path, images=np.stack([f.image for f in frames]), depths=np.stack([f.depth for f in frames]),
             stamps=np.array([f.stamp for f in frames], np.float64),
             camera=np.array([c.fx, c.fy, c.cx, c.cy, c.width, c.height, calibration.depth_scale], np.float64))


def load_frames(path):
    from mnemoslam.client.kernel.frames import Calibration, Frame, PinholeCamera

    data = np.load(path)
    fx, fy, cx, cy, w, h, depth_scale = data["camera"].tolist()
    calibration = Calibration(PinholeCamera(fx, fy, cx, cy, int(w), int(h)), None, depth_scale=depth_scale)
    images, depths, stamps = data["images"], data["depths"], data["stamps"]
    frames = (Frame(index=i, stamp=float(stamps[i]), image=images[i], depth=depths[i], source=f"crash#{i}")
              for i in range(len(stamps)))
    return calibration, frames


def instrument(hold: tuple[str, int, str] | None) -> None:
    """Announce every memory move of every mapper in this process; hold the chosen one."""
    from mnemoslam.service.memory.manager import Memory

    counts = {"transfer": 0, "retrieve": 0}
    originals = {"transfer": Memory._transfer, "retrieve": Memory._retrieve}

    def wrap(kind: str, tag: str):
        original = originals[kind]

        def move(self, node):
            counts[kind] += 1
            n = counts[kind]
            emit(tag, node, n)
            held = hold is not None and hold[0] == kind and hold[1] == n
            if held and hold[2] == "before":
                _hold(kind, node, n, "before")
            out = original(self, node)
            if held and hold[2] == "after":
                _hold(kind, node, n, "after")
            return out

        return move

    Memory._transfer = wrap("transfer", "T")
    Memory._retrieve = wrap("retrieve", "R")


def _hold(kind: str, node: int, n: int, point: str) -> None:
    emit("HOLD", kind, node, n, point)
    while True:  # until the SIGKILL
        time.sleep(60)


def main(argv: list[str]) -> int:
    db, frames_path, overrides = argv[0], argv[1], json.loads(argv[2])
    hold = None
    if len(argv) > 3:
        assert argv[3] == "--hold" and len(argv) == 7, argv
        hold = (argv[4], int(argv[5]), argv[6])
        assert hold[0] in ("transfer", "retrieve") and hold[2] in ("before", "after"), hold

    from mnemoslam.service.builder import build_pipeline
    from mnemoslam.service.config import load_config
    from mnemoslam.storage import MapStore

    instrument(hold)
    config = load_config(None, overrides)
    emit("IMPORTED")
    if not sys.stdin.readline():  # the test did not need this child after all
        return 0
    calibration, frames = load_frames(frames_path)
    with MapStore(db) as store:
        pipeline = build_pipeline(store, "crash", calibration, config, background=True)
        emit("READY", pipeline.session_id)
        for frame in frames:
            r = pipeline.process(frame)
            if r.node_id is not None:
                emit("K", r.node_id)
        pipeline.close()
    emit("DONE")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
