"""Where a keyframe's per-pixel class labels come from: a `Segmenter` turns an RGB image into
an H×W label image (class ids into its `classes` table). `OnnxSegmenter` runs an ONNX
segmentation or detection model through onnxruntime (the model adapter: input name, size,
padding, layout, dtype and output kind come from `SemanticsConfig`, so another model plugs in
by config with its own class list). A detection model's boxes become labels too: each box
paints its class over the pixels at the depth of the box's centre (`box_depth_band`), smaller
boxes over larger ones; pixels outside every box get the out-of-table id `len(classes)`
(never an object). `CameraLabels` takes the labels a camera sent with the
frame (`frame.extras["labels"]`). `make_segmenter` builds the configured one, or returns
None with the reason semantics are off (e.g. the model file is missing); with `source: auto`
(the default) the worker takes the camera's labels where a frame carries them and the model
(`LazyModel`, loaded when the service starts, or when first needed) for the rest."""
from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Protocol, runtime_checkable

import cv2
import numpy as np

from ..config import SemanticsConfig
from .classes import class_table

log = logging.getLogger("mnemoslam.semantics")

REPO = Path(__file__).resolve().parents[2]


@runtime_checkable
class Segmenter(Protocol):
    """Per-pixel class labels of an RGB image."""

    classes: tuple[str, ...]  # class names by id
    name: str

    def segment(self, rgb: np.ndarray, depth: np.ndarray | None = None) -> np.ndarray:
        """H×W uint8/uint16 class ids for an H×W×3 uint8 RGB image (and its depth in metres,
        which detection models use to keep a box's object apart from its background)."""
        ...


def models_dir() -> Path:
    """MNEMOSLAM_MODELS, default ../shared/models next to the repository."""
    return Path(os.environ.get("MNEMOSLAM_MODELS") or REPO.parent / "shared" / "models")


def model_path(name: str) -> Path:
    """The model file of `semantics.model`: a path (absolute, or with a directory part, as
    given) or a file name under `models_dir()`."""
    p = Path(name).expanduser()
    if p.is_absolute() or len(p.parts) > 1:
        return p
    return models_dir() / p


