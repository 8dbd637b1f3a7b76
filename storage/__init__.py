"""SQLite long-term memory (LTM) of the map: sessions, nodes (keyframes), links, features,
words, images and statistics in one file. See `storage.store` for how `MapStore` is split by
concern, `storage.records` for the encodings, `storage.connection` for the durability /
threading guarantees, `storage.schema` for the tables and migrations and
`storage.repository` for the interface the service uses."""
from .grids import LocalGridRecord
from .records import (
    LINK_NAMES,
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
from .repository import MapRepository
from .store import MapStore

__all__ = [
    "LINK_NAMES", "KeyframeRecord", "LinkRecord", "LocalGridRecord", "LinkType",
    "MapRepository", "MapStore", "NodeRecord", "ObjectRecord",
    "SessionRecord", "StoreError", "UnknownIdError", "link_name",
]
