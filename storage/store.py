"""`MapStore`: the SQLite long-term memory (LTM) of the map.

One file holds every session of every robot (RTAB-Map's multi-session database). `MapStore`
is the one class that opens it; it is composed of one part per group of tables, all on its
one `Connection`:

- `storage.connection` (`Connection`): opening, pragmas, the writer connection and the
  reader pool, transactions, the background WAL checkpointer, migrations, the `admin`
  table, closing; the durability and threading guarantees.
- `storage.sessions` (`Sessions`): sessions (a map id each), their ends and calibrations.
- `storage.nodes` (`Nodes`): the graph's writes: keyframes, links, merges, poses, labels,
  statistics.
- `storage.queries` (`Queries`): the graph's reads: nodes, features, images, links,
  trajectories, statistics, counts; export.
- `storage.words` (`Words`): the vocabulary's words and the nodes' word ids.
- `storage.grids` (`Grids`): the keyframes' local occupancy grids (schema v7).
- `storage.objects` (`Objects`): the semantic map's 3-D objects and which keyframes it took.
- `storage.records` (the records, errors, `LinkType`) and `storage.codec` (their encodings,
  the checks every write does before touching the file, the row decoders).

Each method of `MapStore` is its part's (same signature and docstring), listed below by the
role that calls it; `storage.roles` has those roles as small interfaces (`KeyframeLog`,
`MapUpdateStore`, `SemanticStore`, `MapReader`, ...), which is what callers other than the
store's owner should depend on.
"""
from __future__ import annotations

import functools
from collections.abc import Callable
from pathlib import Path
from typing import Any, Concatenate, ParamSpec, Self, TypeVar

from . import schema
from .connection import Connection
from .grids import Grids
from .nodes import Nodes
from .objects import Objects
from .queries import Queries
from .sessions import Sessions
from .words import Words

P = ParamSpec("P")
R = TypeVar("R")


def _via(part: str, method: Callable[Concatenate[Any, P], R]) -> Callable[Concatenate[MapStore, P], R]:
    """A `MapStore` method that is `method` of its part `part` (same signature and docstring)."""

    def call(self: MapStore, *args: P.args, **kwargs: P.kwargs) -> R:
        return method(getattr(self, part), *args, **kwargs)

    functools.update_wrapper(call, method)
    call.__qualname__ = f"MapStore.{method.__name__}"
    return call


