"""Issue 13 (3): the live web viewer. Its page (GET /viewer) in headless Chromium, driven by
Playwright, while the synthetic loop streams with its camera labels into the real service
(`mnemoslam serve` with semantics on): the page's trajectory grows, a door is listed among the
objects, the canvases draw it (screenshot), and the service still stops cleanly with the
page's event stream open. Then the viewer's access rule: with api.protect_reads the token
comes as `?token=` (a browser's EventSource sends no header), and only for the viewer."""
import json
import threading
import time

import cv2
import numpy as np
import pytest
import requests

from mnemoslam.client.datasets import open_dataset
from mnemoslam.client.streamer import stream_dataset
from mnemoslam.client.transport import ZenohSettings
from mnemoslam.service.api import TOKEN_ENV, ApiThread, create_app
from mnemoslam.service.config import load_config
from mnemoslam.service.demo import ServiceProcess, free_port, log_errors
from mnemoslam.service.server import SlamService

from conftest import require_chromium

CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync"]
SESSION_BGR = (255, 163, 77)  # the first session's trajectory colour (#4da3ff) in the screenshot


class _Until:
    """A dataset's frames in order until `stop` is set: the stream then ends at once (the test
    need not wait for the whole loop)."""

    def __init__(self, dataset, stop: threading.Event):
        self.dataset, self.stop = dataset, stop
        self.calibration, self.name = dataset.calibration, dataset.name
        self.class_names = getattr(dataset, "class_names", None)

    def __len__(self):
        return len(self.dataset)

    def __iter__(self):
        for i in range(len(self.dataset)):
            if self.stop.is_set():
                return
            yield self.dataset.frame(i)


def _count(page) -> int:
    return int(page.get_attribute("#traj-count", "data-count"))


def test_viewer_shows_the_stream_live_in_chromium(tmp_path):
    chromium = require_chromium()
    from playwright.sync_api import sync_playwright

    svc = ServiceProcess(tmp_path / "map.db", {"semantics": {"enabled": True, "source": "camera"},
                                               "service": {"idle_timeout": 3600.0}}).start()
    stop, failed = threading.Event(), []

    def stream():
        try:
            stream_dataset(_Until(open_dataset("synthetic:loop", rate=10), stop), "r1",
                           ZenohSettings(connect=[svc.endpoint]), rate=None, progress=False, wait_for_subscriber=10.0,
                           labels=True)
        except Exception as e:  # reported by the test
            failed.append(e)

    streamer = threading.Thread(target=stream, name="stream", daemon=True)
    try:
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=str(chromium), args=CHROMIUM_ARGS, headless=True)
            try:
                page = browser.new_page(viewport={"width": 1280, "height": 860})
                page.goto(f"http://127.0.0.1:{svc.http_port}/viewer")
                page.wait_for_function("document.getElementById('status').textContent === 'live'", timeout=20_000)
                assert _count(page) == 0  # nothing streamed yet
                streamer.start()
                # the trajectory grows while the robot streams: first a few keyframes, then more
                page.wait_for_function("+document.getElementById('traj-count').dataset.count >= 3", timeout=60_000)
                first = _count(page)
                page.wait_for_function(f"+document.getElementById('traj-count').dataset.count > {first}",
                                       timeout=60_000)
                assert not failed, failed
                # a door fused from the camera's labels is listed among the objects
                door = page.wait_for_selector('#objects li[data-label="door"]', timeout=90_000)
                assert "door" in door.inner_text()
                # the robot's live row and its session's memory sizes (from the map update's statistics)
                page.wait_for_function("document.querySelector('#robots tbody').innerText.includes('r1')")
                page.wait_for_function("[...document.querySelectorAll('#sessions tbody td')]"
                                       ".some((td, i) => i % 6 === 4 && /^[0-9]+$/.test(td.textContent))",
                                       timeout=30_000)
                page.wait_for_timeout(700)  # one more update drawn
                shot = tmp_path / "viewer.png"
                page.screenshot(path=str(shot))
                boxes = {name: page.locator(f"#{name}").bounding_box() for name in ("top", "orbit")}
                updates = int(page.get_attribute("#updates", "data-updates"))
                assert updates >= 3
                # the service stops (exit 0) with the page's event stream still open
                stop.set()
                streamer.join(60)
                assert not streamer.is_alive()
                t = time.monotonic()
                assert svc.stop(timeout=30) == 0
                assert time.monotonic() - t < 20
                page.wait_for_function("document.getElementById('status').textContent !== 'live'", timeout=20_000)
            finally:
                browser.close()
    finally:
        stop.set()
        if streamer.is_alive():
            streamer.join(60)
        svc.stop()
    assert not failed, failed
    assert log_errors(svc.log_path) == []  # no error in the service, its shutdown with the stream open included

    image = cv2.imread(str(shot))
    assert image is not None and image.shape[0] >= 800 and image.shape[1] >= 1200, "not a full-page PNG"
    for name, box in boxes.items():
        x, y, w, h = (int(round(box[k])) for k in ("x", "y", "width", "height"))
        area = image[y:y + h, x:x + w]
        assert area.size and area.reshape(-1, 3).std(axis=0).max() > 8, f"the {name} canvas is blank"
        # the trajectory is drawn in its session's colour
        drawn = np.all(np.abs(area.astype(int) - SESSION_BGR) <= 12, axis=2).sum()
        assert drawn > 30, f"no trajectory on the {name} canvas ({drawn} pixels of its colour)"


