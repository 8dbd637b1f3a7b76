"""The REST API under hostile input: a schema-driven fuzz of its OpenAPI (schemathesis) and
the cases users reported, against the real service (`mnemoslam serve` in its own process:
uvicorn, SQLite, Zenoh) holding a streamed session. Bad input gets a 4xx, never a 5xx."""
import collections

import pytest
import requests
import schemathesis
from hypothesis import HealthCheck, Phase, given, settings
from schemathesis import GenerationMode
from schemathesis.checks import not_a_server_error, response_schema_conformance

from mnemoslam.client.datasets import open_dataset
from mnemoslam.client.planner import ApiError
from mnemoslam.client.streamer import stream_dataset
from mnemoslam.client.transport import ZenohSettings
from mnemoslam.service.demo import ServiceProcess

FRAMES = 30
# per operation, generation mode and id choice (plus every boundary case): ~1,000 requests, ~30 s on a quiet 2-core
# machine
EXAMPLES = 40


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    # idle_timeout: p1 must stay listed while the fuzz (longer than the default 60 s) runs before
    # the tests that read it
    # semantics off: the object endpoints' answers without a semantic map
    svc = ServiceProcess(tmp_path_factory.mktemp("api") / "map.db",
                         {"service": {"idle_timeout": 3600.0}, "semantics": {"enabled": False}}).start()
    try:
        stream_dataset(open_dataset("synthetic:loop", max_frames=FRAMES), "p1", ZenohSettings(connect=[svc.endpoint]),
                       rate=None, progress=False, wait_for_subscriber=10.0)
        svc.wait_processed("p1", FRAMES)
        yield svc
    finally:
        svc.stop()


@pytest.mark.parametrize("path", [
    "/sessions/1/nodes?offset=9223372036854775808",  # the reported 500s: ids and offsets beyond SQLite's int64
    "/sessions/99999999999999999999/graph",
    "/sessions/99999999999999999999/nodes",
    "/sessions/99999999999999999999/trajectory",
    "/nodes/99999999999999999999/statistics",
    "/nodes/9223372036854775808/statistics",
    "/sessions/-1/graph",
    "/nodes/-1/statistics",
    "/robots/bad%20robot",  # not a robot id of the wire protocol
    "/robots/" + "r" * 65,
])
def test_out_of_range_parameters_are_422(service, path):
    with pytest.raises(ApiError) as e:
        service.api.get(path)
    assert e.value.status == 422 and e.value.detail


@pytest.mark.parametrize("path", [f"/sessions/{2**63 - 1}/graph", f"/nodes/{2**63 - 1}/statistics"])
def test_largest_int64_id_is_a_clear_404(service, path):
    with pytest.raises(ApiError) as e:
        service.api.get(path)
    assert e.value.status == 404 and e.value.detail


def test_openapi_fuzz_finds_no_server_error(service):
    """Every operation of the served OpenAPI with schemathesis's boundary cases (each bound,
    one beyond it, wrong types, wrong methods) and generated valid (positive) and invalid
    (negative) parameters, with any ids and with the ids of the streamed session (so the
    queries also run on real data): no 5xx, and every response matches its documented schema.
    Derandomized: the same requests on every run."""
    base_url = f"http://127.0.0.1:{service.http_port}"
    schema = schemathesis.openapi.from_url(f"{base_url}/openapi.json")
    operations = [result.ok() for result in schema.get_all_operations()]
    session = service.session_of("p1")
    real_ids = {"session_id": session, "node_id": service.api.nodes(session, limit=1)["nodes"][0]["id"]}
    calls: collections.Counter = collections.Counter()
    failures: dict[str, str] = {}  # the first finding per operation and run
    http = requests.Session()

    def call_and_check(case):
        response = case.call(base_url=base_url, session=http, timeout=10)
        calls[case.operation.label] += 1
        case.validate_response(response, checks=[not_a_server_error, response_schema_conformance])

    def run(name, test):
        try:
            test()
        except (Exception, BaseExceptionGroup) as e:  # every operation's findings, reported together
            failures.setdefault(name, str(e))

    for operation in operations:
        op = operation.label
        both = [GenerationMode.POSITIVE, GenerationMode.NEGATIVE]
        coverage = schema.config.generation_for(operation=operation, phase="coverage")
        # run() calls the lambda at once, in this iteration: the loop variables are the current ones
        run(f"{op} coverage", lambda: [call_and_check(case) for case in schema.iter_coverage_cases(  # noqa: B023
            operation, generation_modes=both, generation_config=coverage)])  # noqa: B023
        fixed = {p.name: real_ids[p.name] for p in operation.path_parameters if p.name in real_ids}
        plans = [(mode, {}) for mode in (both if operation.path_parameters or operation.query else both[:1])]
        if fixed:  # with a real id: nothing left to make invalid unless the operation has a query
            plans += [(mode, fixed) for mode in (both if operation.query else both[:1])]
        for mode, ids in plans:
            @settings(max_examples=EXAMPLES, derandomize=True, database=None, deadline=None,
                      phases=[Phase.explicit, Phase.generate, Phase.shrink],
                      suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])
            @given(case=operation.as_strategy(generation_mode=mode, path_parameters=ids or None))
            def fuzz(case):
                call_and_check(case)

            run(f"{op} {mode.value}{' with real ids' if ids else ''}", fuzz)
    http.close()
    assert not failures, "\n\n".join(f"{k}: {v}" for k, v in failures.items())
    # a fuzz that exercised nothing proves nothing: every route of the API was called, many times
    assert len(operations) >= 10 and set(calls) == {op.label for op in operations}, calls
    assert min(calls.values()) >= 10 and sum(calls.values()) >= 10 * EXAMPLES, calls


