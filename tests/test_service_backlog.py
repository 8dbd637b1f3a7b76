"""Issue 24: a map update that falls behind tracking must not make the service's memory grow
with every keyframe it has not done yet (each RGB-D keyframe update is ~1.6 MB at 640x480,
97 % of it the depth and grey images)."""
from __future__ import annotations

import numpy as np

from mnemoslam.client.datasets import open_dataset
from mnemoslam.service.config import load_config
from mnemoslam.service.memory.keyframes import KeyframeWriter
from mnemoslam.service.pipeline import Pipeline
from mnemoslam.storage import MapStore


class StalledMapper:
    """A map update that never finishes one (a mapping child starved of CPU): it only keeps
    what it is handed, as the queue to the mapping process does."""

    def __init__(self):
        self.updates = []
        self.mapped = 0

    @property
    def submitted(self) -> int:
        return len(self.updates)

    def submit(self, update) -> None:
        self.updates.append(update)

    def to_map(self, pose):
        return pose

    def close(self) -> None:
        pass


def array_bytes(update) -> int:
    f = update.features
    return sum(a.nbytes for a in (f.keypoints, f.descriptors, f.points, f.octaves, f.depth, f.grey, f.depth_sigma)
               if isinstance(a, np.ndarray))


def test_map_backlog_keeps_images_of_a_bounded_number_of_keyframes(tmp_path):
    # 60 frames, a keyframe every 3 cm: 20 keyframes (120 frames at 5 cm gave ~40 and took twice as long)
    ds = open_dataset("synthetic:loop", max_frames=60)
    config = load_config(overrides={"loop": {"backlog_images": 4}, "keyframe": {"linear_update": 0.03}})
    mapper = StalledMapper()
    with MapStore(tmp_path / "map.db") as store:
        memory = KeyframeWriter(store, "r1", ds.calibration, config)
        pipeline = Pipeline(ds.calibration, config, memory, mapper, robot="r1")
        for i in range(len(ds)):
            pipeline.process(ds.frame(i))
        memory.close("stopped")
    n = len(mapper.updates)
    assert n > 12, f"only {n} keyframes: the test needs a backlog well beyond loop.backlog_images"
    with_images = [u for u in mapper.updates if u.features.depth is not None or u.features.grey is not None]
    assert len(with_images) == 4  # the first loop.backlog_images, then none while nothing is mapped
    assert pipeline.images_withheld == n - 4
    frame_bytes = ds.frame(0).depth.nbytes
    # what the backlog holds grows by the features only (tens of kB per keyframe), not by the images
    late = [array_bytes(u) for u in mapper.updates[4:]]
    assert max(late) < frame_bytes / 4
    assert all(u.features.points is not None and len(u.features.points) for u in mapper.updates)
