"""GET /metrics, Prometheus's view of the service: scraped over HTTP from the real service
(`mnemoslam serve` in its own process, real Zenoh on loopback, real SQLite) after a camera
streamed into it, and parsed with prometheus_client's own parser."""
import math

import pytest
import requests
from prometheus_client.parser import text_string_to_metric_families

from mnemoslam.client.datasets import open_dataset
from mnemoslam.client.planner import ApiError
from mnemoslam.client.streamer import stream_dataset
from mnemoslam.client.transport import ZenohSettings
from mnemoslam.service.api import TOKEN_ENV, ApiThread, create_app
from mnemoslam.service.config import load_config
from mnemoslam.service.demo import ServiceProcess
from mnemoslam.service.server import SlamService

from conftest import service_config

FRAMES = 40
TEXT_0_0_4 = "text/plain; version=0.0.4; charset=utf-8"


@pytest.fixture(scope="module")
def svc(tmp_path_factory):
    s = ServiceProcess(tmp_path_factory.mktemp("metrics") / "map.db",
                       service_config({"service": {"idle_timeout": 3600.0}})).start()
    yield s
    s.stop()


def _samples(text: str) -> list:
    return [s for family in text_string_to_metric_families(text) for s in family.samples]


def _value(samples, name: str, **labels) -> float:
    found = [s.value for s in samples if s.name == name and all(s.labels.get(k) == v for k, v in labels.items())]
    assert len(found) == 1, (name, labels, found)
    return found[0]


def test_a_stream_shows_in_the_scraped_metrics(svc):
    stats = stream_dataset(open_dataset("synthetic:loop", max_frames=FRAMES), "m1",
                           ZenohSettings(connect=[svc.endpoint]), rate=None, progress=False, wait_for_subscriber=10.0)
    assert stats.frames == FRAMES
    svc.wait_processed("m1", FRAMES)
    r = svc.wait_mapped("m1")  # every keyframe's map update done: its statistics are in the database
    with pytest.raises(ApiError):
        svc.api.robot("nobody")  # a 404 on a route template

    resp = requests.get(f"http://127.0.0.1:{svc.http_port}/metrics", timeout=10)
    assert resp.status_code == 200 and resp.headers["content-type"] == TEXT_0_0_4
    samples = _samples(resp.text)
    assert samples and all(math.isfinite(s.value) for s in samples), [s for s in samples if not math.isfinite(s.value)]
    m1 = {"robot": "m1"}
    # the robot's frames, as its REST status counts them
    assert _value(samples, "mnemoslam_frames_received_total", **m1) == FRAMES == r["frames_received"]
    assert _value(samples, "mnemoslam_frames_processed_total", **m1) == FRAMES == r["frames_processed"]
    assert _value(samples, "mnemoslam_frames_dropped_total", **m1) == 0
    assert _value(samples, "mnemoslam_frames_tracked_total", **m1) == r["tracked"] > 0
    assert _value(samples, "mnemoslam_keyframes_total", **m1) == r["keyframes"] > 0
    assert _value(samples, "mnemoslam_keyframes_mapped_total", **m1) == r["keyframes_mapped"] == r["keyframes"]
    assert _value(samples, "mnemoslam_queue_depth", **m1) == 0
    assert _value(samples, "mnemoslam_map_backlog", **m1) == 0
    assert _value(samples, "mnemoslam_frames_per_second", **m1) > 0
    assert _value(samples, "mnemoslam_robot_state", robot="m1", state="tracking") == 1
    assert _value(samples, "mnemoslam_robot_state", robot="m1", state="lost") == 0
    assert not [s for s in samples if s.name == "mnemoslam_frames_rejected_total" and s.labels["robot"] == "m1"]
    assert _value(samples, "mnemoslam_robots") == 1
    # the map update of every keyframe (its statistics in the database): a cumulative histogram
    count = _value(samples, "mnemoslam_map_update_seconds_count", **m1)
    assert count == r["keyframes_mapped"]
    assert _value(samples, "mnemoslam_map_update_seconds_sum", **m1) > 0
    buckets = sorted(((float(s.labels["le"]), s.value) for s in samples
                      if s.name == "mnemoslam_map_update_seconds_bucket" and s.labels["robot"] == "m1"))
    assert buckets[-1] == (math.inf, count) and all(a[1] <= b[1] for a, b in zip(buckets, buckets[1:]))
    sizes = {m: _value(samples, "mnemoslam_memory_nodes", robot="m1", memory=m) for m in ("stm", "wm", "ltm")}
    assert sum(sizes.values()) > 0 and sizes["ltm"] == 0  # the default WM is unbounded
    assert _value(samples, "mnemoslam_vocabulary_words", **m1) > 0
    for link in ("loop", "proximity"):
        assert _value(samples, "mnemoslam_loop_closures_total", robot="m1", link=link) >= 0
    # REST latency by route template (wait_processed polled /robots/{robot})
    http = "mnemoslam_http_request_duration_seconds"
    assert _value(samples, f"{http}_count", method="GET", route="/robots/{robot}", status="200") > 0
    assert _value(samples, f"{http}_count", method="GET", route="/robots/{robot}", status="404") == 1
    assert _value(samples, f"{http}_sum", method="GET", route="/robots/{robot}", status="200") > 0
    assert not [s for s in samples if s.labels.get("route", "").startswith("/robots/") and "{" not in s.labels["route"]]
    assert _value(samples, "process_resident_memory_bytes") > 0

    # a scrape is a request too: the next scrape counts it; and OpenMetrics when asked for
    resp = requests.get(f"http://127.0.0.1:{svc.http_port}/metrics", timeout=10,
                        headers={"Accept": "application/openmetrics-text; version=1.0.0"})
    assert resp.headers["content-type"].startswith("application/openmetrics-text; version=1.0.0")
    assert resp.text.endswith("# EOF\n")
    assert _value(_samples(requests.get(f"http://127.0.0.1:{svc.http_port}/metrics", timeout=10).text),
                  f"{http}_count", method="GET", route="/metrics", status="200") == 2


