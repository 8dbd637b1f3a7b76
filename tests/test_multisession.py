"""Issue 22: a second session joins the map by appearance, never by coordinates.

The synthetic `walk_a`, then `walk_b` into the same map database, offline. B starts more than
2 m from where A started and the two walks share the living room -> doorway stretch. Each
session's frame starts at the identity, so B's coordinates coincide numerically with A's
without meaning anything there: before the fix, proximity search joined B to A's map at its
4th keyframe by those coordinates (a dense link from the graph's pose, 2.75 m off the truth),
and B's whole trajectory lay 2.76 m off in A's frame. Now proximity, path and rehearsal stay
inside a map (`Memory.same_map`); B joins by an appearance hypothesis once it walks
A's stretch, and then lies in A's frame."""
import numpy as np
import pytest

from mnemoslam.client.datasets import open_dataset
from mnemoslam.client.kernel.geometry import invert, rotation_angle
from mnemoslam.service.builder import build_pipeline
from mnemoslam.storage import LinkType, MapStore
from mnemoslam.storage.connectivity import MapIndex

from conftest import run_cli as _run
from conftest import slam_config

RATE = 5.0  # frames/s of each walk (36 and 38 s)
BOUND_JOIN_M = 0.5  # m of B's path after the overlap before it joins (measured -0.08 m: 5 keyframes before it)


@pytest.fixture(scope="module")
def two_walks(cli_walks):
    """walk_a, then walk_b into one map (`cli_walks`' run, read from its file): each walk's ground
    truth and keyframes (node id, frame index), every node's final pose and the links as stored."""
    _, db, _ = cli_walks
    walks = {}
    with MapStore(db, create=False) as store:
        for session, name in ((1, "walk_a"), (2, "walk_b")):
            gt = open_dataset(f"synthetic:{name}", rate=RATE).ground_truth
            nodes = store.nodes(session_id=session, limit=None, merged=None)
            index = np.searchsorted(gt.stamps, [n.stamp for n in nodes])
            assert np.allclose(gt.stamps[index], [n.stamp for n in nodes])
            walks[name] = (gt, sorted(zip((n.id for n in nodes), index.tolist())))
        poses = {n.id: n.pose for n in store.nodes(limit=None, merged=None)}
        links = store.links()
        stored = {tuple(r): i for i, r in enumerate(store.link_rows()[1].tolist())}  # (from, to, type) -> order
        links.sort(key=lambda lk: stored.get((lk.from_id, lk.to_id, int(lk.type)), len(stored)))  # as stored
    return walks, poses, links


def _truth(walks):
    owner = {n: (gt, i) for gt, kfs in walks.values() for n, i in kfs}
    return owner


def test_sessions_join_only_where_they_share_a_place_and_correctly(two_walks):
    walks, poses, links = two_walks
    a_nodes = {n for n, _ in walks["walk_a"][1]}
    b_nodes = [n for n, _ in walks["walk_b"][1]]
    truth = _truth(walks)
    cross = [lk for lk in links if (lk.from_id in a_nodes) != (lk.to_id in a_nodes)
             and lk.from_id in truth and lk.to_id in truth]
    assert cross, "B never joined A's map"
    for lk in cross:  # every link between the sessions is where the truth says
        (ga, ia), (gb, ib) = truth[lk.from_id], truth[lk.to_id]
        d = invert(invert(ga.poses[ia]) @ gb.poses[ib]) @ lk.transform
        assert np.linalg.norm(d[:3, 3]) < 0.05 and np.degrees(rotation_angle(d[:3, :3])) < 3.0, \
            (LinkType(lk.type).label, lk.from_id, lk.to_id, d[:3, 3])
    # none before B walks A's path: B's keyframes more than 1 m from every A keyframe come first (B
    # relocalizes once it sees A's stretch: measured 0.56 m from A's nearest keyframe; the dense
    # proximity link by coordinates was at B's 4th keyframe, 3 m from A's)
    pa = np.array([walks["walk_a"][0].poses[i][:3, 3] for _, i in walks["walk_a"][1]])
    pb = np.array([walks["walk_b"][0].poses[i][:3, 3] for _, i in walks["walk_b"][1]])
    entry = int(np.argmax([np.min(np.linalg.norm(pa - p, axis=1)) < 1.0 for p in pb]))
    first = min(b_nodes.index(lk.to_id if lk.to_id in b_nodes else lk.from_id) for lk in cross)
    assert first >= entry > 0, (first, entry)


