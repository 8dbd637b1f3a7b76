"""SQLite long-term memory (LTM) of the map (`mnemoslam.storage`): sessions, nodes (keyframes), links, features,
words, images and statistics in one file. See `store` for how `MapStore` is split by
concern, `records` for the encodings, `connection` for the durability /
threading guarantees, `schema` for the tables and migrations and
`repository` for the interface the service uses."""
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
