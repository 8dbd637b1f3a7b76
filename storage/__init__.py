"""SQLite long-term memory (LTM) of the map (`mnemoslam.storage`): sessions, nodes (keyframes),
links, features, words, images, statistics, the semantic map's objects and the keyframes' local
occupancy grids in one file. `MapStore` (`store`) opens it and is composed of one part per
group of tables; `roles` has the small interfaces its callers depend on (`KeyframeLog` for
tracking, `MapUpdateStore` for the map update through memory, `MapReader` for the REST API,
viewer and metrics, `GridStore` for the occupancy grid, ...). `records` has the records and
errors, `codec` their encodings, `connection` the durability and threading guarantees,
`schema` the tables and migrations. Nothing outside this package opens the file with sqlite3."""
from .grids import LocalGridRecord
from .records import (
    LINK_NAMES,
    MAP_UPDATE_LINKS,
    KeyframeRecord,
    LinkRecord,
    LinkType,
    NodeRecord,
    ObjectRecord,
    SessionRecord,
    StoreError,
    UnknownIdError,
    link_name,
)
from .roles import ApiStore, GridStore, KeyframeLog, MapReader, MapUpdateStore, SemanticStore, WordStore
from .store import MapStore

__all__ = [
    "LINK_NAMES", "MAP_UPDATE_LINKS", "ApiStore", "GridStore", "KeyframeLog", "KeyframeRecord", "LinkRecord",
    "LinkType", "LocalGridRecord", "MapReader", "MapStore", "MapUpdateStore", "NodeRecord", "ObjectRecord",
    "SemanticStore", "SessionRecord", "StoreError", "UnknownIdError", "WordStore", "link_name",
]