def _overlap_to_join(walks, links) -> float:
    """B's path (ground truth, every frame) from its first frame within 0.5 m of A's path (the
    overlap: from there it could join) to its keyframe at the first link between the sessions:
    how soon it joined (`bench_multisession`'s "after overlap")."""
    (gt_a, kf_a), (gt_b, kf_b) = walks["walk_a"], walks["walk_b"]
    a_nodes, frame = {n for n, _ in kf_a}, dict(kf_b)
    pa, pb = gt_a.poses[:, :3, 3], gt_b.poses[:, :3, 3]
    entry = int(np.argmax([np.min(np.linalg.norm(pa - p, axis=1)) < 0.5 for p in pb]))
    first = next(lk for lk in links if (lk.from_id in a_nodes) != (lk.to_id in a_nodes))  # links as stored
    joined = frame[first.to_id if first.to_id in frame else first.from_id]
    return float(np.linalg.norm(np.diff(pb[entry:joined + 1], axis=0), axis=1).sum())


def test_the_second_session_joins_soon_after_it_enters_the_shared_stretch(two_walks):
    """Relocalization (loop.relocalize): B's keyframes are searched for in A's map by appearance
    until it joined, and two verified links that agree join it. Before, B joined only through
    the loop detector's Bayes filter, 3.2 m of path after it entered A's stretch."""
    walks, _, links = two_walks
    after = _overlap_to_join(walks, links)
    assert after <= BOUND_JOIN_M, after
    # never on one link: the first links between the sessions are two appearance links, to two
    # different nodes of A
    a_nodes = {n for n, _ in walks["walk_a"][1]}
    cross = [lk for lk in links if (lk.from_id in a_nodes) != (lk.to_id in a_nodes)]
    assert [LinkType(lk.type) for lk in cross[:2]] == [LinkType.GLOBAL_CLOSURE] * 2
    assert len({lk.from_id for lk in cross[:2]}) == 2


def test_the_second_session_lies_in_the_first_ones_frame(two_walks):
    walks, poses, _ = two_walks
    (gt_a, kf_a), (gt_b, kf_b) = walks["walk_a"], walks["walk_b"]
    a0, i0 = kf_a[0]
    to_truth = gt_a.poses[i0] @ invert(poses[a0])  # A's map frame -> the scene (A's first keyframe)
    for gt, kfs, bound in ((gt_a, kf_a, 0.006), (gt_b, kf_b, 0.0075)):  # measured 0.19 / 0.25 cm
        err = np.array([np.linalg.norm((to_truth @ poses[n])[:3, 3] - gt.poses[i][:3, 3]) for n, i in kfs])
        assert np.sqrt(np.mean(err ** 2)) < bound, (np.sqrt(np.mean(err ** 2)), bound)


@pytest.fixture(scope="module")
def walks_from_ltm(tmp_path_factory):
    """walk_a's first 60 frames (25 keyframes), then walk_b's first 80 (it joins at frame 54),
    with working memory bounded to 5 nodes (memory.max_wm_nodes): when B starts, all but A's
    newest 5 nodes are in LTM, so it can only find A's living room there."""
    from mnemoslam.client.datasets.subrange import frame_range

    db = tmp_path_factory.mktemp("multisession_ltm") / "map.db"
    config = slam_config({"memory": {"max_wm_nodes": 5}})
    walks, stats = {}, {}
    with MapStore(db) as store:
        for name, frames in (("walk_a", "0:60"), ("walk_b", "0:80")):
            full = open_dataset(f"synthetic:{name}", rate=RATE)
            ds = frame_range(full, frames)
            pipeline = build_pipeline(store, name, ds.calibration, config)
            keyframes = [(r.node_id, r.index) for r in map(pipeline.process, ds) if r.node_id is not None]
            pipeline.close()
            walks[name] = (full.ground_truth, keyframes)
        links = store.links()
        stored = {tuple(r): i for i, r in enumerate(store.link_rows()[1].tolist())}
        links.sort(key=lambda lk: stored.get((lk.from_id, lk.to_id, int(lk.type)), len(stored)))
        stats = {n: store.statistics(n) for n, _ in walks["walk_b"][1]}
    return walks, links, stats


