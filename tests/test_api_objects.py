"""The semantic REST endpoints, their access control and the planner client, against a real
uvicorn server (in a thread) over a real SQLite map: keyframes on a line with odometry
links, objects saved through `save_objects`, and a service stand-in that reports robots."""
import math
import time
from types import SimpleNamespace

import numpy as np
import pytest
import requests

from mnemoslam.client.kernel.frames import Calibration, PinholeCamera
from mnemoslam.client.planner import ApiError, PlannerClient
from mnemoslam.service.api import TOKEN_ENV, ApiThread, create_app
from mnemoslam.service.config import Config, load_config, to_dict
from mnemoslam.storage import MapStore
from mnemoslam.storage.records import KeyframeRecord, LinkType, ObjectRecord

TOKEN = "s3cret-token"
# objects: (label, world position); anchors are the nearest keyframe (keyframes at x = 0..9, y = z = 0)
OBJECTS = [("door", (2.0, 1.0, 0.0)), ("door", (7.5, -1.0, 0.0)), ("chair", (4.0, 0.5, 0.0)),
           ("chair", (9.0, 0.0, 1.0)), ("table", (5.0, 2.0, 0.0))]


def _robot(name, position=None, node_id=None, session_id=None):
    return {"robot": name, "state": "tracking", "queue_depth": 0, "queue_mb": 0.0, "frames_received": 1,
            "frames_processed": 1, "frames_dropped": 0, "frames_rejected": {}, "tracked": 1, "lost": 0,
            "keyframes": 1, "fps": 30.0, "processing_ms": 10.0, "last_stamp": 1.0, "session_id": session_id,
            "position": position, "node_id": node_id, "keyframes_mapped": 1, "map_backlog": 0}


def make_map(path, objects=OBJECTS):
    store = MapStore(path)
    rng = np.random.default_rng(0)
    cal = Calibration(PinholeCamera(500.0, 500.0, 320.0, 240.0, 640, 480), None, 1000.0)
    sid = store.begin_session("r1", cal, {})
    ids = []
    for i in range(10):
        P = np.eye(4)
        P[0, 3] = float(i)
        n = 20
        ids.append(store.add_keyframe(KeyframeRecord(
            session_id=sid, stamp=float(i), pose=P, keypoints=(rng.random((n, 2)) * 640).astype(np.float32),
            descriptors=rng.integers(0, 256, (n, 32), dtype=np.uint8),
            points=rng.normal(size=(n, 3)).astype(np.float32))))
        if i:
            T = np.eye(4)
            T[0, 3] = 1.0
            store.add_link(ids[-2], ids[-1], LinkType.NEIGHBOR, T)
    recs = []
    for label, pos in objects:
        anchor = ids[int(np.clip(round(pos[0]), 0, 9))]
        centroid = np.asarray(pos, float) - store.get_node(anchor).pose[:3, 3]
        hist = np.full(32, 0.01, np.float32)
        recs.append(ObjectRecord(None, anchor, 15 if label == "door" else 3, label, 0.9, hist, centroid,
                                 np.array([1.0, 2.0, 0.1]), 12, np.array([anchor], np.int64)))
    oids = store.save_objects(recs) if recs else []
    return store, sid, ids, oids


class FakeService:
    def __init__(self, store, config, robots=(), semantics=True):
        self.store, self.config, self._robots = store, config, list(robots)
        self._semantics = semantics

    def robots(self):
        return list(self._robots)

    def status(self):
        return {"uptime_s": 1.0, "robots": len(self._robots), "rejected_total": 0, "config": to_dict(self.config)}

    def semantics_status(self):
        if self._semantics:
            return {"enabled": True, "source": "camera", "model": None, "reason": None, "classes": ["other", "door"]}
        return {"enabled": False, "source": "model", "model": None, "reason": "semantics.enabled is false",
                "classes": []}


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    store, sid, ids, oids = make_map(tmp_path_factory.mktemp("objects") / "map.db")
    robots = [_robot("r1", [0.5, 0.0, 0.0], ids[0], sid), _robot("r2", None, None, None), _robot("r3", None, None, sid)]
    svc = FakeService(store, load_config(None, {"api": {"token": TOKEN}}), robots)
    server = ApiThread(create_app(svc)).start()
    yield SimpleNamespace(store=store, sid=sid, ids=ids, oids=oids, url=server.url, svc=svc,
                          api=PlannerClient(server.url), admin=PlannerClient(server.url, token=TOKEN))
    server.stop()
    store.close()


