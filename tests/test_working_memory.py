"""STM/WM/LTM bookkeeping (service/memory/working_memory.py): who moves, in which order."""
from mnemoslam.service.memory.working_memory import WorkingMemory


def test_stm_feeds_wm_in_order():
    m = WorkingMemory(stm_size=3)
    moved = [m.add(n) for n in range(1, 7)]
    assert moved == [[], [], [], [1], [2], [3]]
    assert list(m.stm) == [4, 5, 6] and m.wm == [1, 2, 3] and not m.ltm
    assert (m.sizes().stm, m.sizes().wm, m.sizes().ltm) == (3, 3, 0)
    assert m.in_ram(5) and m.in_wm(2) and not m.in_wm(5) and 7 not in m


def test_transfer_lowest_weight_then_oldest_and_never_protected_or_recent():
    m = WorkingMemory(stm_size=2, max_wm_nodes=4, recent_wm_ratio=0.0)
    for n in range(1, 10):
        m.add(n, weight=5 if n == 1 else 0)  # node 1 was rehearsed: it stays longest
    assert m.wm == [1, 2, 3, 4, 5, 6, 7]
    assert m.over_limit(0.0)
    out = m.select_transfers(0.0, protected={2})
    assert out == [3, 4, 5]  # 7 in WM, limit 4: three go; 1 is heavy, 2 protected
    assert m.select_transfers(0.0, protected={2}, preferred={3, 4}) == [5, 6, 7]  # near ones go last (1: heavy)
    m.transferred(out)
    assert m.wm == [1, 2, 6, 7] and m.ltm == {3, 4, 5} and m.select_transfers(0.0) == []
    # nodes that entered WM since the last loop closure stay (up to recent_wm_ratio of WM)
    m2 = WorkingMemory(stm_size=1, max_wm_nodes=2, recent_wm_ratio=0.5)
    for n in range(1, 6):
        m2.add(n)
    assert m2.wm == [1, 2, 3, 4]
    m2.loop_closed()
    m2.add(6)
    assert m2.select_transfers(0.0) == [1, 2, 3]  # 5 entered after the loop closure: kept
    # the time threshold alone transfers one node per update
    m3 = WorkingMemory(stm_size=1, time_threshold_ms=100.0, recent_wm_ratio=0.0)
    for n in range(1, 5):
        m3.add(n)
    assert m3.select_transfers(50.0) == [] and m3.select_transfers(150.0) == [1]


def test_working_memory_adapts_to_the_time_budget():
    """memory.time_threshold_ms (Rtabmap/TimeThr): updates over budget lower WM's limit in
    proportion (at most a tenth at once) and WM follows it; updates well within raise it back
    one node per update, up to max_wm_nodes."""
    m = WorkingMemory(stm_size=1, max_wm_nodes=60, time_threshold_ms=100.0, recent_wm_ratio=0.0)
    for n in range(1, 52):
        m.add(n)
    assert len(m.wm) == 50 and m.limit == 60
    m.adapt(200.0)  # twice the budget: half of WM would fit, a tenth goes now
    assert m.limit == 45
    m.transferred(m.select_transfers(200.0))
    assert len(m.wm) == 45
    for _ in range(5):
        m.adapt(200.0)
        m.transferred(m.select_transfers(200.0))
    assert m.limit == 25 and len(m.wm) == 25  # where the updates fit
    m.adapt(90.0)  # within budget, not well within: the limit holds
    assert m.limit == 25
    for k in range(3):  # new nodes keep coming: WM stays at its limit
        m.add(100 + k)
        m.adapt(50.0)
        m.transferred(m.select_transfers(50.0))
    assert m.limit == 28 and len(m.wm) == 28
    for _ in range(40):
        m.adapt(50.0)
    assert m.limit == 60 and m.time_limit is None  # back to max_wm_nodes
    # without a budget nothing adapts
    m2 = WorkingMemory(stm_size=1, max_wm_nodes=60)
    m2.adapt(1e6)
    assert m2.limit == 60


def test_retrieval_breadth_first_around_the_seeds_bounded():
    m = WorkingMemory(stm_size=1, max_retrieved=2, retrieval_depth=2)
    for n in range(1, 9):
        m.add(n)
    m.transferred([1, 2, 3, 4, 5])
    chain = {n: [n - 1, n + 1] for n in range(1, 9)}
    assert m.select_retrievals([6], chain) == [5, 4]  # depth 1 then 2
    assert m.select_retrievals([None, 1], chain) == [2, 3]
    m.retrieved([5, 4])
    assert m.wm[-2:] == [5, 4] and m.ltm == {1, 2, 3}
    assert WorkingMemory(max_retrieved=0).select_retrievals([1], chain) == []