def _first_event(url: str, **params) -> dict:
    with requests.get(url, params=params, stream=True, timeout=10) as r:
        assert r.status_code == 200, r.text
        assert r.headers["content-type"].startswith("text/event-stream")
        for line in r.iter_lines(decode_unicode=True):
            if line.startswith("data: "):
                return json.loads(line[len("data: "):])
    raise AssertionError("the stream ended without an update")


def test_viewer_takes_the_token_as_a_query_parameter_with_protect_reads(tmp_path, monkeypatch):
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    config = load_config(None, {"api": {"token": "view-me", "protect_reads": True},
                                "storage": {"path": str(tmp_path / "map.db")},
                                "zenoh": {"listen": [f"tcp/127.0.0.1:{free_port()}"]}})
    service = SlamService(config).start()
    server = ApiThread(create_app(service)).start()
    try:
        url = server.url
        for path in ("/viewer", "/viewer/events"):
            assert requests.get(url + path, timeout=10).status_code == 401
            r = requests.get(url + path, params={"token": "wrong"}, timeout=10)
            assert r.status_code == 401 and "/viewer?token=" in r.json()["detail"]
        page = requests.get(url + "/viewer", params={"token": "view-me"}, timeout=10)
        assert page.status_code == 200 and "<canvas" in page.text
        assert requests.get(url + "/viewer", headers={"Authorization": "Bearer view-me"}, timeout=10).status_code == 200
        first = _first_event(url + "/viewer/events", token="view-me")
        assert first["reset"] is True and first["robots"] == [] and first["sessions"] == []
        # only the viewer takes the token from the URL
        assert requests.get(url + "/robots", params={"token": "view-me"}, timeout=10).status_code == 401
        assert "/viewer" not in requests.get(url + "/openapi.json", headers={"Authorization": "Bearer view-me"},
                                             timeout=10).json()["paths"]
        # an open event stream does not hold the server's shutdown
        held = requests.get(url + "/viewer/events", params={"token": "view-me"}, stream=True, timeout=10)
        assert next(held.iter_lines()) is not None
        t = time.monotonic()
        server.stop()
        assert not server._thread.is_alive() and time.monotonic() - t < 5
        held.close()
    finally:
        server.stop()
        service.stop()


class _Service:
    """The service as the viewer reads it: its store and its robots."""

    def __init__(self, store, robots):
        self.store, self._robots = store, robots

    def robots(self):
        return list(self._robots)


def _keyframe(store, sid, x: float) -> int:
    from mnemoslam.storage.records import KeyframeRecord

    pose = np.eye(4)
    pose[0, 3] = x
    rng = np.random.default_rng(int(x * 10))
    return store.add_keyframe(KeyframeRecord(session_id=sid, stamp=x, pose=pose,
                                             keypoints=(rng.random((20, 2)) * 640).astype(np.float32),
                                             descriptors=rng.integers(0, 256, (20, 32), dtype=np.uint8),
                                             points=rng.normal(size=(20, 3)).astype(np.float32)))