def test_metrics_are_a_read_behind_the_token_with_protect_reads(monkeypatch):
    """With api.protect_reads the scraper sends the token (Prometheus: `authorization`
    in its scrape config); /health stays open. A service that is not running (no database)
    still answers with its service-wide metrics."""
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    service = SlamService(load_config(None, {"api": {"token": "scrape-me", "protect_reads": True}}))
    with ApiThread(create_app(service)) as url:
        assert requests.get(f"{url}/health", timeout=10).status_code == 200
        assert requests.get(f"{url}/metrics", timeout=10).status_code == 401
        assert requests.get(f"{url}/metrics", timeout=10, headers={"Authorization": "Bearer wrong"}).status_code == 401
        # labels stay bounded whatever clients send: made-up methods and paths are not label values
        assert requests.request("BREW", f"{url}/metrics", timeout=10).status_code == 405
        assert requests.get(f"{url}/no/such/path/1234", timeout=10).status_code == 404
        resp = requests.get(f"{url}/metrics", timeout=10, headers={"Authorization": "Bearer scrape-me"})
        assert resp.status_code == 200 and resp.headers["content-type"] == TEXT_0_0_4
        samples = _samples(resp.text)
        assert _value(samples, "mnemoslam_robots") == 0 and _value(samples, "mnemoslam_robot_slots") == 32
        assert _value(samples, "mnemoslam_http_request_duration_seconds_count", method="GET", route="/metrics",
                      status="401") == 2
        http = [s for s in samples if s.name == "mnemoslam_http_request_duration_seconds_count"]
        assert {(s.labels["method"], s.labels["route"], s.labels["status"]) for s in http} == {
            ("GET", "/health", "200"), ("GET", "/metrics", "401"), ("other", "/metrics", "405"),
            ("GET", "unmatched", "404")}
        assert "/metrics" not in requests.get(f"{url}/openapi.json", timeout=10,
                                              headers={"Authorization": "Bearer scrape-me"}).json()["paths"]
