"""The long-term memory by role: one small interface per kind of caller, each listing exactly
the `MapStore` methods that caller uses, with `MapStore`'s signatures (semantics, errors and
threading are `MapStore`'s: see its methods). Code that is handed a map depends on its role,
not on `MapStore`, so each caller's reach into the file is explicit and the store can change
behind it; `MapStore` implements every role (tests/test_storage.py checks the signatures).
Who opens the file (the server, recovery, the mapping child, the runner, `mnemoslam db`)
holds the `MapStore` itself.

- `KeyframeLog`: tracking's writes, a session and its keyframes, each committed before it
  is reported (`service.memory.keyframes.KeyframeWriter`).
- `WordStore`: the map's visual vocabulary, persisted with each keyframe
  (`service.memory.vocabulary.Vocabulary`).
- `MapUpdateStore`: the map update's reads and writes. Its one way to the store is memory
  (`service.memory.manager.Memory`, RTAB-Map's Memory, the only path to DBDriver), which
  the mapper (`service.mapping`) calls through methods.
- `SemanticStore`: the semantic worker's (`service.semantics.worker.SemanticWorker`):
  objects, which keyframes it took, the images it back-fills from.
- `GridStore`: the map's occupancy grid and cloud (`service.grid`), which also makes the grids
  of keyframes stored before grids were.
- `MapReader`: the readers' (REST API, viewer, metrics, the object index, evaluation):
  sessions, nodes, links, trajectories, statistics, objects, counts; nothing it calls writes.
  `ApiStore` adds the REST API's writes: a node's label, deleting an object.
"""
from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Protocol, runtime_checkable

import numpy as np

from mnemoslam.client.kernel.frames import Calibration
from mnemoslam.client.kernel.trajectory import Trajectory

from .connection import ChangeCounter
from .grids import LocalGridRecord
from .records import KeyframeRecord, LinkRecord, NodeRecord, ObjectRecord, SessionRecord


@runtime_checkable
class KeyframeLog(Protocol):
    """Tracking's writes: a session per robot stream and its keyframes."""

    def begin_session(self, robot: str, calibration: Calibration, config: dict | None = None) -> int: ...

    def end_session(self, session_id: int, reason: str = "stopped") -> None: ...

    def add_keyframe(self, rec: KeyframeRecord) -> int: ...

    def save_local_grids(self, grids: Iterable[LocalGridRecord]) -> int: ...


@runtime_checkable
class WordStore(Protocol):
    """The map's visual vocabulary: a node's word ids with the words created for it, and
    loading them back."""

    def save_node_words(self, node_id: int, word_ids: np.ndarray, new_word_ids: np.ndarray | None = None,
                        new_descriptors: np.ndarray | None = None) -> None: ...

    def load_words(self, word_ids: Iterable[int] | None = None) -> tuple[np.ndarray, np.ndarray]: ...

    def load_vocabulary_state(self) -> dict[str, np.ndarray]: ...

    def next_word_id(self) -> int: ...


@runtime_checkable
class MapUpdateStore(WordStore, Protocol):
    """The map update, through memory: the keyframes it takes from the store (features,
    images, odometry), what it retrieves from LTM, and its writes (links, rehearsal's merges,
    corrected poses, statistics last)."""

    # -- reads --------------------------------------------------------------------------------
    def calibration(self, session_id: int) -> Calibration: ...

    def get_node(self, node_id: int) -> NodeRecord | None: ...

    def get_nodes(self, node_ids: Iterable[int]) -> list[NodeRecord]: ...

    def node_ids(self, ended: bool | None = None, merged: bool | None = False) -> np.ndarray: ...

    def nodes(self, session_id: int | None = None, robot: str | None = None, bbox=None,
              limit: int | None = 100, offset: int = 0, merged: bool | None = None) -> list[NodeRecord]: ...

    def unmapped_nodes(self, session_ids: Iterable[int] | None = None,
                       end_reason: str | None = None) -> dict[int, list[int]]: ...

    def load_features(self, node_id: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]: ...

    def load_features_many(self, node_ids: Iterable[int]) -> dict[int, tuple[np.ndarray, np.ndarray, np.ndarray,
                                                                             np.ndarray | None]]: ...

    def load_images(self, node_id: int) -> tuple[bytes | None, bytes | None]: ...

    def links(self, session_id: int | None = None, node_ids: Iterable[int] | None = None,
              type: int | None = None) -> list[LinkRecord]: ...

    def link_pairs(self, types: Iterable[int] | None = None) -> np.ndarray: ...

    # -- writes -------------------------------------------------------------------------------
    def add_link(self, from_id: int, to_id: int, type: int, transform: np.ndarray,
                 information: np.ndarray | None = None, *, replace: bool = False) -> None: ...

    def add_links(self, links: Iterable[tuple], *, replace: bool = False) -> None: ...

    def merge_node(self, node_id: int, into_id: int, transform: np.ndarray, information: np.ndarray) -> int: ...

    def update_poses(self, poses: Mapping[int, np.ndarray]) -> int: ...

    def set_statistics(self, node_id: int, statistics: dict) -> None: ...