def test_the_second_session_finds_the_first_in_long_term_memory(walks_from_ltm):
    walks, links, stats = walks_from_ltm
    a_nodes = [n for n, _ in walks["walk_a"][1]]
    b_first = walks["walk_b"][1][0][0]
    assert stats[b_first]["memory"]["ltm"] >= len(a_nodes) - 6  # A's nodes but the newest 5 in LTM
    truth = _truth(walks)
    cross = [lk for lk in links if (lk.from_id in a_nodes) != (lk.to_id in a_nodes)]
    assert len(cross) >= 2
    for lk in cross:  # every link between the sessions is where the truth says
        (ga, ia), (gb, ib) = truth[lk.from_id], truth[lk.to_id]
        d = invert(invert(ga.poses[ia]) @ gb.poses[ib]) @ lk.transform
        assert np.linalg.norm(d[:3, 3]) < 0.05 and np.degrees(rotation_angle(d[:3, :3])) < 3.0, \
            (LinkType(lk.type).label, lk.from_id, lk.to_id, d[:3, 3])
    # joined through A nodes that were in LTM (not the 5 newest, which start in WM), as soon as
    # with the whole map in WM (measured -0.08 m of path after the overlap, the same keyframe)
    assert not {lk.from_id for lk in cross[:2]} & set(a_nodes[-5:])
    assert _overlap_to_join(walks, links) <= BOUND_JOIN_M


def test_identical_posters_elsewhere_do_not_join_the_maps(tmp_path):
    """`straight` looks at the hall's six identical posters that `loop` saw 7 m away (its frames
    140-200, then straight's first 40): PnP verifies them (90-110 inliers) and two keyframes
    agree on the wrong place, 3.2 m off; the dense check of the whole view refuses them
    (without it they joined the maps at straight's frame 16)."""
    from mnemoslam.client.datasets.subrange import frame_range

    db = tmp_path / "map.db"
    nodes = {}
    with MapStore(db) as store:
        for name, frames in (("loop", "140:200"), ("straight", "0:40")):
            ds = frame_range(open_dataset(f"synthetic:{name}", rate=RATE), frames)
            pipeline = build_pipeline(store, name, ds.calibration, slam_config())
            nodes[name] = [r.node_id for r in map(pipeline.process, ds) if r.node_id is not None]
            pipeline.close()
        old = set(nodes["loop"])
        assert not [lk for lk in store.links() if (lk.from_id in old) != (lk.to_id in old)]
        decisions = [r["decision"] for n in nodes["straight"] for r in (store.statistics(n) or {}).get(
            "relocalization", [])]
    assert "rejected: not refined densely" in decisions and "joined" not in decisions, decisions


def _at_once(store, walks: dict, cfg) -> dict:
    """Pipelines on one store (one per robot, created together) processing their frames
    interleaved, frame k of each in the order of `walks` (name -> (dataset, first index)):
    robots mapping at the same time, offline. Returns name -> [(node, frame)] of its keyframes."""
    pipelines = {name: build_pipeline(store, name, ds.calibration, cfg) for name, (ds, _) in walks.items()}
    keyframes: dict = {name: [] for name in walks}
    for k in range(max(len(ds) + start for ds, start in walks.values())):
        for name, (ds, start) in walks.items():
            if 0 <= k - start < len(ds):
                r = pipelines[name].process(ds.frame(k - start))
                if r.node_id is not None:
                    keyframes[name].append((r.node_id, k - start))
    for p in pipelines.values():
        p.close()
    return keyframes


def test_identical_posters_elsewhere_do_not_join_robots_mapping_at_once(tmp_path):
    """The posters' negative control with the two robots mapping at the same time (`loop`'s
    frames 140-200, `straight`'s first 40 starting 20 frames later, interleaved): each map
    update searches the other's keyframes by appearance (`mapping.live`), and the dense check
    refuses the posters there too: no link between the two, each its own map."""
    from mnemoslam.client.datasets.subrange import frame_range

    walks = {name: (frame_range(open_dataset(f"synthetic:{name}", rate=RATE), frames), start)
             for name, frames, start in (("loop", "140:200", 0), ("straight", "0:40", 20))}
    with MapStore(tmp_path / "map.db") as store:
        kfs = _at_once(store, walks, slam_config())
        old = {n for n, _ in kfs["loop"]}
        assert not [lk for lk in store.links() if (lk.from_id in old) != (lk.to_id in old)]
        decisions = [r for name in kfs for n, _ in kfs[name]
                     for r in (store.statistics(n) or {}).get("relocalization", [])]
    assert any(r.get("live") for r in decisions), "the robots did not search each other"
    assert "rejected: not refined densely" in [r["decision"] for r in decisions], decisions
    assert "joined" not in [r["decision"] for r in decisions]