class OnnxSegmenter:
    """An ONNX semantic segmentation model through onnxruntime (CPU, `threads` intra-op
    threads). The image's longer side is resized to `model_size`, the rest padded with
    `model_pad` grey (the model's training pre-processing); the label map is cropped and
    resized back (nearest) to the image's size."""

    def __init__(self, path: str | Path, config: SemanticsConfig):
        import onnxruntime as ort

        self.path = Path(path)
        self.name = self.path.name
        self.config = config
        self.classes = class_table(config.classes)
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = max(1, int(config.threads))
        opts.inter_op_num_threads = 1
        opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        self.session = ort.InferenceSession(str(self.path), opts, providers=["CPUExecutionProvider"])
        inputs = {i.name: i for i in self.session.get_inputs()}
        self.input = config.model_input if config.model_input in inputs else next(iter(inputs))
        if self.input != config.model_input:
            log.warning("%s has no input %r; using %r", self.name, config.model_input, self.input)
        outputs = [o.name for o in self.session.get_outputs()]
        if config.model_output not in ("argmax", "scores", "boxes", "yolo"):
            raise ValueError(f"unknown semantics.model_output {config.model_output!r} (argmax | scores | boxes | yolo)")
        if config.model_output == "boxes":
            missing = [n for n in config.box_outputs if n not in outputs]
            if len(config.box_outputs) != 3 or missing:
                raise ValueError(f"semantics.box_outputs {list(config.box_outputs)} must name 3 of the model's outputs "
                                 f"{outputs} (boxes, scores, classes)")
            self.outputs = [str(n) for n in config.box_outputs]
        else:
            self.outputs = outputs[:1]
        if config.box_format not in ("xyxy", "yxyx", "cxcywh"):
            raise ValueError(f"unknown semantics.box_format {config.box_format!r} (xyxy | yxyx | cxcywh)")

    def segment(self, rgb: np.ndarray, depth: np.ndarray | None = None) -> np.ndarray:
        c = self.config
        h, w = rgb.shape[:2]
        s = int(c.model_size)
        scale = s / max(h, w)
        nh, nw = max(1, round(h * scale)), max(1, round(w * scale))
        x = np.full((s, s, 3), c.model_pad, np.uint8)
        x[:nh, :nw] = cv2.resize(rgb, (nw, nh), interpolation=cv2.INTER_LINEAR)
        if c.model_dtype == "float32":
            x = (x.astype(np.float32) - c.model_mean) * c.model_scale
        x = x[None]
        if c.model_layout == "nchw":
            x = np.ascontiguousarray(x.transpose(0, 3, 1, 2))
        outs = [np.asarray(o) for o in self.session.run(self.outputs, {self.input: x})]
        if c.model_output in ("boxes", "yolo"):
            boxes, classes = self._detections(outs)
            return paint_boxes(boxes / scale, classes, (h, w), len(self.classes), depth, c.box_depth_band)
        out = outs[0]
        if c.model_output == "scores":  # 1×K×S×S or 1×S×S×K
            out = out.argmax(axis=1 if out.shape[1] == len(self.classes) else -1)
        labels = out.reshape(out.shape[-2:])[:nh, :nw]
        labels = np.clip(labels, 0, len(self.classes) - 1).astype(np.uint8 if len(self.classes) <= 256 else np.uint16)
        return cv2.resize(labels, (w, h), interpolation=cv2.INTER_NEAREST)

    def _detections(self, outs: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """(N×4 xyxy boxes in model-input pixels, N class ids into `classes`) of the detections
        scoring at least `min_score`."""
        c, k = self.config, len(self.classes)
        if c.model_output == "boxes":
            boxes = outs[0].reshape(-1, 4).astype(np.float64)
            scores = outs[1].reshape(-1).astype(np.float64)
            ids = np.rint(outs[2].reshape(-1)).astype(np.int64)
        else:  # yolo: one (4+K)×N or N×(4+K) tensor, class = best score
            out = outs[0].reshape(outs[0].shape[-2:]).astype(np.float64)
            if out.shape[0] == 4 + k and out.shape[1] != 4 + k:
                out = out.T
            boxes, class_scores = out[:, :4], out[:, 4:]
            ids = class_scores.argmax(axis=1) if class_scores.shape[1] else np.zeros(len(out), np.int64)
            scores = class_scores.max(axis=1) if class_scores.shape[1] else np.zeros(len(out))
        n = min(len(boxes), len(scores), len(ids))
        boxes, scores, ids = boxes[:n], scores[:n], ids[:n] + int(c.class_offset)
        fmt = "cxcywh" if c.model_output == "yolo" else c.box_format
        if fmt == "yxyx":
            boxes = boxes[:, [1, 0, 3, 2]]
        elif fmt == "cxcywh":
            boxes = np.column_stack([boxes[:, :2] - boxes[:, 2:] / 2, boxes[:, :2] + boxes[:, 2:] / 2])
        if c.box_normalized:
            boxes = boxes * float(c.model_size)
        keep = (scores >= c.min_score) & (ids >= 0) & (ids < k) & np.isfinite(boxes).all(axis=1) \
            & (boxes[:, 2] > boxes[:, 0]) & (boxes[:, 3] > boxes[:, 1])
        boxes, scores, ids = boxes[keep], scores[keep], ids[keep]
        if c.model_output == "yolo" and len(boxes):  # raw candidates: non-maximum suppression per class
            xywh = np.column_stack([boxes[:, :2], boxes[:, 2:] - boxes[:, :2]])
            idx = np.asarray(cv2.dnn.NMSBoxesBatched(xywh.tolist(), scores.tolist(), ids.tolist(),
                                                     float(c.min_score), float(c.nms_iou)), np.int64).reshape(-1)
            boxes, ids = boxes[idx], ids[idx]
        return boxes, ids


def paint_boxes(boxes: np.ndarray, classes: np.ndarray, shape: tuple[int, int], k: int,
                depth: np.ndarray | None = None, band: float = 0.0) -> np.ndarray:
    """An H×W label image from detections (N×4 xyxy boxes in image pixels, N class ids < k):
    larger boxes first, so a smaller box in front wins; with `depth` and `band` > 0 a box
    labels only its pixels within `band` × the median depth of its central half (the
    detected object, not what is behind it or in front). Unlabelled pixels are `k`."""
    h, w = shape
    labels = np.full((h, w), k, np.uint8 if k < 256 else np.uint16)
    b = np.column_stack([np.floor(boxes[:, :2]), np.ceil(boxes[:, 2:])]).astype(np.int64) if len(boxes) else \
        np.zeros((0, 4), np.int64)
    b[:, [0, 2]] = b[:, [0, 2]].clip(0, w)
    b[:, [1, 3]] = b[:, [1, 3]].clip(0, h)
    area = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    for i in np.argsort(-area, kind="stable"):  # one array operation per detection (a few dozen)
        x0, y0, x1, y1 = b[i]
        if x1 <= x0 or y1 <= y0:
            continue
        region = labels[y0:y1, x0:x1]
        if depth is None or band <= 0:
            region[...] = classes[i]
            continue
        d = depth[y0:y1, x0:x1]
        valid = np.isfinite(d) & (d > 0)
        qh, qw = (y1 - y0) // 4, (x1 - x0) // 4
        centre = d[qh:y1 - y0 - qh, qw:x1 - x0 - qw][valid[qh:y1 - y0 - qh, qw:x1 - x0 - qw]]
        if centre.size == 0:
            continue  # no depth on the object: nothing to place in 3-D
        z = float(np.median(centre))
        region[valid & (np.abs(d - z) <= band * z)] = classes[i]
    return labels


class CameraLabels:
    """The labels the camera sent with the frame (`frame.extras["labels"]`, class names in
    `extras["label_names"]` or the configured table)."""

    def __init__(self, config: SemanticsConfig):
        self.classes = class_table(config.classes)
        self.name = "camera"

    # never called: labels come with the frame
    def segment(self, rgb: np.ndarray, depth: np.ndarray | None = None) -> np.ndarray:  # pragma: no cover
        raise RuntimeError("camera labels come with the frame; a keyframe without labels is skipped")


def make_segmenter(config: SemanticsConfig) -> tuple[Segmenter | None, str | None]:
    """(the configured segmenter, None) or (None, why semantics are off). With `source: auto`
    the model when it can run (a `LazyModel`: the service's worker loads it when it starts,
    `semantics.preload`; offline runs when first needed, so a camera sending labels never
    loads it), else the camera's labels alone (`model_reason` says why there is no model)."""
    if not config.enabled:
        return None, "semantics.enabled is false"
    if config.source == "camera":
        return CameraLabels(config), None
    if config.source not in ("model", "auto"):
        return None, f"unknown semantics.source {config.source!r} (auto | model | camera)"
    why = model_reason(config)
    if config.source == "auto":
        if why is not None:
            log.warning("semantics: only the camera's labels (no model: %s)", why)
            return CameraLabels(config), None
        return LazyModel(model_path(config.model), config), None
    if why is not None:
        return None, why
    try:
        return OnnxSegmenter(model_path(config.model), config), None
    except Exception as e:  # a broken or foreign model file
        return None, f"cannot load model {model_path(config.model)}: {e}"


def model_reason(config: SemanticsConfig) -> str | None:
    """Why the configured model cannot run (file missing, no onnxruntime), or None."""
    path = model_path(config.model)
    if not path.is_file():
        return f"model {path} not found (set semantics.model or MNEMOSLAM_MODELS)"
    try:
        import onnxruntime  # noqa: F401
    except ImportError as e:
        return f"onnxruntime is not installed ({e})"
    return None


class LazyModel:
    """`source: auto`'s model: an `OnnxSegmenter` built by `load()` (the service's semantic
    worker calls it when it starts, `semantics.preload`) or else on the first keyframe that
    needs it (one without the camera's labels). A model that cannot load raises then, every
    time."""

    def __init__(self, path: Path, config: SemanticsConfig):
        self.path, self.config = Path(path), config
        self.name = self.path.name
        self.classes = class_table(config.classes)
        self._model: OnnxSegmenter | None = None
        self._error: Exception | None = None

    @property
    def loaded(self) -> bool:
        return self._model is not None

    def load(self) -> OnnxSegmenter:
        """The model, loaded now if it is not yet (~0.1 s on an idle core, and part of it holds
        the GIL: better before a robot streams than on its first keyframe)."""
        if self._model is None:
            if self._error is not None:
                raise self._error
            try:
                self._model = OnnxSegmenter(self.path, self.config)
            except Exception as e:
                self._error = RuntimeError(f"cannot load model {self.path}: {e}")
                raise self._error from e
        return self._model

    def segment(self, rgb: np.ndarray, depth: np.ndarray | None = None) -> np.ndarray:
        return self.load().segment(rgb, depth)


def semantics_status(config: SemanticsConfig) -> dict:
    """What `SlamService.semantics_status()` reports, without loading the model: {"enabled",
    "source", "model" (the model file the service segments with, None when it has none),
    "reason" (why off, or None), "model_reason" (why there is no model, or None), "classes"}.
    `enabled` is true only when the configured source can run (`auto` always can: the
    camera's labels)."""
    classes = list(class_table(config.classes))
    why = model_reason(config) if config.source in ("model", "auto") else None
    model = str(model_path(config.model)) if config.source in ("model", "auto") and why is None else None
    reason = None
    if not config.enabled:
        reason = "semantics.enabled is false"
    elif config.source not in ("model", "camera", "auto"):
        reason = f"unknown semantics.source {config.source!r} (auto | model | camera)"
    elif config.source == "model":
        reason = why
    return {"enabled": reason is None, "source": config.source, "model": model, "reason": reason,
            "model_reason": why, "classes": classes}
