"""Start-up on a reopened map (issue 11): a new session's mapper puts the previous map's nodes
in LTM (ids only) and the newest `memory.max_wm_nodes` of them in WM (RTAB-Map's
loadLastNodes), loads only their words, and can close loops to yesterday's map."""
import numpy as np
import pytest

from mnemoslam.service.builder import build_pipeline
from mnemoslam.service.evaluation import evaluate
from mnemoslam.service.mapping.mapper import Mapper
from mnemoslam.service.memory.vocabulary import Vocabulary
from mnemoslam.storage import LinkType, MapStore

from conftest import WALK_A, slam_config, synthetic

WM = 5
LOOPS = (LinkType.GLOBAL_CLOSURE, LinkType.LOCAL_SPACE, LinkType.MERGED)  # merged: rehearsal into an old node


def _session(db, ds, cfg):
    with MapStore(db) as store:
        pipeline = build_pipeline(store, ds.name, ds.calibration, cfg)  # map update inline
        results = [pipeline.process(ds.frame(i)) for i in range(len(ds))]
        pipeline.close()
        return pipeline.session_id, [r.node_id for r in results if r.node_id is not None]


@pytest.fixture(scope="module")
def first(tmp_path_factory):
    """One walk of walk_a (unlimited WM), the map closed: yesterday's map."""
    # rendered once for the session (tests/conftest.py): tests/test_rehearsal.py plays the same frames
    ds = synthetic("walk_a", **WALK_A)
    db = tmp_path_factory.mktemp("startup") / "map.db"
    sid, ids = _session(db, ds, _cfg())
    return {"ds": ds, "db": db, "sid": sid, "ids": ids}


def _cfg(**memory):
    """The default configuration with semantics and the occupancy grid off (tests/conftest.py
    `slam_config`): these tests check the memory's tiers, words, links and poses, which neither
    changes."""
    return slam_config({"memory": memory, "grid": {"enabled": False}})


def test_a_new_session_starts_with_the_last_nodes_in_wm_and_the_others_in_ltm(first):
    ids = first["ids"]
    assert len(ids) > 2 * WM
    cfg = _cfg(max_wm_nodes=WM)
    with MapStore(first["db"]) as store:
        m = Mapper(first["ds"].calibration.camera, cfg.loop, store, memory=cfg.memory)
        assert m.memory.tiers.wm == ids[-WM:] and not m.memory.tiers.stm
        assert m.memory.tiers.ltm == set(ids[:-WM])
        # only WM's features, words and graph nodes are in RAM, WM at the stored poses
        assert set(m.memory.features) == set(ids[-WM:]) == set(m.vocabulary.node_ids()) == set(m.graph.poses())
        stored = {n.id: n.pose for n in store.get_nodes(ids)}
        assert all(np.array_equal(m.graph.pose(n), stored[n]) for n in ids[-WM:])
        used = np.unique(np.concatenate([store.load_features(n)[3] for n in ids[-WM:]]))
        used = used[used >= 0]
        assert len(m.vocabulary) == len(used) and m.vocabulary.dormant == 0
        full = Vocabulary.from_store(store)
        assert len(full) > len(used)
        assert np.array_equal(m.vocabulary.descriptors(used), full.descriptors(used))
        assert m.vocabulary._next_id == full._next_id  # new words get new ids
        for n in ids[-WM:]:  # the same postings as in the whole vocabulary
            assert all(np.array_equal(a, b) for a, b in zip(m.vocabulary.node_words(n), full.node_words(n)))
        # the old nodes' graph adjacency is there for the prediction and retrieval
        assert ids[0] in m.memory.neighbours and ids[1] in m.memory.neighbours[ids[0]]

        # an old LTM node comes back: features, words, a graph node at its stored pose
        old = ids[2]
        assert m.retrieve([old]) == [old]
        assert m.memory.tiers.in_wm(old) and old in m.vocabulary and old in m.memory.features
        assert np.array_equal(m.graph.pose(old), stored[old])
        assert m.vocabulary.node_words(old)[0].tolist() == full.node_words(old)[0].tolist()
        assert m.memory.tiers.weights[old] == store.get_node(old).weight


def test_an_unlimited_wm_loads_the_whole_map_as_before(first):
    ids = first["ids"]
    cfg = _cfg()
    with MapStore(first["db"]) as store:
        m = Mapper(first["ds"].calibration.camera, cfg.loop, store, memory=cfg.memory)
        assert m.memory.tiers.wm == ids and not m.memory.tiers.ltm
        a, b = m.vocabulary.state(), Vocabulary.from_store(store).state()
        assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)


def test_a_second_session_closes_loops_to_the_first_sessions_map(first, tmp_path):
    """The same walk again, WM of 5: the old map's nodes come back from LTM and the new session
    links to them, which places it in the old map's frame."""
    import shutil
    db = tmp_path / "map.db"
    shutil.copy(first["db"], db)
    ds, old = first["ds"], set(first["ids"])
    sid, ids = _session(db, ds, _cfg(max_wm_nodes=WM))
    with MapStore(db) as store:
        stats = [store.statistics(n) for n in ids]
        links = [lk for lk in store.links(session_id=sid) if lk.type in LOOPS]
        trajectory, before = store.trajectory(sid), store.trajectory(first["sid"])
    retrieved = {n for st in stats for n in st["memory"]["retrieved"]}
    assert retrieved & old
    to_old = [lk for lk in links if lk.from_id in old and lk.to_id in set(ids)]
    assert len(to_old) >= 3, (len(links), len(to_old))
    assert max(st["memory"]["wm"] for st in stats) <= WM + 2  # + nodes linked to STM / the loop node
    # in the old map's frame, as accurate (measured: 2.1 cm from the old keyframes unaligned since the
    # session joins by appearance only (issue 22); 7.8 mm when proximity joined it by coordinates, which
    # coincide here by construction: both sessions start at the identity, at the same place)
    assert evaluate(before, trajectory, align="none").ate_rmse < 0.03
    assert evaluate(ds.ground_truth, trajectory).ate_rmse < evaluate(ds.ground_truth, before).ate_rmse + 0.005