def test_the_older_robot_finding_the_newer_ones_keyframes_joins_the_newer_map(tmp_path):
    """Robots mapping at the same time, offline: walk_b's first keyframe is the older, and
    walk_b is the one that finds the other's keyframes (walk_a walked their shared stretch
    first). The newer map, walk_a's, joins walk_b's (the map index names maps by their oldest
    node, and the `relocalized` event is for the session whose frame changes): walk_a's mapper
    places walk_b's keyframe in its graph and the two links go there; afterwards both
    trajectories lie in walk_b's frame."""
    walks = {name: (frame_range_of(name, "0:70"), 0) for name in ("walk_b", "walk_a")}
    with MapStore(tmp_path / "map.db") as store:
        kfs = _at_once(store, walks, slam_config())
        b_nodes = {n for n, _ in kfs["walk_b"]}
        cross = [lk for lk in store.links() if (lk.from_id in b_nodes) != (lk.to_id in b_nodes)]
        poses = {n.id: n.pose for n in store.nodes(limit=None, merged=None)}
        found_by_b = [n for n, _ in kfs["walk_b"]
                      if any(r["decision"] == "joined" for r in (store.statistics(n) or {}).get("relocalization", []))]
        index = MapIndex()
        index.refresh(store)
        joins = {s: index.join(s) for s in (1, 2)}
    assert min(b_nodes) < min(n for n, _ in kfs["walk_a"])  # walk_b is the older map
    assert found_by_b and len(cross) >= 2 and all(lk.type == LinkType.GLOBAL_CLOSURE for lk in cross[:2]), cross
    # walk_a's session (2) joined walk_b's map (session 1's)
    assert joins[2].joined and not joins[1].joined and joins[2].map == joins[1].map, joins
    gt_b, gt_a = walks["walk_b"][0].ground_truth, walks["walk_a"][0].ground_truth
    n0, i0 = kfs["walk_b"][0]
    # walk_b's frame did not move (its first keyframe is its frame's origin); walk_a's did: its
    # first keyframe now lies where walk_a started in walk_b's frame (> 2 m away)
    assert np.allclose(poses[n0], np.eye(4), atol=1e-4), poses[n0]
    assert np.linalg.norm(poses[kfs["walk_a"][0][0]][:3, 3]) > 2.0
    to_truth = gt_b.poses[i0] @ invert(poses[n0])
    for name, gt in (("walk_b", gt_b), ("walk_a", gt_a)):
        err = np.array([np.linalg.norm((to_truth @ poses[n])[:3, 3] - gt.poses[i, :3, 3]) for n, i in kfs[name]])
        # measured (walk_a in walk_b's frame) 0.27 cm, walk_b 0.23 cm
        assert np.sqrt(np.mean(err ** 2)) < 0.01, (name, np.sqrt(np.mean(err ** 2)))


def frame_range_of(name: str, frames: str):
    from mnemoslam.client.datasets.subrange import frame_range

    return frame_range(open_dataset(f"synthetic:{name}", rate=RATE), frames)


# -- offline: `mnemoslam run DATASET --db MAP.db --out DIR` (issue 22 item 6) ---------------------

def _summary(folder):
    import json

    return json.loads((folder / "summary.json").read_text())


@pytest.fixture(scope="module")
def cli_walks(tmp_path_factory):
    """walk_a, then walk_b, into one map file (not there before) through the CLI, 5 frames/s."""
    root = tmp_path_factory.mktemp("run_db")
    db = root / "maps" / "map.db"
    db.parent.mkdir()
    printed = {name: _run(f"synthetic:{name}?rate={RATE:g}", "--db", str(db), "--out", str(root / name))
               for name in ("walk_a", "walk_b")}
    return root, db, printed


def _in_a_frame(root, name):
    """(name's trajectory.tum placed in the scene by A's first pose (A's frame -> truth), its
    ground truth at the same stamps)."""
    from mnemoslam.client.kernel.trajectory import read_tum

    ta, ga = read_tum(root / "walk_a" / "trajectory.tum"), read_tum(root / "walk_a" / "groundtruth.tum")
    assert ta.stamps[0] == ga.stamps[0]
    to_truth = ga.poses[0] @ invert(ta.poses[0])
    t, g = read_tum(root / name / "trajectory.tum"), read_tum(root / name / "groundtruth.tum")
    k = np.searchsorted(g.stamps, t.stamps)
    assert np.allclose(g.stamps[k], t.stamps)
    return np.einsum("ij,njk->nik", to_truth, t.poses), g.poses[k]