@runtime_checkable
class SemanticStore(Protocol):
    """The semantic worker's: the objects it fuses into, which keyframes it took, and the
    keyframes it back-fills from their stored images."""

    def objects(self, label: str | None = None) -> list[ObjectRecord]: ...

    def save_objects(self, objects: Iterable[ObjectRecord]) -> list[int]: ...

    def delete_objects(self, ids: Iterable[int]) -> int: ...

    def mark_segmented(self, node_ids: Iterable[int], source: str, status: str = "fused") -> int: ...

    def unsegmented_nodes(self, limit: int = 8) -> list[int]: ...

    def get_nodes(self, node_ids: Iterable[int]) -> list[NodeRecord]: ...

    def load_images(self, node_id: int) -> tuple[bytes | None, bytes | None]: ...

    def calibration(self, session_id: int) -> Calibration: ...

    def links_after(self, rowid: int = 0) -> tuple[int, np.ndarray]: ...


@runtime_checkable
class MapReader(Protocol):
    """The readers' (REST API, viewer, metrics, the object index, evaluation): reads only."""

    # -- sessions and the graph (REST, the object index's paths, evaluation) -------------------
    def sessions(self, robot: str | None = None) -> list[SessionRecord]: ...

    def session(self, session_id: int) -> SessionRecord | None: ...

    def get_node(self, node_id: int) -> NodeRecord | None: ...

    def get_nodes(self, node_ids: Iterable[int]) -> list[NodeRecord]: ...

    def nodes(self, session_id: int | None = None, robot: str | None = None, bbox=None,
              limit: int | None = 100, offset: int = 0, merged: bool | None = None) -> list[NodeRecord]: ...

    def count_nodes(self, session_id: int | None = None, robot: str | None = None, bbox=None,
                    merged: bool | None = None) -> int: ...

    def links(self, session_id: int | None = None, node_ids: Iterable[int] | None = None,
              type: int | None = None) -> list[LinkRecord]: ...

    def link_pairs(self, types: Iterable[int] | None = None) -> np.ndarray: ...

    def links_after(self, rowid: int = 0) -> tuple[int, np.ndarray]: ...

    def link_rows(self, rowid: int = 0) -> tuple[int, np.ndarray]: ...

    def node_sessions(self, after_id: int = 0) -> dict[str, np.ndarray]: ...

    def trajectory(self, session_id: int) -> Trajectory: ...

    def statistics(self, node_id: int) -> dict | None: ...

    def stats(self) -> dict: ...

    # -- the map update's progress (metrics, the viewer) -----------------------------------------
    def map_updates(self, session_id: int, after_node: int = 0) -> list[tuple]: ...

    def count_links(self, types: Iterable[int], session_id: int | None = None) -> dict[int, int]: ...

    def node_positions(self, session_id: int, after_id: int = 0) -> np.ndarray: ...

    def link_segments(self, types: Iterable[int], session_id: int, limit: int | None = None) -> list[tuple]: ...

    # -- the semantic map (REST's objects through the object index, metrics, the viewer) ---------
    def get_object(self, object_id: int) -> ObjectRecord | None: ...

    def object_arrays(self, label: str | None = None) -> dict[str, np.ndarray]: ...

    def segmentation_coverage(self) -> dict[str, int]: ...

    def change_counter(self) -> ChangeCounter: ...


@runtime_checkable
class ApiStore(MapReader, Protocol):
    """The REST API's (and its object index's): the readers' reads and an operator's two
    writes, naming a node and deleting an object (when no semantic worker runs)."""

    def set_label(self, node_id: int, label: str | None) -> None: ...

    def delete_objects(self, ids: Iterable[int]) -> int: ...


@runtime_checkable
class GridStore(Protocol):
    """The map's occupancy grid and cloud (`service.grid`): which nodes have local grids, the
    grids, the stored depth of keyframes written before grids were (their grid is made once,
    then saved), the links that join keyframes into maps (`MapConnectivity.refresh`), and the
    file's change counter (a request with nothing committed since reads no pose)."""

    def sessions(self, robot: str | None = None) -> list[SessionRecord]: ...

    def get_nodes(self, node_ids: Iterable[int]) -> list[NodeRecord]: ...

    def calibration(self, session_id: int) -> Calibration: ...

    def load_images(self, node_id: int) -> tuple[bytes | None, bytes | None]: ...

    def grid_nodes(self, has_grid: bool = True) -> dict[str, np.ndarray]: ...

    def local_grids(self, node_ids: Iterable[int]) -> dict[int, LocalGridRecord]: ...

    def nodes_without_grid(self, node_ids: Iterable[int] | None = None) -> list[int]: ...

    def save_local_grids(self, grids: Iterable[LocalGridRecord]) -> int: ...

    def links_after(self, rowid: int = 0) -> tuple[int, np.ndarray]: ...

    def change_counter(self) -> ChangeCounter: ...
