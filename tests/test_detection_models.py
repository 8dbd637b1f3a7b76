"""Detection models through the model adapter (issue 14): an ONNX detection model plugs in by
config (`semantics.model_output: boxes | yolo`, its own class list) and its boxes become
labels the fusion turns into objects. The ONNX models here are built in the test with the
`onnx` package (constant outputs: what a detector would answer), run by the real
onnxruntime; the box geometry is checked on the synthetic scene with a perfect detector
(the boxes of its instance masks)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mnemoslam.service.config import SemanticsConfig
from mnemoslam.service.semantics.objects import ObjectFusion
from mnemoslam.service.semantics.segmentation import OnnxSegmenter, make_segmenter, paint_boxes

onnx = pytest.importorskip("onnx")
from onnx import TensorProto, helper, numpy_helper  # noqa: E402

SIZE = 64  # the models' square input side
CLASSES = ["person", "door", "chair"]


def _model(path, outputs: dict, size: int = SIZE) -> str:
    """An ONNX model with a 1×size×size×3 uint8 input whose outputs are the given constants."""
    nodes, outs = [], []
    for name, value in outputs.items():
        arr = np.asarray(value, np.float32)
        nodes.append(helper.make_node("Constant", [], [name], value=numpy_helper.from_array(arr, f"{name}_value")))
        outs.append(helper.make_tensor_value_info(name, TensorProto.FLOAT, list(arr.shape)))
    inp = helper.make_tensor_value_info("image", TensorProto.UINT8, [1, size, size, 3])
    model = helper.make_model(helper.make_graph(nodes, "detector", [inp], outs),
                              opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.save(model, str(path))
    return str(path)


def _config(path, **kw) -> SemanticsConfig:
    return SemanticsConfig(enabled=True, source="model", model=path, model_input="image", model_size=SIZE,
                           classes=list(CLASSES), **kw)


def _assert_one_door(seg, rows: slice, cols: slice) -> None:
    """A 64×64 image's labels are door (1) at [rows, cols] and unlabelled elsewhere."""
    labels = seg.segment(np.zeros((64, 64, 3), np.uint8))
    expected = np.full((64, 64), len(CLASSES))
    expected[rows, cols] = 1
    np.testing.assert_array_equal(labels, expected)


def test_boxes_model_labels_its_boxes_in_image_pixels(tmp_path):
    """Boxes in model-input pixels come back to the image (128×96 resized by 0.5 into the
    64² input); low scores and class ids outside the table are ignored; a smaller box in
    front of a larger one keeps its class; pixels in no box are the out-of-table id."""
    path = _model(tmp_path / "det.onnx", {
        "boxes": [[[8, 8, 24, 40], [0, 0, 60, 44], [30, 2, 40, 12], [40, 30, 50, 40], [10, 10, 12, 12]]],
        "scores": [[0.9, 0.8, 0.3, 0.95, 0.99]],
        "classes": [[1, 2, 0, 7, -1]],
    })
    seg, reason = make_segmenter(_config(path, model_output="boxes"))
    assert reason is None and isinstance(seg, OnnxSegmenter)
    labels = seg.segment(np.zeros((96, 128, 3), np.uint8))
    assert labels.shape == (96, 128)
    assert (labels[16:80, 16:48] == 1).all()  # the door, painted over the chair's larger box
    chair = np.zeros((96, 128), bool)
    chair[0:88, 0:120] = True
    chair[16:80, 16:48] = False
    assert (labels[chair] == 2).all()
    assert (labels[88:, :] == len(CLASSES)).all() and (labels[:, 120:] == len(CLASSES)).all()
    assert not (labels == 0).any()  # the person scored 0.3 < min_score


def test_tf_style_boxes_normalized_yxyx_counting_from_one(tmp_path):
    path = _model(tmp_path / "tf.onnx", {
        "detection_boxes": [[[0.25, 0.5, 0.75, 1.0]]],  # ymin, xmin, ymax, xmax of the input
        "detection_scores": [[0.7]],
        "detection_classes": [[2]],  # door, counting from 1
    })
    seg, reason = make_segmenter(_config(path, model_output="boxes", box_format="yxyx", box_normalized=True,
                                         class_offset=-1,
                                         box_outputs=["detection_boxes", "detection_scores", "detection_classes"]))
    assert reason is None
    _assert_one_door(seg, slice(16, 48), slice(32, 64))