def test_run_db_adds_a_session_that_joins_the_map_and_writes_it_in_the_maps_frame(cli_walks):
    root, db, printed = cli_walks
    assert not (root / "walk_a" / "map.db").exists() and not (root / "walk_b" / "map.db").exists()
    a, b = _summary(root / "walk_a"), _summary(root / "walk_b")
    assert (a["session"], a["sessions_before"], a["joined"], a["cross_links"]) == (1, 0, False, 0)
    assert (b["session"], b["sessions_before"], b["joined"], b["map"]) == (2, 1, True, 0)
    assert b["cross_links"] >= 2 and sum(b["cross_links_by_type"].values()) == b["cross_links"]
    # it joined once B walked A's stretch: not at its start (measured at frame 54 of 191, 10.8 s)
    assert 40 <= b["joined_index"] <= 150 and b["joined_stamp"] == pytest.approx(b["joined_index"] / RATE)
    line = f"session 2 joined map 0 at keyframe {b['joined_keyframe']} (frame {b['joined_index']}"
    assert line in printed["walk_b"] and "did not join" not in printed["walk_b"]
    with MapStore(db, create=False) as store:
        assert [s.id for s in store.sessions()] == [1, 2]
        b_nodes = {n.id for n in store.nodes(session_id=2, limit=None, merged=None)}
        assert b["joined_keyframe"] in b_nodes
    for name, bound in (("walk_a", 0.006), ("walk_b", 0.009)):  # measured 0.21 / 0.29 cm RMSE
        est, truth = _in_a_frame(root, name)
        rmse = np.sqrt(np.mean(np.sum((est[:, :3, 3] - truth[:, :3, 3]) ** 2, axis=1)))
        assert rmse < bound, (name, rmse)
    # keyframes.tum too is in A's frame
    from mnemoslam.client.kernel.trajectory import read_tum

    kb, tb = read_tum(root / "walk_b" / "keyframes.tum"), read_tum(root / "walk_b" / "trajectory.tum")
    k = np.searchsorted(tb.stamps, kb.stamps)
    assert np.abs(kb.poses[:, :3, 3] - tb.poses[k, :3, 3]).max() < 1e-6


def test_a_third_session_joins_the_map_of_two(cli_walks, tmp_path):
    """`synthetic:loop` (its first 15 s) into the map walk_a and walk_b made: it joins the one
    map by appearance (its start is walk_b's living room) and lies in A's frame like the
    other two (measured 2026-11-27: joined at frame 0, 0.24 cm RMSE in A's frame, bench
    `walk_a->walk_b->loop`)."""
    import shutil

    root, db, _ = cli_walks
    shutil.copy(db, tmp_path / "map.db")
    _run(f"synthetic:loop?rate={RATE:g}", "--frames", "0:75", "--db", str(tmp_path / "map.db"),
         "--out", str(root / "loop"))
    c = _summary(root / "loop")
    assert (c["session"], c["sessions_before"], c["joined"], c["map"]) == (3, 2, True, 0)
    assert c["cross_links"] >= 2
    from mnemoslam.storage.connectivity import MapIndex

    index = MapIndex()
    with MapStore(tmp_path / "map.db", create=False) as store:  # one map of the three sessions (/maps)
        index.refresh(store)
        assert [s.id for s in store.sessions()] == [1, 2, 3]
    maps = index.maps()
    assert list(maps) == [0] and maps[0]["sessions"] == [1, 2, 3], maps
    est, truth = _in_a_frame(root, "loop")
    rmse = np.sqrt(np.mean(np.sum((est[:, :3, 3] - truth[:, :3, 3]) ** 2, axis=1)))
    assert rmse < 0.009, rmse


def test_run_without_db_replaces_its_own_map(tmp_path):
    out = tmp_path / "run"
    for _ in range(2):
        printed = _run("synthetic:walk_a?rate=5", "--frames", "0:15", "--out", str(out))
        with MapStore(out / "map.db", create=False) as store:
            assert len(store.sessions()) == 1
    assert "joined" not in printed and _summary(out)["sessions_before"] == 0


def test_run_db_negative_control_and_frames(tmp_path):
    """synthetic:straight after synthetic:loop: no place in common, so no link between them
    and each its own map; --frames plays a sub-range with the full run's stamps."""
    db = tmp_path / "map.db"
    _run("synthetic:loop?rate=5", "--frames", "0:150", "--db", str(db), "--out", str(tmp_path / "loop"))
    printed = _run("synthetic:straight?rate=5", "--frames", "20:", "--db", str(db), "--out", str(tmp_path / "s"))
    s = _summary(tmp_path / "s")
    assert (s["session"], s["joined"], s["map"], s["cross_links"]) == (2, False, 1, 0)
    assert "session 2 did not join the map's 1 older session(s): a map of its own (1); 0 cross-session link(s)" \
        in printed
    from mnemoslam.client.kernel.trajectory import read_tum

    t, g = read_tum(tmp_path / "s" / "trajectory.tum"), read_tum(tmp_path / "s" / "groundtruth.tum")
    full = open_dataset("synthetic:straight", rate=RATE)
    assert s["frames"] == len(full) - 20 == len(t)
    assert t.stamps[0] == pytest.approx(20 / RATE) and np.allclose(g.stamps, full.stamps[20:])
    assert "ATE RMSE" in printed
    with MapStore(db, create=False) as store:
        mine = {n.id for n in store.nodes(session_id=2, limit=None, merged=None)}
        assert all((lk.from_id in mine) == (lk.to_id in mine) for lk in store.links())


