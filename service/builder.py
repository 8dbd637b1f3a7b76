"""One place that assembles a robot's SLAM session — memory, map update, pipeline — for the
offline runner (`mnemoslam run`) and the service (`serve`, and `demo` through it). How the map
update runs is the caller's choice: inline (offline runs stay reproducible), on a thread, or
in the service's mapping child process."""
from __future__ import annotations

import dataclasses
import logging
from typing import Callable

from mnemoslam.client.kernel.frames import Calibration
from mnemoslam.storage import MapStore

from .config import Config, ConfigError, SemanticsConfig
from .mapping.mapper import Mapper
from .mapping.process import MappingProcess
from .memory.keyframes import KeyframeWriter
from .pipeline import Pipeline
from .semantics.segmentation import make_segmenter
from .semantics.worker import SemanticWorker

log = logging.getLogger("mnemoslam.builder")


def build_semantics(store: MapStore, config: Config, *,
                    background: bool = False) -> tuple[SemanticWorker | None, str | None]:
    """The semantic worker of the map `store` when `config.semantics.enabled` (on its own
    thread with `background`, else inline), or None and why not (e.g. the model is missing).
    Semantics keys set while semantics end up off are named in a warning (they do nothing)."""
    segmenter, off = make_segmenter(config.semantics)
    if segmenter is None:
        unused = unused_semantics_keys(config.semantics)
        log.warning("semantics are off: %s%s", off, f" (set but unused: {', '.join(unused)})" if unused else "")
        return None, off
    worker = SemanticWorker(store, segmenter, config.semantics, background=background)
    log.info("semantics: source %s (%s)%s", worker.source, segmenter.name,
             ", back-fill from stored images" if worker.backfills else "")
    return worker, None


def unused_semantics_keys(config: SemanticsConfig) -> list[str]:
    """The `semantics.*` keys set to other than their defaults (but `enabled`)."""
    default = SemanticsConfig()
    return [f"semantics.{f.name}" for f in dataclasses.fields(SemanticsConfig)
            if f.name != "enabled" and getattr(config, f.name) != getattr(default, f.name)]


def with_distortion(calibration: Calibration, distortion: list[float] | None) -> Calibration:
    """The calibration with `features.distortion` (None: the source's; []: none; else the
    coefficients k1, k2, p1, p2[, k3[, k4, k5, k6]]) as its camera's lens distortion."""
    if distortion is None or tuple(distortion) == calibration.camera.distortion:
        return calibration
    try:
        camera = dataclasses.replace(calibration.camera, distortion=tuple(float(v) for v in distortion))
        out = dataclasses.replace(calibration, camera=camera)
    except (TypeError, ValueError) as e:
        raise ConfigError(f"features.distortion: {e}") from None
    log.info("lens distortion %s (features.distortion; the source said %s)", list(camera.distortion),
             list(calibration.camera.distortion))
    return out


def build_pipeline(store: MapStore, robot: str, calibration: Calibration, config: Config, *,
                   mapping: MappingProcess | None = None, background: bool = False,
                   on_event: Callable[[str, dict], None] | None = None,
                   semantics: tuple[SemanticWorker | None, str | None] | None = None,
                   incremental: bool = True) -> Pipeline:
    """A new session of `robot` in the map `store`: its keyframe writer (a session in the database), its
    map update when `config.loop.enabled` (in `mapping`'s child process when given, else a
    Mapper on its own thread with `background`, else inline) reporting to `on_event(kind,
    data)`, its semantic worker (`semantics`: the map's shared (worker, why off) from
    `build_semantics`, which the caller closes; else one of its own, see `build_semantics`,
    that the pipeline closes), and the pipeline over them. End it with `Pipeline.close()`.

    Localization only (`incremental` false, or `memory.incremental` false): nothing of the
    robot is written to the map (`service.localization`): no session, its keyframes kept in
    RAM (`TransientKeyframes`), its map update a `Localizer` (on its own thread with
    `background`, never in `mapping`'s child), no semantics."""
    calibration = with_distortion(calibration, config.features.distortion)
    if not (incremental and config.memory.incremental):
        from .localization import Localizer, TransientKeyframes

        localizer = Localizer(calibration.camera, config.loop, store, on_event=on_event, background=background,
                              memory=config.memory) if config.loop.enabled else None
        return Pipeline(calibration, config, TransientKeyframes(), localizer, None,
                        "localization only: nothing is written to the map", robot=robot, owns_semantics=False)
    writer = KeyframeWriter(store, robot, calibration, config)
    mapper = None
    if config.loop.enabled:
        if mapping is not None:
            mapper = mapping.mapper(robot, calibration.camera, on_event)
        else:
            mapper = Mapper(calibration.camera, config.loop, store, on_event=on_event, background=background,
                            memory=config.memory)
    owned = semantics is None
    worker, off = build_semantics(store, config, background=background) if owned else semantics
    return Pipeline(calibration, config, writer, mapper, worker, off, robot=robot, owns_semantics=owned)