def test_feed_sends_what_changed(tmp_path):
    """The feed of one client over a real map: a first full update (trajectory decimated, the
    memory sizes, the objects), then nothing while nothing changes, new keyframes appended,
    the whole trajectory again with its loop link when one is added (and every `full_every`
    seconds while live), and the session marked ended when its robot goes."""
    from mnemoslam.service.semantics.queries import ObjectIndex
    from mnemoslam.service.viewer import Limits, ViewerFeed
    from mnemoslam.storage.records import LinkType

    from test_api_objects import _robot, make_map

    store, sid, ids, _ = make_map(tmp_path / "map.db")  # keyframes at x = 0..9; doors, chairs, a table
    store.set_statistics(ids[-1], {"timings_ms": {"loop": 1.0}, "memory": {"stm": 3, "wm": 7, "ltm": 0, "words": 42}})
    now = [100.0]
    service = _Service(store, [_robot("r1", [9.0, 0.0, 0.0], ids[-1], sid)])
    index = ObjectIndex(store)
    feed = ViewerFeed(service, objects=lambda s: index, limits=Limits(max_points=4, full_every=5.0),
                      clock=lambda: now[0])
    try:
        first = feed.next()
        assert first["reset"] is True and first["robots"][0]["robot"] == "r1"
        (s,) = first["sessions"]
        assert s["id"] == sid and s["live"] is True and s["full"] is True and s["nodes"] == 10
        assert np.reshape(s["points"], (-1, 3))[:, 0].tolist() == [0.0, 3.0, 6.0, 9.0]  # decimated, ends kept
        assert s["links"] == [] and s["memory"] == {"stm": 3, "wm": 7, "ltm": 0, "words": 42}
        assert first["objects"]["total"] == 5
        assert {"door", "chair", "table"} == {o["label"] for o in first["objects"]["items"]}
        assert ["door", 2] in first["objects"]["labels"]

        quiet = feed.next()
        assert quiet["reset"] is False and quiet["sessions"] == [] and "objects" not in quiet

        new = [_keyframe(store, sid, 10.0), _keyframe(store, sid, 11.0)]
        (s,) = feed.next()["sessions"]
        assert s["full"] is False and s["nodes"] == 12 and s["points"] == [10.0, 0.0, 0.0, 11.0, 0.0, 0.0]

        store.add_link(ids[0], new[-1], LinkType.GLOBAL_CLOSURE, np.eye(4))  # a loop closure
        (s,) = feed.next()["sessions"]
        assert s["full"] is True and s["nodes"] == 12 and len(s["points"]) == 4 * 3
        assert s["links"] == [["loop", 0.0, 0.0, 0.0, 11.0, 0.0, 0.0]]
        assert feed.next()["sessions"] == []

        now[0] += 6.0  # a live session's whole trajectory again every full_every seconds
        (s,) = feed.next()["sessions"]
        assert s["full"] is True and s["links"] == [["loop", 0.0, 0.0, 0.0, 11.0, 0.0, 0.0]]

        service._robots = []  # the robot went: its session is ended, sent once more as such
        (s,) = feed.next()["sessions"]
        assert s["live"] is False and "points" not in s
        now[0] += 6.0
        assert feed.next()["sessions"] == []  # nothing changed in it
    finally:
        index.close()
        store.close()


def _extent_x(page, canvas: str) -> tuple[int, int]:
    """Leftmost and rightmost pixel columns of the first session's colour on a canvas."""
    box = page.locator(f"#{canvas}").bounding_box()
    png = page.screenshot(clip=box)
    image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    cols = np.flatnonzero(np.all(np.abs(image.astype(int) - SESSION_BGR) <= 12, axis=2).any(axis=0))
    assert len(cols), f"no trajectory on the {canvas} canvas"
    return int(cols[0]), int(cols[-1])