# -- through the service: the join is visible (issue 22 item 2) -----------------------------------

def test_service_walk_b_after_walk_a_relocalizes_once_and_maps_show_it(tmp_path):
    """`serve`, walk_a as robot A, restart, walk_b as robot B: one `relocalized` event naming
    map 0 with B's frame in it, /maps one map with both sessions, /robots and /robots/B agree,
    /sessions says when B joined, and B's keyframes over REST lie in A's frame. The first
    LIVE_FRAMES of each walk (as the live test below): A walks the shared stretch at its frames
    17-25, B enters it at its frame ~55 and joins there (the whole walks' accuracy in A's frame is
    `two_walks`' offline tests')."""
    from mnemoslam.client.kernel import protocol
    from mnemoslam.client.streamer import stream_dataset
    from mnemoslam.client.transport import ZenohSettings, open_session
    from mnemoslam.service.demo import ServiceProcess, keyframe_trajectory

    db = tmp_path / "map.db"
    # streamed as fast as the service takes the frames, the map update falls behind tracking; every
    # keyframe goes to it with its images all the same (loop.backlog_images), as in the offline run
    conf = {"semantics": {"enabled": False}, "service": {"queue_size": 10000, "idle_timeout": 3600.0},
            "loop": {"backlog_images": 100000}}
    walks = {name: open_dataset(f"synthetic:{name}", rate=RATE) for name in ("walk_a", "walk_b")}
    svc = ServiceProcess(db, conf).start()
    try:
        stats = stream_dataset(walks["walk_a"], "A", ZenohSettings(connect=[svc.endpoint]), rate=None,
                               progress=False, wait_for_subscriber=10.0, max_frames=LIVE_FRAMES)
        svc.wait_processed("A", stats.frames)
        svc.wait_mapped("A")
        traj_a = keyframe_trajectory(svc.api, svc.session_of("A"))
    finally:
        svc.stop()
    svc = ServiceProcess(db, conf).start()
    events = []
    try:
        z = open_session(ZenohSettings(connect=[svc.endpoint]))
        sub = z.declare_subscriber(protocol.KeySpace().events("B"),
                                   lambda s: events.append(protocol.decode_event(s.payload.to_bytes())))
        try:
            stats = stream_dataset(walks["walk_b"], "B", ZenohSettings(connect=[svc.endpoint]), rate=None,
                                   progress=False, wait_for_subscriber=10.0, max_frames=LIVE_FRAMES)
            svc.wait_processed("B", stats.frames)
            svc.wait_mapped("B")
            import time
            time.sleep(2.5)  # the service looks at the links every second
        finally:
            sub.undeclare()
            z.close()
        api = svc.api
        sb = svc.session_of("B")
        reloc = [e for e in events if e.kind == "relocalized"]
        assert len(reloc) == 1, [e.kind for e in events]
        e = reloc[0]
        assert (e["session_id"], e["map"]) == (sb, 0) and e["link"] in ("loop", "proximity", "merged")
        maps = api.get("/maps")
        assert len(maps) == 1 and maps[0]["id"] == maps[0]["map"] == 0, maps
        assert maps[0]["sessions"] == [svc.session_of("A"), sb] and sorted(maps[0]["robots"]) == ["A", "B"]
        traj_b = keyframe_trajectory(api, sb)
        assert maps[0]["keyframes"] <= len(traj_a) + len(traj_b) and maps[0]["keyframes"] >= len(traj_a)
        robots = {r["robot"]: r for r in api.get("/robots")}
        assert robots["B"]["map"] == api.robot("B")["map"] == 0
        sess = {s["id"]: s for s in api.get("/sessions")}
        b = sess[sb]
        assert (b["map"], b["map_id"], b["joined"], b["joined_keyframe"]) == (0, 1, True, e["node_id"])
        assert b["joined_stamp"] == pytest.approx(e["stamp"]) and e["stamp"] > 5.0  # not at B's start
        a = sess[svc.session_of("A")]
        assert (a["map"], a["joined"]) == (0, False) and np.allclose(np.reshape(a["T_map_session"], (4, 4)), np.eye(4),
                                                                      atol=1e-6)
        # in A's frame: A's first keyframe places the map in the scene; B's keyframes and
        # T_map_session (B's first keyframe's camera in the map) against B's ground truth
        gt_a, gt_b = walks["walk_a"].ground_truth, walks["walk_b"].ground_truth
        traj_a = keyframe_trajectory(api, svc.session_of("A"))  # (A's poses after B joined)
        to_truth = gt_a.poses[np.searchsorted(gt_a.stamps, traj_a.stamps[0])] @ invert(traj_a.poses[0])
        k = np.searchsorted(gt_b.stamps, traj_b.stamps)
        err = np.linalg.norm(np.einsum("ij,njk->nik", to_truth, traj_b.poses)[:, :3, 3] - gt_b.poses[k, :3, 3], axis=1)
        T = np.reshape(b["T_map_session"], (4, 4))
        print(f"B in A's frame: keyframes RMSE {np.sqrt(np.mean(err ** 2)) * 100:.2f} cm, its first keyframe "
              f"{np.linalg.norm((to_truth @ T)[:3, 3] - gt_b.poses[k[0], :3, 3]) * 100:.2f} cm off")
        # measured 0.12 cm on the first LIVE_FRAMES of each walk (0.30 cm on the whole walks; the issue asks
        # for <= 1.5 cm)
        assert np.sqrt(np.mean(err ** 2)) < 0.004, np.sqrt(np.mean(err ** 2))
        assert np.allclose(np.reshape(e["T_map_session"], (4, 4)), T, atol=0.01)
        # measured 0.13 cm (0.45 cm on the whole walks)
        assert np.linalg.norm((to_truth @ T)[:3, 3] - gt_b.poses[k[0], :3, 3]) < 0.004
    finally:
        svc.stop()


