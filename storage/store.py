"""`MapStore`: the SQLite long-term memory (LTM) of the map.

One file holds every session of every robot (RTAB-Map's multi-session database). `MapStore`
is the one class callers use; it is composed of one class per concern, all on the same
connection:

- `storage.connection` (`Connection`): opening, pragmas, the writer connection and the
  reader pool, transactions, the background WAL checkpointer, migrations, closing; the
  durability and threading guarantees.
- `storage.records`: the records, errors, `LinkType`, the encodings (blobs, JSON) and the
  validation every write does before touching the file.
- `storage.nodes` (`Nodes`): sessions, keyframes, links, poses, labels, statistics.
- `storage.words` (`Words`): the vocabulary's words and the nodes' word ids.
- `storage.queries` (`Queries`): reads of nodes, links, trajectories, statistics; export.
- `storage.objects` (`Objects`): the semantic map's 3-D objects (anchored to keyframes).
- `storage.grids` (`Grids`): the keyframes' local occupancy grids.

`storage.repository.MapRepository` lists the methods the service uses.
"""
from __future__ import annotations

from .grids import Grids
from .nodes import Nodes
from .objects import Objects
from .queries import Queries
from .records import MAP_UPDATE_LINKS, StoreError, _pack, _unpack  # noqa: F401 (imported from here before the split)
from .words import Words


class MapStore(Nodes, Words, Queries, Objects, Grids):
    """The long-term memory in one SQLite file. See `storage.records` for the encodings and
    `storage.connection` for the durability and threading guarantees."""

    def __repr__(self) -> str:
        return f"MapStore({str(self.path)!r}{', closed' if self.closed else ''})"