def test_viewer_pans_and_zooms_in_chromium(tmp_path):
    """The top-down view: the wheel zooms about the cursor, a drag pans, a double-click fits
    the map again; the 3D view: shift-drag pans its target, a double-click resets it. Checked
    on the view state the page exposes and on the drawn trajectory (x = 0..9 m)."""
    chromium = require_chromium()
    from playwright.sync_api import sync_playwright

    from test_api_objects import make_map

    store, sid, ids, _ = make_map(tmp_path / "map.db")
    service = _Service(store, [])
    service.config = load_config()
    server = ApiThread(create_app(service)).start()
    view = lambda page, name: json.loads(page.get_attribute(f"#{name}", "data-view"))  # noqa: E731
    try:
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=str(chromium), args=CHROMIUM_ARGS, headless=True)
            try:
                page = browser.new_page(viewport={"width": 1280, "height": 860})
                page.goto(server.url + "/viewer")
                page.wait_for_function("+document.getElementById('traj-count').dataset.count >= 2", timeout=20_000)
                page.wait_for_timeout(300)
                # the sessions table lists the session under its frame's map (its own here)
                assert page.get_attribute(f'#sessions tr[data-session="{sid}"]', "data-map") == str(
                    store.sessions()[0].map_id)
                fitted = view(page, "top")
                assert fitted["fitted"] is True
                left, right = _extent_x(page, "top")
                box = page.locator("#top").bounding_box()
                centre = (box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
                # zoom out about the canvas centre: the same metres now span fewer pixels
                page.mouse.move(*centre)
                page.mouse.wheel(0, 500)
                page.wait_for_timeout(300)
                zoomed = view(page, "top")
                assert zoomed["fitted"] is False and zoomed["k"] == pytest.approx(fitted["k"] * np.exp(-0.5), rel=1e-6)
                assert zoomed["cx"] == pytest.approx(fitted["cx"], abs=1e-6)  # the cursor's point stays
                l2, r2 = _extent_x(page, "top")
                assert (r2 - l2) / (right - left) == pytest.approx(np.exp(-0.5), abs=0.05)
                # drag 120 px to the right: the map moves with the pointer
                page.mouse.move(*centre)
                page.mouse.down()
                page.mouse.move(centre[0] + 60, centre[1], steps=3)
                page.mouse.move(centre[0] + 120, centre[1], steps=3)
                page.mouse.up()
                page.wait_for_timeout(300)
                panned = view(page, "top")
                assert panned["cx"] == pytest.approx(zoomed["cx"] - 120 / zoomed["k"], rel=1e-3, abs=1e-3)
                l3, r3 = _extent_x(page, "top")
                assert abs((l3 - l2) - 120) <= 3 and abs((r3 - r2) - 120) <= 3
                # a double-click fits the map again
                page.mouse.dblclick(*centre)
                page.wait_for_timeout(300)
                assert view(page, "top") == fitted and _extent_x(page, "top") == (left, right)
                # 3D: shift-drag moves the orbit's target, a double-click resets the view
                before = view(page, "orbit")
                obox = page.locator("#orbit").bounding_box()
                ocentre = (obox["x"] + obox["width"] / 2, obox["y"] + obox["height"] / 2)
                page.keyboard.down("Shift")
                page.mouse.move(*ocentre)
                page.mouse.down()
                page.mouse.move(ocentre[0] + 80, ocentre[1] + 40, steps=4)
                page.mouse.up()
                page.keyboard.up("Shift")
                page.wait_for_timeout(300)
                moved = view(page, "orbit")
                assert moved["yaw"] == before["yaw"] and moved["pitch"] == before["pitch"]  # panned, not orbited
                assert np.linalg.norm(np.subtract(moved["target"], before["target"])) > 0.1
                page.mouse.dblclick(*ocentre)
                page.wait_for_timeout(300)
                assert view(page, "orbit") == before
            finally:
                browser.close()
    finally:
        server.stop()
        store.close()


def test_feed_tells_which_sessions_share_a_frame(tmp_path):
    """Each session's "frame" is the map id of the oldest session links join it to: a second
    robot's session has its own until a loop link places it in the first one's frame, then
    that frame is sent once (the page lists the session under that map)."""
    from mnemoslam.client.kernel.frames import Calibration, PinholeCamera
    from mnemoslam.service.semantics.queries import ObjectIndex
    from mnemoslam.service.viewer import ViewerFeed
    from mnemoslam.storage.records import LinkType

    from test_api_objects import make_map

    store, sid, ids, _ = make_map(tmp_path / "map.db")
    s2 = store.begin_session("r2", Calibration(PinholeCamera(500.0, 500.0, 320.0, 240.0, 640, 480)))
    second = [_keyframe(store, s2, 20.0), _keyframe(store, s2, 21.0)]
    store.add_link(second[0], second[1], LinkType.NEIGHBOR, np.eye(4))
    maps = {s.id: s.map_id for s in store.sessions()}
    index = ObjectIndex(store)
    feed = ViewerFeed(_Service(store, []), objects=lambda s: index)
    try:
        first = {e["id"]: e for e in feed.next()["sessions"]}
        assert first[sid]["frame"] == maps[sid] and first[s2]["frame"] == maps[s2] != maps[sid]
        assert all("frame" not in e for e in feed.next()["sessions"])  # sent when it changes
        store.add_link(ids[-1], second[1], LinkType.GLOBAL_CLOSURE, np.eye(4))  # r2 relocalizes on r1's map
        update = {e["id"]: e for e in feed.next()["sessions"]}
        assert update[s2]["frame"] == maps[sid] and "frame" not in update.get(sid, {})
    finally:
        index.close()
        store.close()
