"""Visual words: `Words` stores the words a vocabulary creates with the word ids of a node's
features (`save_node_words`, one transaction, so a node never points at an unsaved word),
loads them (all, some, or with the inverted index rebuilt: `load_vocabulary_state`),
counts, deletes and prunes them. Encodings and checks are `storage.codec`'s;
transactions are `storage.connection`'s."""
from __future__ import annotations

import json
import sqlite3
import time
from collections.abc import Iterable

import numpy as np

from .codec import as_features, as_int, as_word_ids, pack
from .connection import Part
from .records import StoreError, UnknownIdError


class Words(Part):
    """The vocabulary's words and the nodes' word ids (the `MapStore` methods of those)."""

    def set_word_ids(self, node_id: int, word_ids: np.ndarray | None) -> None:
        """Attach (or clear) the visual-word id of each feature of a node."""
        nid = as_int(node_id, "node_id")
        blob = None
        if word_ids is not None:
            blob = pack(as_features(word_ids, "word_ids", np.int32, None), np.int32)
        with self.db.write("set_word_ids") as c:
            row = c.execute("SELECT count FROM features WHERE node_id = ?", (nid,)).fetchone()
            if row is None:
                raise UnknownIdError(f"no node {nid}")
            if word_ids is not None and len(word_ids) != row[0]:
                raise ValueError(f"{len(word_ids)} word_ids for the {row[0]} features of node {nid}")
            c.execute("UPDATE features SET word_ids = ? WHERE node_id = ?", (blob, nid))

    def save_node_words(self, node_id: int, word_ids: np.ndarray, new_word_ids: np.ndarray | None = None,
                        new_descriptors: np.ndarray | None = None) -> None:
        """Attach the visual-word id of each feature of a node (-1 = no word) and store the
        words the vocabulary created for it (`new_word_ids` (M,), `new_descriptors` M×32
        uint8), in one transaction. Every id ≥ 0 in `word_ids` must then be in `words`: a
        node never points at an unsaved word, even after a kill -9. Ids are never reused: a
        word id already stored is a StoreError, and the highest id ever stored is kept
        (admin `next_word_id`) so that pruning the newest words does not free their ids."""
        nid = as_int(node_id, "node_id")
        wid = as_word_ids(word_ids, "word_ids", -1)
        if (new_word_ids is None) != (new_descriptors is None):
            raise ValueError("new_word_ids and new_descriptors go together")
        new = np.zeros(0, np.int64) if new_word_ids is None else as_word_ids(new_word_ids, "new_word_ids", 0)
        desc = b""
        if new_descriptors is not None:
            d = as_features(new_descriptors, "new_descriptors", np.uint8, 32)
            if len(d) != len(new):
                raise ValueError(f"{len(d)} new_descriptors for {len(new)} new_word_ids")
            if len(np.unique(new)) != len(new):
                raise ValueError("new_word_ids has duplicates")
            desc = pack(d, np.uint8)
        used = np.unique(wid[wid >= 0])
        blob = pack(wid, np.int32)
        with self.db.write("save_node_words") as c:
            row = c.execute("SELECT count FROM features WHERE node_id = ?", (nid,)).fetchone()
            if row is None:
                raise UnknownIdError(f"no node {nid}")
            if len(wid) != row[0]:
                raise ValueError(f"{len(wid)} word_ids for the {row[0]} features of node {nid}")
            if len(new):
                ids = json.dumps(new.tolist())
                try:
                    # One statement: word j is bytes 32j..32j+31 of the descriptor blob.
                    c.execute("INSERT INTO words (id, descriptor, time_enter) "
                              "SELECT j.value, substr(?1, 32 * j.key + 1, 32), ?2 FROM json_each(?3) j",
                              (desc, time.time(), ids))
                except sqlite3.IntegrityError as e:
                    dup = [r[0] for r in c.execute(
                        "SELECT id FROM words WHERE id IN (SELECT value FROM json_each(?)) ORDER BY id LIMIT 10",
                        (ids,))]
                    raise StoreError(f"word id(s) {', '.join(map(str, dup))} already stored: word ids are never "
                                     "reused (two vocabularies writing to one map?); nothing written") from e
                c.execute("INSERT INTO admin (key, value) VALUES ('next_word_id', ?1) ON CONFLICT(key) DO UPDATE "
                          "SET value = MAX(CAST(value AS INTEGER), CAST(excluded.value AS INTEGER))",
                          (str(int(new.max()) + 1),))
            if len(used):
                ids = json.dumps(used.tolist())
                found = c.execute("SELECT COUNT(*) FROM words WHERE id IN (SELECT value FROM json_each(?))",
                                  (ids,)).fetchone()[0]
                if found != len(used):
                    have = {r[0] for r in c.execute(
                        "SELECT id FROM words WHERE id IN (SELECT value FROM json_each(?))", (ids,))}
                    missing = [w for w in used.tolist() if w not in have]
                    raise ValueError(f"node {nid} refers to {len(missing)} word(s) not in the map "
                                     f"({', '.join(map(str, missing[:10]))}{' …' if len(missing) > 10 else ''}): "
                                     "pass them as new_word_ids/new_descriptors; nothing written")
            c.execute("UPDATE features SET word_ids = ? WHERE node_id = ?", (blob, nid))

    def count_words(self) -> int:
        with self.db.read() as c:
            return c.execute("SELECT COUNT(*) FROM words").fetchone()[0]

    def load_words(self, word_ids: Iterable[int] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(ids (W,) int64 ascending, descriptors W×32 uint8) of the given (default: all)
        stored words; unknown ids are left out."""
        with self.db.read(snapshot=True) as c:
            if word_ids is None:
                return self._words(c)
            ids = np.unique(as_word_ids(word_ids, "word_ids", 0))
            return self._words(c, json.dumps(ids.tolist()))

    _WORD_CHUNK = 1 << 18  # words per aggregate query of the loader (8 MB of descriptors)

    def _words(self, c, only: str | None = None) -> tuple[np.ndarray, np.ndarray]:
        # One row per word in SQL, but never per word in Python: each chunk comes back as
        # one concatenated descriptor blob and one JSON array of ids (both aggregates see
        # the rows in the same order, so they line up whatever that order is).
        where = "" if only is None else "AND id IN (SELECT value FROM json_each(?3)) "
        sql = ("SELECT CAST(group_concat(descriptor, x'') AS BLOB), json_group_array(id), "
               "COALESCE(SUM(length(descriptor) != 32), 0) FROM "
               f"(SELECT id, descriptor FROM words WHERE id > ?1 {where}ORDER BY id LIMIT ?2)")
        ids, descs, last = [], [], -1
        while True:
            params = (last, self._WORD_CHUNK) if only is None else (last, self._WORD_CHUNK, only)
            blob, id_json, bad = c.execute(sql, params).fetchone()
            chunk = np.asarray(json.loads(id_json), np.int64)
            if not len(chunk):
                break
            if bad:
                raise StoreError(f"corrupt words table: {bad} descriptor(s) are not 32 bytes")
            ids.append(chunk)
            descs.append(np.frombuffer(blob, np.uint8).reshape(-1, 32))
            last = int(chunk.max())
            if len(chunk) < self._WORD_CHUNK:
                break
        if not ids:
            return np.zeros(0, np.int64), np.zeros((0, 32), np.uint8)
        all_ids, desc = np.concatenate(ids), np.concatenate(descs)
        if np.any(np.diff(all_ids) <= 0):
            order = np.argsort(all_ids, kind="stable")
            all_ids, desc = all_ids[order], desc[order]
        return all_ids, desc

    def next_word_id(self) -> int:
        """One past the highest word id ever stored (what a vocabulary that loads no words
        must hand out next: ids are never reused)."""
        with self.db.read(snapshot=True) as c:
            top = c.execute("SELECT MAX(id) FROM words").fetchone()[0]
            mark = c.execute("SELECT value FROM admin WHERE key = 'next_word_id'").fetchone()
        return max(0 if top is None else int(top) + 1, 0 if mark is None else int(mark[0]))

    def load_vocabulary_state(self) -> dict[str, np.ndarray]:
        """Everything `service.memory.vocabulary.Vocabulary.from_state` needs, from one snapshot:
        `word_ids` (W,) ascending and `descriptors` W×32 uint8 from `words`; the inverted
        index rebuilt from the nodes' `features.word_ids` (nodes without word ids are not
        indexed): `post_word`, `post_node`, `post_count` (one row per distinct (node, word),
        words missing from `words` left out), `node_ids` and `node_nfeat` (features with a
        word id ≥ 0); `next_id` (1,) = one past the highest word id ever stored or referenced."""
        with self.db.read(snapshot=True) as c:
            ids, desc = self._words(c)
            mark = c.execute("SELECT value FROM admin WHERE key = 'next_word_id'").fetchone()
            rows = c.execute("SELECT node_id, count, word_ids FROM features WHERE word_ids IS NOT NULL "
                             "ORDER BY node_id").fetchall()
        nodes = np.fromiter((r[0] for r in rows), np.int64, len(rows))
        counts = np.fromiter((r[1] for r in rows), np.int64, len(rows))
        blobs = [r[2] for r in rows]
        sizes = np.fromiter((len(b) for b in blobs), np.int64, len(blobs))
        bad = np.nonzero(sizes != 4 * counts)[0]
        if len(bad):
            i = int(bad[0])
            raise StoreError(f"corrupt word_ids of node {nodes[i]}: {sizes[i]} bytes for {counts[i]} features")
        w = np.frombuffer(b"".join(blobs), np.dtype("<i4")).astype(np.int64)
        n = np.repeat(nodes, counts)
        quantized = w >= 0
        nfeat = np.bincount(np.repeat(np.arange(len(nodes)), counts)[quantized], minlength=len(nodes))
        next_id = max(int(ids[-1]) + 1 if len(ids) else 0, int(w.max()) + 1 if len(w) else 0,
                      int(mark[0]) if mark is not None else 0)
        present = np.zeros(next_id, bool)
        present[ids] = True
        keep = quantized.copy()
        keep[quantized] = present[w[quantized]]
        key, post_count = np.unique((n[keep] << 32) | w[keep], return_counts=True)
        return {
            "word_ids": ids, "descriptors": desc,
            "post_word": key & 0xFFFFFFFF, "post_node": key >> 32, "post_count": post_count.astype(np.int64),
            "node_ids": nodes, "node_nfeat": nfeat.astype(np.int64),
            "next_id": np.array([next_id], np.int64),
        }

    def delete_words(self, word_ids: Iterable[int]) -> int:
        """Delete words (e.g. ones whose nodes are all gone); unknown ids are ignored. The
        caller makes sure no stored node still refers to them (`prune_words` checks it
        itself). Returns the number deleted."""
        ids = np.unique(as_word_ids(word_ids, "word_ids", 0))
        if not len(ids):
            return 0
        with self.db.write("delete_words") as c:
            return c.execute("DELETE FROM words WHERE id IN (SELECT value FROM json_each(?))",
                             (json.dumps(ids.tolist()),)).rowcount

    def prune_words(self) -> np.ndarray:
        """Delete every word no stored node refers to, in one transaction; returns their ids."""
        with self.db.write("prune_words") as c:
            (id_json,) = c.execute("SELECT json_group_array(id) FROM words").fetchone()
            ids = np.asarray(json.loads(id_json), np.int64)
            used = [np.frombuffer(r[0], np.dtype("<i4")) for r in
                    c.execute("SELECT word_ids FROM features WHERE word_ids IS NOT NULL")]
            orphans = ids[~np.isin(ids, np.concatenate(used) if used else np.zeros(0, np.int32))]
            if len(orphans):
                c.execute("DELETE FROM words WHERE id IN (SELECT value FROM json_each(?))",
                          (json.dumps(orphans.tolist()),))
        return orphans