def _status(fn, *a, **kw):
    with pytest.raises(ApiError) as e:
        fn(*a, **kw)
    return e.value.status, e.value.detail


def test_nearest_by_point_and_robot(world):
    r = world.api.nearest_object("door", (8.0, 0.0, 0.0))
    assert set(r) == {"object", "distance", "node_id"}
    o = r["object"]
    assert {"id", "label", "confidence", "position", "extent", "observations"} <= set(o)
    assert o["id"] == world.oids[1] and o["label"] == "door" and o["position"] == pytest.approx([7.5, -1.0, 0.0])
    assert r["distance"] == pytest.approx(math.hypot(0.5, 1.0)) and r["node_id"] == o["node_id"] == world.ids[8]
    assert o["extent"] == [1.0, 2.0, 0.1] and o["observations"] == 12 and o["confidence"] == pytest.approx(0.9)
    assert world.api.last_semantics == "on"
    r = world.api.nearest_object("door", robot="r1")  # r1 at (0.5, 0, 0)
    assert r["object"]["id"] == world.oids[0] and r["distance"] == pytest.approx(math.hypot(1.5, 1.0))
    r = world.api.nearest_object("chair", robot="r3")  # no tracked pose: its session's latest keyframe (x = 9)
    assert r["object"]["id"] == world.oids[3]


@pytest.mark.parametrize("params,status,reason", [
    ({"label": "sofa", "x": 0, "y": 0, "z": 0}, 404, "no object labelled 'sofa'"),
    ({"label": "door", "robot": "r9"}, 404, "unknown robot"),
    ({"label": "door", "robot": "r2"}, 404, "no pose"),
    ({"label": "door", "x": 1, "y": 2}, 400, "x, y and z"),
    ({"label": "door", "x": 1, "y": 2, "z": 3, "robot": "r1"}, 400, "one of them"),
    ({"label": "door"}, 400, "one of them"),
    ({"label": "door", "x": "nan", "y": 0, "z": 0}, 422, ""),
    ({"label": "door", "x": "inf", "y": 0, "z": 0}, 422, ""),
    ({"label": "door", "x": "one", "y": 0, "z": 0}, 422, ""),
    ({"label": "door", "robot": "bad robot"}, 422, ""),
    ({"x": 0, "y": 0, "z": 0}, 422, ""),
    ({"label": "", "x": 0, "y": 0, "z": 0}, 422, ""),
])
def test_nearest_errors(world, params, status, reason):
    r = requests.get(f"{world.url}/objects/nearest", params=params, timeout=10)
    assert r.status_code == status, r.text
    assert reason in str(r.json()["detail"])


def test_list_get_labels_path(world):
    every = world.api.objects()
    assert every["total"] == len(OBJECTS) and [o["id"] for o in every["objects"]] == world.oids
    doors = world.api.objects(label="door")
    assert [o["id"] for o in doors["objects"]] == world.oids[:2]
    near = world.api.objects(point=(4.0, 0.0, 0.0), radius=2.1)  # chair at 0.5, door (2, 1) at 2.24, table at 2.24
    assert near["total"] == 1 and near["objects"][0]["label"] == "chair"
    page = world.api.objects(point=(4.0, 0.0, 0.0), limit=2, offset=1)
    by_dist = sorted(range(len(OBJECTS)), key=lambda i: (np.linalg.norm(np.subtract(OBJECTS[i][1], (4, 0, 0))), i))
    assert page["total"] == 5 and [o["id"] for o in page["objects"]] == [world.oids[i] for i in by_dist[1:3]]
    assert _status(world.api.objects, radius=1.0)[0] == 400  # radius without a point
    assert world.api.object(world.oids[4])["label"] == "table"
    assert _status(world.api.object, 10**9) == (404, "no object 1000000000")
    assert world.api.labels() == {"total": 5, "labels": [{"label": "chair", "count": 2}, {"label": "door", "count": 2},
                                                         {"label": "table", "count": 1}]}
    p = world.api.object_path(world.oids[1], robot="r1")  # door at (7.5, -1): from node x=0 to node x=8 (or 7)
    assert p["start_node"] == world.ids[0] and p["goal_node"] in (world.ids[7], world.ids[8])
    assert [n["id"] for n in p["nodes"]] == world.ids[:world.ids.index(p["goal_node"]) + 1]
    assert p["nodes"][-1]["position"][0] == pytest.approx(world.ids.index(p["goal_node"]))
    assert p["length"] == pytest.approx(world.ids.index(p["goal_node"])) and p["robot"] == "r1"
    assert _status(world.api.object_path, world.oids[1], robot="r2")[0] == 404
    assert _status(world.api.object_path, 10**9, robot="r1")[0] == 404
    assert world.api.semantics()["enabled"] is True