def test_a_retrieved_node_is_not_transferred_again_before_it_could_be_used():
    """Churn (issue 23): WM full of nodes near the pose (transferred last), two old nodes
    retrieved around a loop hypothesis far away: they must not be the ones sent back to LTM
    by the same update, nor by the next retrieval_immunity - 1; after that they can go."""
    m = WorkingMemory(stm_size=1, max_wm_nodes=4, recent_wm_ratio=0.0, retrieval_immunity=3)
    for n in range(1, 8):
        m.add(n)
    m.tick()
    m.transferred(m.select_transfers(0.0))
    assert m.wm == [3, 4, 5, 6] and m.ltm == {1, 2}
    near = {3, 4, 5, 6, 7, 8, 9}
    for update in range(3):
        m.tick()
        if update == 0:
            m.retrieved([1, 2])
        m.add(8 + update)  # one more node enters WM each update
        out = m.select_transfers(0.0, preferred=near)
        assert not {1, 2} & set(out), (update, out)  # the others go, near ones or not
        m.transferred(out)
        assert len(m.wm) == 4
    m.tick()
    m.add(11)
    assert m.select_transfers(0.0, preferred=near) == [1]  # immunity over: not near, it goes first


def test_a_transferred_node_is_not_retrieved_back_at_once():
    m = WorkingMemory(stm_size=1, max_wm_nodes=3, max_retrieved=2, retrieval_depth=2, retrieval_immunity=2)
    for n in range(1, 6):
        m.add(n)
    m.tick()
    m.transferred([1])
    chain = {n: [n - 1, n + 1] for n in range(1, 9)}
    m.transferred([2])  # earlier: clock 1 as well
    assert m.select_retrievals([3], chain) == []  # both just went
    m.tick()
    assert m.select_retrievals([3], chain) == []
    m.tick()
    assert m.select_retrievals([3], chain) == [2, 1]
    # no immunity configured: as before, back at once
    m0 = WorkingMemory(stm_size=1, max_wm_nodes=3, max_retrieved=2, retrieval_depth=2)
    for n in range(1, 6):
        m0.add(n)
    m0.transferred([1, 2])
    assert m0.select_retrievals([3], chain) == [2, 1]


def test_a_bounded_working_memory_retrieves_old_nodes_and_closes_loops_to_them(tmp_path):
    """figure-8 walked twice with at most 20 nodes in WM: the first lap's nodes go to LTM, come
    back around the loop hypotheses and the new keyframes, and the second lap closes loops to
    them; the map's accuracy holds. Its first 260 frames (~200 keyframes, the second lap
    revisiting the first from frame ~190 on; measured: 70 loop links to retrieved nodes, ATE
    0.18 cm; all 401 frames: 240, 0.21 cm)."""
    import csv

    from mnemoslam.service.evaluation import evaluate
    from mnemoslam.storage import MapStore

    from conftest import FIGURE8, run_tracked_once, slam_config, synthetic

    ds = synthetic("figure8", **FIGURE8, max_frames=260)  # rendered once for the session (conftest)
    # no occupancy grid and semantics off (conftest `slam_config`): the map update never reads
    # either (the grids are tests/test_grid*.py's, the objects tests/test_semantics.py's); the tracking of
    # that run (conftest `figure8_run`), replayed when this module runs beside it: a bounded
    # working memory changes the map update only
    cfg = slam_config({"memory": {"max_wm_nodes": 20}, "grid": {"enabled": False}})
    out = run_tracked_once(ds, cfg, tmp_path, progress=False)
    rows = list(csv.DictReader(open(tmp_path / "updates.csv")))
    assert len(rows) == out.summary.keyframes
    assert max(int(r["wm"]) for r in rows) <= 20
    assert int(rows[-1]["ltm"]) > 0 and sum(int(r["retrieved"]) for r in rows) > 0
    with MapStore(tmp_path / "map.db") as store:
        stats = {n.id: store.statistics(n.id) for n in store.nodes(limit=None)}
        loops = [(lk.from_id, lk.to_id) for lk in store.links() if lk.type in (1, 2)]  # appearance, proximity
    transferred_at, retrieved_at = {}, {}
    for node, st in sorted(stats.items()):
        for n in st["memory"]["transferred"]:
            transferred_at.setdefault(n, node)
        for n in st["memory"]["retrieved"]:
            retrieved_at.setdefault(n, node)
    # loop links whose older node had been in LTM and was brought back before the link
    back = [(a, b) for a, b in loops if a in retrieved_at and transferred_at.get(a, b) < retrieved_at[a] <= b]
    assert len(back) >= 5, (len(loops), len(back))
    assert evaluate(ds.ground_truth, out.trajectory).ate_rmse < 0.01
