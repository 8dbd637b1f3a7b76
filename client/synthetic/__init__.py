"""The synthetic indoor scene camera: the backbone of the tests and of the demo.

A living room, an office and a hall (world z up, metres) built from axis-aligned quads and
boxes with procedural, seed-deterministic textures, ray-cast exactly into RGB (BGR uint8),
depth (z in metres), semantic labels (ADE20K-32 class ids, `CLASS_NAMES`) and object
instance ids. Camera paths ("loop", "figure8", "walk_a", "walk_b", "straight"; "fastrot", a
handheld look-around at up to 60°/s per axis) and a `Dataset` player on top, with optional
depth noise (`noise=True`/"axial", or "kinect": `kinect.py`) and motion blur (`exposure`,
`blur.py`) and, as an option, a person walking through it (`person=True`, `person.py`):

    from mnemoslam.client.synthetic import SyntheticDataset, SyntheticScene, get_scene, trajectory
    ds = SyntheticDataset("loop", rate=30, noise=True)          # or open_dataset("synthetic:loop")
    f = ds.frame(0); f.image, f.depth, f.extras["labels"], ds.ground_truth.poses[0]
    r = get_scene(0).render(pose_c2w, camera)                    # r.rgb r.depth r.labels r.instances
    doors = get_scene(0).objects_of_class(15)                    # SceneObject(bbox_min, bbox_max, ...)
"""
from .dataset import SyntheticDataset, add_depth_noise, add_rgb_noise, depth_sigma
from .person import Person, Walk
from .raster import RenderResult
from .scene import CLASS_NAMES, DOORWAYS, ROOMS, SceneObject, SyntheticScene, get_scene, render
from .trajectories import TRAJECTORIES, CameraPath, trajectory

__all__ = [
    "SyntheticDataset", "SyntheticScene", "SceneObject", "RenderResult", "CLASS_NAMES", "ROOMS", "DOORWAYS",
    "TRAJECTORIES", "CameraPath", "trajectory", "get_scene", "render", "depth_sigma", "add_depth_noise",
    "add_rgb_noise", "Person", "Walk",
]