def test_objects_follow_the_graph_and_deletes(world, tmp_path):
    store, sid, ids, oids = make_map(tmp_path / "m.db")
    svc = FakeService(store, load_config(None, {"api": {"token": TOKEN}}), [], semantics=False)
    with ApiThread(create_app(svc)) as url:
        api, admin = PlannerClient(url), PlannerClient(url, token=TOKEN)
        assert api.nearest_object("table", (5, 2, 0))["distance"] == pytest.approx(0.0)
        assert api.last_semantics == "off"
        status, detail = _status(api.nearest_object, "sofa", (0, 0, 0))
        assert status == 404 and "semantics are off" in detail
        # loop closure moves the table's anchor keyframe by 1 m: the answer follows within a second
        P = store.get_node(ids[5]).pose.copy()
        P[1, 3] += 1.0
        store.update_poses({ids[5]: P})
        deadline = time.monotonic() + 3
        while time.monotonic() < deadline:
            pos = api.nearest_object("table", (5, 2, 0))["object"]["position"]
            if pos[1] == pytest.approx(3.0):
                break
            time.sleep(0.05)
        assert pos == pytest.approx([5.0, 3.0, 0.0]), "stale position after the graph moved"
        moved_after = time.monotonic() - (deadline - 3)
        assert moved_after < 2.0
        # delete (token): gone at once from every query
        assert _status(api.delete_object, oids[4])[0] == 401
        assert admin.delete_object(oids[4]) == {"deleted": 1}
        assert _status(api.nearest_object, "table", (5, 2, 0))[0] == 404
        assert _status(api.object, oids[4])[0] == 404
        assert _status(admin.delete_object, oids[4])[0] == 404
        assert api.labels()["total"] == 4
    store.close()


def test_empty_map_says_so(tmp_path):
    store, *_ = make_map(tmp_path / "e.db", objects=[])
    with ApiThread(create_app(FakeService(store, Config()))) as url:
        api = PlannerClient(url)
        assert _status(api.nearest_object, "door", (0, 0, 0)) == (404, "the map has no objects")
        assert api.objects()["total"] == 0 and api.labels() == {"total": 0, "labels": []}
    store.close()


def test_mutations_need_the_token(world):
    node = world.ids[3]
    assert _status(world.api.label_node, node, "kitchen") == (
        401, "missing API token: send 'Authorization: Bearer <token>'")
    assert _status(PlannerClient(world.url, token="wrong").label_node, node, "kitchen") == (401, "wrong API token")
    r = requests.post(f"{world.url}/nodes/{node}/label", json={"label": "kitchen"}, timeout=10)
    assert r.status_code == 401 and r.headers["www-authenticate"].startswith("Bearer")
    assert world.admin.label_node(node, "kitchen")["label"] == "kitchen"
    assert world.store.get_node(node).label == "kitchen"
    assert _status(world.admin.label_node, world.ids[4], "kitchen")[0] == 409  # labels are unique
    assert _status(world.admin.label_node, 10**9, "x")[0] == 404
    assert world.admin.label_node(node, None)["label"] is None
    status, detail = _status(world.admin.delete_object, world.oids[0])  # semantics on: the workers own the objects
    assert status == 409 and "semantics.enabled" in detail and world.store.count_objects() == len(OBJECTS)
    r = requests.post(f"{world.url}/nodes/{node}/label", json={"label": ""}, timeout=10,
                      headers={"Authorization": f"Bearer {TOKEN}"})
    assert r.status_code == 422
    # reads stay open; /config never shows the token
    assert world.api.labels()["total"] >= 4
    assert world.api.get("/config")["api"]["token"] == "***"