# -- through the service: two robots mapping at the same time (issue 22 item 4) -------------------

LIVE_FRAMES = 80  # of each walk: B enters A's stretch at its frame ~55 (A walked it at its frames 17-25)


def _twins(objects, radius=0.4):
    """Pairs of same-label objects (REST `ObjectOut`s) whose positions are within `radius` m."""
    return [(a["id"], b["id"], a["label"]) for i, a in enumerate(objects) for b in objects[i + 1:]
            if a["label"] == b["label"] and np.linalg.norm(np.subtract(a["position"], b["position"])) < radius]


def test_service_walk_a_and_walk_b_streamed_at_once_join_in_the_shared_stretch(tmp_path):
    """`serve`; robots A and B stream walk_a and walk_b at the same time (their first 80 frames,
    5 frames/s, both as fast as the service takes them, with the camera's labels). Each robot's
    map update closes loops only to its own keyframes and to ended sessions' unless the map
    updates running at once search each other (`mapping.live`): then the newer map (that of the
    robot the service admitted second) joins the older once both walk the shared stretch, by two
    agreeing verified links. One `relocalized` event, for the newer; /maps one map with both
    sessions; both trajectories over REST in the older map's frame; the objects of both merged
    (no same-label pair within 0.25 m anchored one in each robot's session)."""
    import threading
    import time

    from mnemoslam.client.kernel import protocol
    from mnemoslam.client.streamer import stream_dataset
    from mnemoslam.client.transport import ZenohSettings, open_session
    from mnemoslam.service.demo import ServiceProcess, keyframe_trajectory

    conf = {"service": {"queue_size": 10000, "idle_timeout": 3600.0}, "loop": {"backlog_images": 100000}}
    walks = {robot: open_dataset(f"synthetic:{name}", rate=RATE) for robot, name in (("A", "walk_a"), ("B", "walk_b"))}
    svc = ServiceProcess(tmp_path / "map.db", conf).start()
    events: list = []
    try:
        z = open_session(ZenohSettings(connect=[svc.endpoint]))
        subs = [z.declare_subscriber(protocol.KeySpace().events(r),
                                     lambda s: events.append(protocol.decode_event(s.payload.to_bytes())))
                for r in walks]
        sent: dict[str, int] = {}

        def stream(robot: str) -> None:
            sent[robot] = stream_dataset(walks[robot], robot, ZenohSettings(connect=[svc.endpoint]), rate=None,
                                         progress=False, wait_for_subscriber=10.0, labels=True,
                                         max_frames=LIVE_FRAMES).frames

        threads = [threading.Thread(target=stream, args=(r,)) for r in walks]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        for r in walks:
            svc.wait_processed(r, sent[r])
            svc.wait_mapped(r)
        api = svc.api
        deadline = time.monotonic() + 120  # every keyframe fused (the semantic worker runs behind)
        status = api.semantics()
        while status["coverage"]["segmented"] < status["coverage"]["keyframes"] and time.monotonic() < deadline:
            time.sleep(0.5)
            status = api.semantics()
        time.sleep(2.5)  # the service looks at the links every second
        for s in subs:
            s.undeclare()
        z.close()
        sessions = {r: svc.session_of(r) for r in walks}
        # the robot whose first keyframe came first has the older map (a map is named by its oldest
        # node's session): the other's joins it; /sessions says which kept its own map
        listed = {s["id"]: s for s in api.get("/sessions")}
        kept = [r for r in walks if listed[sessions[r]]["map"] == listed[sessions[r]]["map_id"]]
        assert len(kept) == 1, listed
        old, new = kept[0], next(r for r in walks if r != kept[0])
        assert listed[sessions[new]]["joined"] and listed[sessions[new]]["map"] == listed[sessions[old]]["map_id"]
        reloc = [e for e in events if e.kind == "relocalized"]
        assert len(reloc) == 1 and reloc[0].robot == new, [(e.robot, e.kind) for e in events]
        e = reloc[0]
        maps = api.get("/maps")
        assert len(maps) == 1 and maps[0]["sessions"] == sorted(sessions.values()), maps
        assert e["session_id"] == sessions[new] and e["map"] == maps[0]["id"]
        robots = {r["robot"]: r for r in api.get("/robots")}
        assert robots["A"]["map"] == robots["B"]["map"] == api.robot(new)["map"] == maps[0]["id"]
        # joined where both walked: the joining keyframe's camera within 0.6 m of the other
        # robot's streamed path (B's first 45 frames never come within 1.2 m of A's)
        gt = {r: walks[r].ground_truth for r in walks}
        k_join = int(np.searchsorted(gt[new].stamps, e["stamp"] - 1e-6))
        other_path = gt[old].poses[:LIVE_FRAMES, :3, 3]
        assert np.min(np.linalg.norm(other_path - gt[new].poses[k_join, :3, 3], axis=1)) < 0.6, (new, k_join)
        # both trajectories in the older map's frame (its first keyframe placed on its ground truth)
        traj = {r: keyframe_trajectory(api, sessions[r]) for r in walks}
        to_truth = gt[old].poses[np.searchsorted(gt[old].stamps, traj[old].stamps[0])] @ invert(traj[old].poses[0])
        rmse = {}
        for r in walks:
            k = np.searchsorted(gt[r].stamps, traj[r].stamps)
            err = np.linalg.norm(np.einsum("ij,njk->nik", to_truth, traj[r].poses)[:, :3, 3] - gt[r].poses[k, :3, 3],
                                 axis=1)
            rmse[r] = float(np.sqrt(np.mean(err ** 2)))
        print(f"live join: {new} at its frame {k_join}; RMSE in {old}'s frame (cm):",
              {r: round(v * 100, 2) for r, v in rmse.items()})
        # the issue asks for 2 cm; measured 0.13 / 0.12 cm (in-process, interleaved: 0.19 / 0.23)
        assert rmse["A"] < 0.006 and rmse["B"] < 0.006, rmse
        # objects: B's fused into A's where both saw the same things: no thing kept twice, once in
        # each robot's part (same-label objects within 0.25 m anchored in the two sessions; with the
        # merge switched off, paintings anchored in both were). Two objects anchored in one session are
        # parts of one thing its robot saw segmented apart: in the failing run examined (this check failed
        # 2 in 19 runs when it took any pair) a chair's legs 0.37 m from its seat, both A's. The same split
        # across the two sessions (a chair pair 0.4 m apart, one anchored in each: once in a CI run of
        # 2026-11-28) is no twin either: within 0.25 m. With the merge off (semantics.merge_overlap 1.01)
        # the twins anchored in both are 0.017-0.146 m apart (two chairs, a table, a door, a painting), the
        # next pairs 0.30 m (a cabinet seen whole and in part) and 0.44 m (a chair and a 0.10 m part of one).
        objects = api.objects(limit=1000)["objects"]
        assert len({o["label"] for o in objects}) >= 2, objects
        svc.stop()  # (the map file read by the test alone)
        with MapStore(tmp_path / "map.db", create=False) as store:
            session_of = {n.id: n.session_id for n in store.nodes(limit=None, merged=None)}
        anchored_in = {o["id"]: session_of[o["node_id"]] for o in objects}
        twins = [(a, b, label) for a, b, label in _twins(objects, radius=0.25) if anchored_in[a] != anchored_in[b]]
        assert not twins, (twins, _twins(objects))
    finally:
        svc.stop()