def test_semantic_endpoints_on_the_real_service(service):
    """The streamed robot reports where it is; with semantics off and no objects
    the object endpoints say so; without a configured token nothing can change the map."""
    r = service.api.robot("p1")
    assert len(r["position"]) == 3 and isinstance(r["node_id"], int)
    import numpy as np

    # one map: /robots and /robots/{id} name the same one, /sessions says the session is its own (not joined)
    assert r["map"] == 0 and [x["map"] for x in service.api.get("/robots")] == [0]
    s = service.api.get("/sessions")[-1]
    assert (s["map"], s["map_id"], s["joined"], s["joined_keyframe"]) == (0, 0, False, None)
    assert s["T_map_session"] is not None and np.allclose(np.reshape(s["T_map_session"], (4, 4)), np.eye(4), atol=1e-6)
    assert service.api.get(f"/sessions/{s['id']}")["map"] == 0
    with pytest.raises(ApiError) as e:
        service.api.nearest_object("door", robot="p1")
    assert e.value.status == 404 and "no objects" in e.value.detail and "semantics are off" in e.value.detail
    assert service.api.last_semantics == "off" and service.api.semantics()["enabled"] is False
    assert service.api.labels() == {"total": 0, "labels": []}
    path = service.api.objects(point=(0, 0, 0), radius=1.0)
    assert path["total"] == 0
    node = service.api.nodes(service.session_of("p1"), limit=1)["nodes"][0]["id"]
    for token in (None, "guess"):
        client = type(service.api)(service.api.base_url, token=token)
        with pytest.raises(ApiError) as e:
            client.label_node(node, "kitchen")
        assert e.value.status == 403 and "MNEMOSLAM_API_TOKEN" in e.value.detail


def test_grid_endpoints_on_the_real_service(service):
    """Every keyframe the service wrote has its local grid (made where keyframes are written):
    the map's grid has them all, free floor and occupied walls; a path from the robot to a point
    a metre ahead of it along its view exists (issue 25)."""
    import numpy as np

    session = service.session_of("p1")
    keyframes = service.api.nodes(session, limit=1)["total"]
    maps = service.api.maps()
    assert [(m["map"], m["id"], m["keyframes"], m["sessions"], m["robots"]) for m in maps] == [
        (0, 0, keyframes, [session], ["p1"])]
    assert maps[0]["last_change"] > 1.7e9 and maps[0]["objects"] >= 0
    g = service.api.grid(0)
    assert g["keyframes"] == keyframes > 3
    data = np.array(g["data"])
    assert (data == 0).sum() > 1000 and (data == 100).sum() > 100
    r = service.api.robot("p1")
    p = service.api.path("p1", point=tuple(np.add(r["position"], (0.0, 0.0, 1.0))))  # 1 m along the first view
    assert 0.5 < p["length"] < 2.0 and p["map"] == 0
