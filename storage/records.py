"""Records of the long-term memory: what goes in and comes out of the database. Owns the
errors (`StoreError`, `UnknownIdError`), `LinkType` and its names (`LINK_NAMES`,
`link_name`), the record dataclasses and the calibration's stored (dict) form. How they are
encoded in the file, the checks every write makes and the row decoders are
`storage.codec`'s.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from mnemoslam.client.kernel.frames import Calibration, PinholeCamera


class StoreError(Exception):
    """The database cannot do what was asked: missing or foreign file, newer schema,
    unknown id, constraint violation, locked or full disk. The message says which."""


class UnknownIdError(StoreError, KeyError):
    """A node or session id that is not in the database."""

    __str__ = Exception.__str__  # KeyError would quote the message


class LinkType(IntEnum):
    """RTAB-Map's Link.type values. Outside the database a type goes by its `label`
    (`LINK_NAMES`): REST, metrics, events, the viewer and the evaluation reports all use it."""

    NEIGHBOR = 0  # odometry between consecutive nodes
    GLOBAL_CLOSURE = 1  # appearance-based loop closure
    LOCAL_SPACE = 2  # proximity by space
    LOCAL_TIME = 3  # proximity by time: along the own path
    USER = 4  # user-added
    VIRTUAL = 5
    NEIGHBOR_MERGED = 6  # odometry across a node removed from the graph
    POSE_PRIOR = 7
    LANDMARK = 8
    MERGED = 10  # rehearsal: T_survivor_merged, from the node a keyframe was merged into (not RTAB-Map's)

    @property
    def label(self) -> str:
        """The type's public name (`LINK_NAMES`)."""
        return LINK_NAMES[self]

    @classmethod
    def from_label(cls, label: str) -> LinkType:
        """The type named `label` (`LINK_NAMES`); ValueError for an unknown name."""
        for t, name in LINK_NAMES.items():
            if name == label:
                return t
        raise ValueError(f"unknown link type {label!r} (one of {', '.join(LINK_NAMES.values())})")


# The one table of link-type names, one name per type: REST (graph links, database
# links_by_type), metrics (loop_closures_total{link}), the `loop_closed` event's `link`, the
# viewer and the evaluation reports (links.csv / links.json) all name a type by it.
LINK_NAMES: dict[LinkType, str] = {
    LinkType.NEIGHBOR: "odometry",  # between consecutive keyframes
    LinkType.GLOBAL_CLOSURE: "loop",  # loop closure by appearance
    LinkType.LOCAL_SPACE: "proximity",  # proximity by space
    LinkType.LOCAL_TIME: "path",  # proximity by time, along the own path
    LinkType.USER: "user",
    LinkType.VIRTUAL: "virtual",
    LinkType.NEIGHBOR_MERGED: "odometry_merged",
    LinkType.POSE_PRIOR: "pose_prior",
    LinkType.LANDMARK: "landmark",
    LinkType.MERGED: "merged",  # rehearsal's survivor -> merged keyframe
}
assert set(LINK_NAMES) == set(LinkType) and len(set(LINK_NAMES.values())) == len(LINK_NAMES)


def link_name(t: int) -> str:
    """The public name of link type `t` (`LINK_NAMES`); a type not in `LinkType` by its number."""
    try:
        return LINK_NAMES[LinkType(t)]
    except ValueError:
        return str(int(t))


# -- records --------------------------------------------------------------------------------


@dataclass
class SessionRecord:
    id: int
    robot: str
    map_id: int
    started_at: float  # wall time, seconds since the epoch
    ended_at: float | None
    calibration: Calibration
    config: dict | None
    # "stopped" (normal end), "idle", "restarted" (a camera restart), "crashed" (found open at
    # start-up), None while running
    end_reason: str | None = None

    def to_dict(self) -> dict:
        d = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        d["calibration"] = calibration_to_dict(self.calibration)
        return d


@dataclass
class NodeRecord:
    id: int
    session_id: int
    robot: str
    stamp: float
    pose: np.ndarray  # 4×4 float64 camera-to-world
    weight: int
    label: str | None
    merged_into: int | None = None  # the node rehearsal merged this keyframe into (None: a map node)

    @property
    def position(self) -> np.ndarray:
        return self.pose[:3, 3]


@dataclass
class LinkRecord:
    from_id: int
    to_id: int
    type: LinkType
    transform: np.ndarray  # 4×4 float64 T_from_to
    information: np.ndarray  # 6×6 float64


@dataclass
class KeyframeRecord:
    """Everything `add_keyframe` writes for one keyframe, in one transaction."""

    session_id: int
    stamp: float
    pose: np.ndarray  # 4×4 camera-to-world
    keypoints: np.ndarray  # (N, 2) float32
    descriptors: np.ndarray  # (N, 32) uint8
    points: np.ndarray  # (N, 3) float32, NaN rows = no depth
    weight: int = 0
    image_jpeg: bytes | None = None
    depth_png: bytes | None = None  # PNG-16, millimetres
    odom_link: tuple | None = None  # (from_id, T_from_to 4×4, information 6×6 | None)
    statistics: dict | None = None
    word_ids: np.ndarray | None = None  # (N,) int32, visual words of the features


@dataclass
class ObjectRecord:
    """A 3-D object of the semantic map (table `objects`). `centroid` is in the anchor
    node's camera frame; `position` (world, = anchor pose @ centroid) is filled by the
    reads and ignored by writes. `id` None = a new object (`save_objects` inserts it)."""

    id: int | None
    node_id: int  # anchor keyframe
    class_id: int  # argmax of `histogram`
    label: str  # the class's name
    confidence: float  # histogram[class_id]
    histogram: np.ndarray  # (K,) float32 posterior over the classes
    centroid: np.ndarray  # (3,) float64, anchor node's camera frame
    extent: np.ndarray  # (3,) float64 axis-aligned size in the map frame (m)
    observations: int  # keyframes that observed it
    keyframes: np.ndarray  # (≤ 64,) int64 ids of the most recent observing keyframes
    position: np.ndarray | None = None  # (3,) world position, read side only


#: How many observing keyframe ids an object keeps (the most recent).
MAX_OBJECT_KEYFRAMES = 64


def calibration_to_dict(c: Calibration) -> dict:
    """The stored (JSON) form of a calibration."""
    cam = c.camera
    d: dict[str, object] = {"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy, "width": cam.width,
                            "height": cam.height, "baseline": c.baseline, "depth_scale": c.depth_scale}
    if cam.distortion:  # (left out when none: older readers see the same form)
        d["distortion"] = list(cam.distortion)
    return d


def calibration_from_dict(d: dict) -> Calibration:
    """The calibration of its stored form (`calibration_to_dict`)."""
    cam = PinholeCamera(float(d["fx"]), float(d["fy"]), float(d["cx"]), float(d["cy"]),
                        int(d["width"]), int(d["height"]), tuple(float(v) for v in d.get("distortion") or ()))
    return Calibration(cam, None if d.get("baseline") is None else float(d["baseline"]),
                       float(d.get("depth_scale", 1000.0)))


#: Link types the map update (service.mapping.mapper.Mapper) writes; each goes *to* the keyframe being updated.
MAP_UPDATE_LINKS = (LinkType.GLOBAL_CLOSURE, LinkType.LOCAL_SPACE, LinkType.LOCAL_TIME)