class MapStore:
    """The long-term memory in one SQLite file, composed of its parts (see the module
    docstring). See `storage.codec` for the encodings and `storage.connection` for the
    durability and threading guarantees."""

    #: MIGRATIONS[i] upgrades schema version i to i + 1; the current version is their count.
    MIGRATIONS: tuple[schema.Migration, ...] = schema.MIGRATIONS

    def __init__(self, path: str | Path, *, create: bool = True, busy_timeout: float = 10.0,
                 readonly: bool = False):
        self.db = Connection(path, create=create, busy_timeout=busy_timeout, migrations=self.MIGRATIONS,
                             readonly=readonly)
        self._sessions = Sessions(self.db)
        self._nodes = Nodes(self.db)
        self._queries = Queries(self.db)
        self._words = Words(self.db)
        self._objects = Objects(self.db)
        self._grids = Grids(self.db)

    # -- the file ------------------------------------------------------------------------------
    @property
    def path(self) -> Path:
        return self.db.path

    @property
    def closed(self) -> bool:
        return self.db.closed

    @property
    def readonly(self) -> bool:
        """Opened read-only (`readonly=True`: localization): every write is a StoreError and
        the file's bytes do not change."""
        return self.db.readonly

    @property
    def current_version(self) -> int:
        """The schema version this code writes (the number of migrations)."""
        return self.db.current_version

    @property
    def schema_version(self) -> int:
        """The schema version stored in the file."""
        return self.db.schema_version

    close = _via("db", Connection.close)
    checkpoint = _via("db", Connection.checkpoint)
    get_info = _via("db", Connection.get_info)
    set_info = _via("db", Connection.set_info)
    change_counter = _via("db", Connection.change_counter)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"MapStore({str(self.path)!r}{', closed' if self.closed else ''})"

    # -- the keyframe log (tracking: `roles.KeyframeLog`) ------------------------------------------
    begin_session = _via("_sessions", Sessions.begin_session)
    end_session = _via("_sessions", Sessions.end_session)
    add_keyframe = _via("_nodes", Nodes.add_keyframe)

    # -- the map update's writes (through service.memory: `roles.MapUpdateStore`) ---------------
    add_link = _via("_nodes", Nodes.add_link)
    add_links = _via("_nodes", Nodes.add_links)
    merge_node = _via("_nodes", Nodes.merge_node)
    update_poses = _via("_nodes", Nodes.update_poses)
    set_statistics = _via("_nodes", Nodes.set_statistics)
    delete_links = _via("_nodes", Nodes.delete_links)
    unmapped_nodes = _via("_queries", Queries.unmapped_nodes)
    end_open_sessions = _via("_sessions", Sessions.end_open_sessions)

    # -- visual words (the vocabulary: `roles.WordStore`) -------------------------------------------
    save_node_words = _via("_words", Words.save_node_words)
    load_words = _via("_words", Words.load_words)
    load_vocabulary_state = _via("_words", Words.load_vocabulary_state)
    next_word_id = _via("_words", Words.next_word_id)
    set_word_ids = _via("_words", Words.set_word_ids)
    count_words = _via("_words", Words.count_words)
    delete_words = _via("_words", Words.delete_words)
    prune_words = _via("_words", Words.prune_words)

    # -- reads of the graph (the map update, the readers: `roles.MapReader`) ---------------------
    sessions = _via("_sessions", Sessions.sessions)
    session = _via("_sessions", Sessions.session)
    calibration = _via("_sessions", Sessions.calibration)
    get_node = _via("_queries", Queries.get_node)
    get_nodes = _via("_queries", Queries.get_nodes)
    node_by_label = _via("_queries", Queries.node_by_label)
    node_ids = _via("_queries", Queries.node_ids)
    nodes = _via("_queries", Queries.nodes)
    count_nodes = _via("_queries", Queries.count_nodes)
    load_features = _via("_queries", Queries.load_features)
    load_features_many = _via("_queries", Queries.load_features_many)
    load_images = _via("_queries", Queries.load_images)
    statistics = _via("_queries", Queries.statistics)
    links = _via("_queries", Queries.links)
    link_pairs = _via("_queries", Queries.link_pairs)
    links_after = _via("_queries", Queries.links_after)
    link_rows = _via("_queries", Queries.link_rows)
    node_sessions = _via("_queries", Queries.node_sessions)
    count_links = _via("_queries", Queries.count_links)
    trajectory = _via("_queries", Queries.trajectory)
    map_updates = _via("_queries", Queries.map_updates)
    node_positions = _via("_queries", Queries.node_positions)
    link_segments = _via("_queries", Queries.link_segments)

    # -- the REST API's writes (`roles.ApiStore`) ---------------------------------------------------
    set_label = _via("_nodes", Nodes.set_label)

    # -- the semantic map (`roles.SemanticStore`; its reads: `roles.MapReader`) --------------------
    save_objects = _via("_objects", Objects.save_objects)
    delete_objects = _via("_objects", Objects.delete_objects)
    mark_segmented = _via("_objects", Objects.mark_segmented)
    unsegmented_nodes = _via("_objects", Objects.unsegmented_nodes)
    objects = _via("_objects", Objects.objects)
    get_object = _via("_objects", Objects.get_object)
    object_arrays = _via("_objects", Objects.object_arrays)
    count_objects = _via("_objects", Objects.count_objects)
    segmentation_coverage = _via("_objects", Objects.segmentation_coverage)

    # -- local occupancy grids (written with each keyframe: `roles.KeyframeLog`; the map's grid:
    # `roles.GridStore`) ---------------------------------------------------------------------------
    save_local_grids = _via("_grids", Grids.save_local_grids)
    local_grids = _via("_grids", Grids.local_grids)
    count_local_grids = _via("_grids", Grids.count_local_grids)
    grid_nodes = _via("_grids", Grids.grid_nodes)
    nodes_without_grid = _via("_grids", Grids.nodes_without_grid)

    # -- the whole file (`mnemoslam db`, REST's database summary) -----------------------------------
    stats = _via("_queries", Queries.stats)
    session_stats = _via("_sessions", Sessions.session_stats)
    file_bytes = _via("_queries", Queries.file_bytes)
    integrity_check = _via("_queries", Queries.integrity_check)
    export = _via("_queries", Queries.export)
