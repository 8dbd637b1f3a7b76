"""SQLite long-term memory (LTM) of the map: sessions, nodes (keyframes), links, features,
words, images, statistics and the semantic map's objects in one file. `MapStore`
(`storage.store`) opens it and is composed of one part per group of tables; `storage.roles`
has the small interfaces its callers depend on (`KeyframeLog` for tracking,
`MapUpdateStore` for the map update through memory, `MapReader` for the REST API, viewer
and metrics, ...). `storage.records` has the records and errors, `storage.codec` their
encodings, `storage.connection` the durability and threading guarantees, `storage.schema`
the tables and migrations. Nothing outside this package opens the file with sqlite3."""
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
from .roles import ApiStore, KeyframeLog, MapReader, MapUpdateStore, SemanticStore, WordStore
from .store import MapStore

__all__ = [
    "LINK_NAMES", "MAP_UPDATE_LINKS", "ApiStore", "KeyframeLog", "KeyframeRecord", "LinkRecord", "LinkType",
    "MapReader", "MapStore", "MapUpdateStore", "NodeRecord", "ObjectRecord", "SemanticStore", "SessionRecord",
    "StoreError", "UnknownIdError", "WordStore", "link_name",
]
