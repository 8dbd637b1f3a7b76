"""The dense views of keyframes in RAM (depth and grey image, reduced), which dense
registration (`service.mapping.verification`) refines links with: `DenseView`, and
`StoredViews`, the memory's cache of them, which decodes a stored keyframe's view from its
stored images when it is first needed."""
from __future__ import annotations

import collections
import logging
import threading

import cv2
import numpy as np

from mnemoslam.client.kernel.frames import PinholeCamera
from mnemoslam.storage import MapUpdateStore

from ..tracking import icp
from .keyframes import decode_images

log = logging.getLogger("mnemoslam.memory")


LEVELS_KEPT = 16  # dense views (per process) whose registration pyramid stays built: the last ones registered


class DenseView:
    """What dense registration needs of a keyframe, kept small: its depth and grey image
    reduced `factor` times (a 640×480 frame keeps 160×120, ~150 kB instead of 1.5 MB).
    The reduced images give exactly the coarse pyramid levels `icp.depth_pyramid` builds
    from the full ones (depth sampled every `factor` pixels, grey by Gaussian pyramid).

    `levels()` builds the pyramid once and keeps it while the view is among the LEVELS_KEPT
    views of the process registered last (~2 MB each at 160×120 with what registration derives
    from them): a map update registers its keyframe with several candidates (its path, the
    nearest keyframes, a loop), and the recent path's keyframes are candidates again in the next
    updates, so that each pyramid was built ~4 times. Registration only reads the levels (their
    derived arrays are memoised on them), so a kept pyramid is the one building it again gives."""

    _recent: collections.OrderedDict[int, DenseView] = collections.OrderedDict()
    _recent_lock = threading.Lock()

    def __init__(self, depth: np.ndarray, grey: np.ndarray, camera: PinholeCamera, factor: int = 4):
        if factor & (factor - 1) or factor > min(icp.STEPS):
            raise ValueError(f"factor must be a power of two <= {min(icp.STEPS)}, got {factor}")
        g = np.asarray(grey)
        if g.ndim == 3:
            g = cv2.cvtColor(g, cv2.COLOR_BGR2GRAY)
        g = g.astype(np.float32) / 255.0 if g.dtype == np.uint8 else g.astype(np.float32)
        f = 1
        while f < factor:
            g, f = cv2.pyrDown(g), f * 2
        self.depth = np.ascontiguousarray(depth[::factor, ::factor], dtype=np.float32)
        self.grey = g[: self.depth.shape[0], : self.depth.shape[1]]
        self.camera = PinholeCamera(camera.fx / factor, camera.fy / factor, camera.cx / factor,
                                    camera.cy / factor, self.depth.shape[1], self.depth.shape[0],
                                    camera.distortion)  # (normalized coefficients: any image scale)
        self.steps = tuple(s // factor for s in icp.STEPS)
        self.factor = factor
        self._levels: list | None = None

    def levels(self) -> list:
        """The registration pyramid of the view (`icp.depth_pyramid`), kept while the view is
        among the LEVELS_KEPT registered last."""
        recent = DenseView._recent
        with DenseView._recent_lock:
            levels = self._levels
            if levels is not None:
                recent.move_to_end(id(self))
                return levels
        levels = icp.depth_pyramid(self.depth, self.camera, self.steps, grey=self.grey)
        with DenseView._recent_lock:
            if self._levels is None:
                self._levels = levels
                recent[id(self)] = self
                while len(recent) > LEVELS_KEPT:
                    recent.popitem(last=False)[1]._levels = None
            return self._levels


class StoredViews(dict):
    """Dense views ({node: DenseView}) of which those of stored keyframes are decoded from
    their stored images when first asked for (`in` or `[]`), so that a resumed session or a
    retrieved node costs a decode only when it becomes a loop candidate."""

    def __init__(self, store: MapUpdateStore, camera: PinholeCamera):
        super().__init__()
        self._store, self._camera = store, camera
        self._stored: set[int] = set()

    def defer(self, node_id) -> None:
        """Decode this node's view from the store when it is first asked for."""
        if not super().__contains__(node_id):
            self._stored.add(node_id)

    def pop(self, node_id, default=None):
        self._stored.discard(node_id)
        return super().pop(node_id, default)

    def _load(self, node_id) -> None:
        if node_id not in self._stored:
            return
        self._stored.discard(node_id)
        try:
            image, depth = decode_images(*self._store.load_images(node_id))
        except Exception as e:  # a bad image costs the dense refinement of this keyframe only
            log.warning("node %d: stored images not usable for dense registration: %s", node_id, e)
            return
        if image is not None and depth is not None:
            self[node_id] = DenseView(depth, image, self._camera)

    def __contains__(self, node_id) -> bool:
        self._load(node_id)
        return super().__contains__(node_id)

    def __getitem__(self, node_id):
        self._load(node_id)
        return super().__getitem__(node_id)