def test_without_a_token_mutations_are_refused(tmp_path, monkeypatch):
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    store, sid, ids, oids = make_map(tmp_path / "n.db")
    with ApiThread(create_app(FakeService(store, Config()))) as url:
        status, detail = _status(PlannerClient(url, token="anything").delete_object, oids[0])
        assert status == 403 and "api.token" in detail and TOKEN_ENV in detail
        assert store.count_objects() == len(OBJECTS)
    store.close()


def test_env_token_and_protected_reads(tmp_path, monkeypatch):
    monkeypatch.setenv(TOKEN_ENV, "from-env")
    store, sid, ids, oids = make_map(tmp_path / "p.db")
    cfg = load_config(None, {"api": {"token": "from-config", "protect_reads": True}})
    with ApiThread(create_app(FakeService(store, cfg, semantics=False))) as url:
        assert PlannerClient(url).health()["status"] == "ok"  # liveness stays open
        for path in ("/labels", "/objects", f"/objects/{oids[0]}", "/semantics", "/sessions", "/robots", "/stats"):
            assert _status(PlannerClient(url).get, path)[0] == 401, path
        assert _status(PlannerClient(url, token="from-config").labels)[0] == 401  # the environment overrides
        assert PlannerClient(url, token="from-env").labels()["total"] == len(OBJECTS)
        assert PlannerClient(url, token="from-env").delete_object(oids[0]) == {"deleted": 1}
    monkeypatch.delenv(TOKEN_ENV)
    with pytest.raises(ValueError, match="protect_reads needs a token"):
        create_app(FakeService(store, load_config(None, {"api": {"protect_reads": True}})))
    store.close()


def test_openapi_documents_every_response(world):
    spec = requests.get(f"{world.url}/openapi.json", timeout=10).json()
    for path, ops in spec["paths"].items():
        for method, op in ops.items():
            ok = op["responses"]["200"]["content"]["application/json"]["schema"]
            assert ok and ok != {}, (method, path)
            assert "$ref" in ok or ok.get("type") in ("array", "object"), (method, path, ok)
    for name in ("NearestOut", "ObjectOut", "ObjectPage", "LabelsOut", "PathOut", "SemanticsOut", "NodeOut",
                 "RobotStatus", "SessionOut", "StatsOut", "Health", "Config"):
        assert name in spec["components"]["schemas"], name
    assert spec["paths"]["/nodes/{node_id}/label"]["post"]["security"] == [{"HTTPBearer": []}]


def test_robot_status_says_which_map_it_is_localized_in(tmp_path):
    """GET /robots/{robot} `map`: the map id of the oldest session links join the robot's latest
    keyframe to. A second robot has its own session's until a loop link places it in the first
    map; then its nearest-door query answers from the first map's objects too."""
    store, sid, ids, oids = make_map(tmp_path / "map.db")
    cal = Calibration(PinholeCamera(500.0, 500.0, 320.0, 240.0, 640, 480), None, 1000.0)
    s2 = store.begin_session("r2", cal, {})
    n2 = store.add_keyframe(KeyframeRecord(session_id=s2, stamp=20.0, pose=np.eye(4),
                                           keypoints=np.zeros((0, 2), np.float32),
                                           descriptors=np.zeros((0, 32), np.uint8),
                                           points=np.zeros((0, 3), np.float32)))
    maps = {s.id: s.map_id for s in store.sessions()}
    robots = [_robot("r1", [9.0, 0.0, 0.0], ids[-1], sid), _robot("r2", [0.0, 0.0, 0.0], n2, s2),
              _robot("r3", None, None, None)]
    with ApiThread(create_app(FakeService(store, Config(), robots))) as url:
        api = PlannerClient(url)
        assert api.robot("r1")["map"] == maps[sid]
        assert api.robot("r2")["map"] == maps[s2] != maps[sid]  # not localized: its own map
        assert api.robot("r3")["map"] is None  # no keyframe yet
        status, detail = _status(api.nearest_object, "door", robot="r2")
        assert status == 404 and "not localized" in detail
        store.add_link(ids[0], n2, LinkType.GLOBAL_CLOSURE, np.eye(4))  # r2 relocalizes on r1's map
        assert api.robot("r2")["map"] == maps[sid]
        assert api.nearest_object("door", robot="r2")["object"]["label"] == "door"
    store.close()
