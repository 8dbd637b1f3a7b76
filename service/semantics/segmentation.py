"""Where a keyframe's per-pixel class labels come from: a `Segmenter` turns an RGB image into
an H×W label image (class ids into its `classes` table). `OnnxSegmenter` runs an ONNX
segmentation model through onnxruntime (the model adapter: input name, size, padding,
layout, dtype and output kind come from `SemanticsConfig`, so another model plugs in by
config with its own class list); `CameraLabels` takes the labels a camera sent with the
frame (`frame.extras["labels"]`). `make_segmenter` builds the configured one, or returns
None with the reason semantics are off (e.g. the model file is missing)."""
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

    def segment(self, rgb: np.ndarray) -> np.ndarray:
        """H×W uint8/uint16 class ids for an H×W×3 uint8 RGB image."""
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
        self.output = self.session.get_outputs()[0].name

    def segment(self, rgb: np.ndarray) -> np.ndarray:
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
        out = np.asarray(self.session.run([self.output], {self.input: x})[0])
        if c.model_output == "scores":  # 1×K×S×S or 1×S×S×K
            out = out.argmax(axis=1 if out.shape[1] == len(self.classes) else -1)
        labels = out.reshape(out.shape[-2:])[:nh, :nw]
        labels = np.clip(labels, 0, len(self.classes) - 1).astype(np.uint8 if len(self.classes) <= 256 else np.uint16)
        return cv2.resize(labels, (w, h), interpolation=cv2.INTER_NEAREST)


class CameraLabels:
    """The labels the camera sent with the frame (`frame.extras["labels"]`, class names in
    `extras["label_names"]` or the configured table)."""

    def __init__(self, config: SemanticsConfig):
        self.classes = class_table(config.classes)
        self.name = "camera"

    def segment(self, rgb: np.ndarray) -> np.ndarray:  # pragma: no cover - labels come with the frame
        raise RuntimeError("camera labels come with the frame; a keyframe without labels is skipped")


def make_segmenter(config: SemanticsConfig) -> tuple[Segmenter | None, str | None]:
    """(the configured segmenter, None) or (None, why semantics are off)."""
    if not config.enabled:
        return None, "semantics.enabled is false"
    if config.source == "camera":
        return CameraLabels(config), None
    if config.source != "model":
        return None, f"unknown semantics.source {config.source!r} (model | camera)"
    path = model_path(config.model)
    if not path.is_file():
        return None, f"model {path} not found (set semantics.model or MNEMOSLAM_MODELS)"
    try:
        return OnnxSegmenter(path, config), None
    except ImportError as e:
        return None, f"onnxruntime is not installed ({e})"
    except Exception as e:  # a broken or foreign model file
        return None, f"cannot load model {path}: {e}"


def semantics_status(config: SemanticsConfig) -> dict:
    """What `SlamService.semantics_status()` reports, without loading the model: {"enabled",
    "source", "model" (the model file, None for camera labels), "reason" (why off, or None),
    "classes"}. `enabled` is true only when the configured source can run."""
    classes = list(class_table(config.classes))
    model = str(model_path(config.model)) if config.source == "model" else None
    reason = None
    if not config.enabled:
        reason = "semantics.enabled is false"
    elif config.source not in ("model", "camera"):
        reason = f"unknown semantics.source {config.source!r} (model | camera)"
    elif config.source == "model":
        if not Path(model).is_file():
            reason = f"model {model} not found (set semantics.model or MNEMOSLAM_MODELS)"
        else:
            try:
                import onnxruntime  # noqa: F401
            except ImportError as e:
                reason = f"onnxruntime is not installed ({e})"
    return {"enabled": reason is None, "source": config.source, "model": model, "reason": reason, "classes": classes}
