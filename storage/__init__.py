"""SQLite long-term memory (LTM) of the map: sessions, nodes (keyframes), links, features,
words, images and statistics in one file. See `storage.store` for the encodings and the
durability / threading guarantees, `storage.schema` for the tables and migrations."""
from .store import (
    KeyframeRecord,
    LinkRecord,
    LinkType,
    MapStore,
    NodeRecord,
    SessionRecord,
    StoreError,
    UnknownIdError,
)

__all__ = [
    "KeyframeRecord", "LinkRecord", "LinkType", "MapStore", "NodeRecord", "SessionRecord", "StoreError",
    "UnknownIdError",
]