def test_yolo_output_is_suppressed_to_the_best_box(tmp_path):
    """One (4+K)×N output: centre, size and K class scores per candidate; overlapping
    candidates of one class leave the best (non-maximum suppression)."""
    cands = np.array([  # cx, cy, w, h, person, door, chair
        [20, 20, 16, 24, 0.0, 0.90, 0.1],
        [21, 21, 16, 24, 0.0, 0.80, 0.1],  # the same door, a worse score: suppressed
        [50, 50, 8, 8, 0.2, 0.10, 0.4],  # nothing scores 0.5
    ], np.float32)
    path = _model(tmp_path / "yolo.onnx", {"output0": cands.T[None]})
    seg, reason = make_segmenter(_config(path, model_output="yolo"))
    assert reason is None
    _assert_one_door(seg, slice(8, 32), slice(12, 28))


def test_a_misconfigured_detection_model_turns_semantics_off_with_the_reason(tmp_path):
    path = _model(tmp_path / "det.onnx", {"boxes": [[[0, 0, 1, 1]]], "scores": [[1.0]], "classes": [[0]]})
    seg, reason = make_segmenter(_config(path, model_output="boxes", box_outputs=["boxes", "scores", "labels"]))
    assert seg is None and "box_outputs" in reason and "'classes'" in reason  # the model's outputs, named
    seg, reason = make_segmenter(_config(path, model_output="masks"))
    assert seg is None and "model_output" in reason


def test_a_box_labels_the_object_at_its_depth_not_the_wall_behind():
    depth = np.full((40, 40), 4.0, np.float32)  # a wall at 4 m ...
    depth[10:30, 12:28] = 2.0  # ... a chair at 2 m in front of it
    depth[14, 14] = np.nan  # holes are never labelled
    depth[20, 20] = 0.0
    labels = paint_boxes(np.array([[8.0, 6.0, 32.0, 34.0]]), np.array([2]), (40, 40), 3, depth, 0.15)
    chair = np.zeros((40, 40), bool)
    chair[10:30, 12:28] = True
    chair[14, 14] = chair[20, 20] = False
    np.testing.assert_array_equal(labels == 2, chair)
    whole = paint_boxes(np.array([[8.0, 6.0, 32.0, 34.0]]), np.array([2]), (40, 40), 3, depth, 0.0)
    assert (whole[6:34, 8:32] == 2).all()  # band 0: the whole box


def test_a_perfect_detector_on_the_synthetic_scene_finds_the_doors():
    """Boxes around the synthetic scene's door instances (a perfect detector), painted at
    their depth and fused with the true poses: each door seen in ≥ 10 of the frames is one
    door object within 0.2 m of its centroid, and no door object is farther than 0.5 m
    from a true door (what the segmentation path is held to, tests/test_semantics.py)."""
    from conftest import LOOP_NOISY, synthetic

    door = 15
    ds = synthetic("loop", **LOOP_NOISY)  # the frames the session's loop runs play (rendered once)
    config = dataclasses.replace(SemanticsConfig(enabled=True), classes=["other", "door"])
    fusion = ObjectFusion(config.classes, config)
    true_doors = {o.instance_id: o for o in ds.scene.objects_of_class(door)}
    seen = dict.fromkeys(true_doors, 0)
    poses = {}
    for i in range(0, len(ds), 6):  # every 6th frame: ~100 keyframes
        f = ds.frame(i)
        inst, sem = f.extras["instances"], f.extras["labels"]
        boxes = []
        for iid in true_doors:
            ys, xs = np.nonzero((inst == iid) & (sem == door))
            if len(ys) >= 200:
                seen[iid] += 1
                boxes.append([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1])
        boxes = np.array(boxes, np.float64).reshape(-1, 4)
        labels = paint_boxes(boxes, np.ones(len(boxes), np.int64), f.depth.shape, 2, f.depth, config.box_depth_band)
        poses[i] = ds.ground_truth.poses[i]
        fusion.fuse(i, poses[i], labels, f.depth, ds.calibration.camera, poses)
    doors = np.array([poses[o.node_id][:3, :3] @ o.centroid + poses[o.node_id][:3, 3] for o in fusion.confirmed()
                      if fusion.record(o, poses[o.node_id]).label == "door"]).reshape(-1, 3)
    well_seen = [iid for iid, n in seen.items() if n >= 10]
    assert well_seen, seen
    errors = {true_doors[iid].name: float(np.linalg.norm(doors - true_doors[iid].center, axis=1).min())
              for iid in well_seen}
    print("door centroid errors (m):", {k: round(v, 3) for k, v in errors.items()}, "frames seen:", seen)
    assert max(errors.values()) <= 0.2, errors
    centres = np.array([o.center for o in true_doors.values()])
    assert max(np.linalg.norm(centres - d, axis=1).min() for d in doors) <= 0.5
