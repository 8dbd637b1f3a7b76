"""Issues 14 and 24 through the service: the synthetic scene streamed with its camera labels
(`stream ... --labels`) into `mnemoslam serve` with no semantic settings (the default source,
auto, takes the camera's labels); then
`GET /objects/nearest?label=door&robot=r1` answers the true nearest door to the robot's final
pose, and the other object endpoints agree with it."""
import time

import numpy as np
import pytest

from mnemoslam.client.datasets import open_dataset
from mnemoslam.client.streamer import stream_dataset
from mnemoslam.client.transport import ZenohSettings
from mnemoslam.service.demo import ServiceProcess, true_doors_in_map_frame

TOKEN = "test-token"


@pytest.fixture(scope="module")
def streamed(tmp_path_factory):
    ds = open_dataset("synthetic:loop", rate=5)  # 300 frames: every door is seen from several keyframes
    svc = ServiceProcess(tmp_path_factory.mktemp("sem") / "map.db",
                         {"api": {"token": TOKEN}, "service": {"idle_timeout": 3600.0}}).start()
    try:
        stream_dataset(ds, "r1", ZenohSettings(connect=[svc.endpoint]), rate=None, progress=False,
                       wait_for_subscriber=10.0, labels=True)
        svc.wait_processed("r1", len(ds), timeout=900)
        svc.wait_mapped("r1", timeout=600)
        yield svc, ds
    finally:
        svc.stop()


def test_nearest_door_to_the_robot_is_the_true_one(streamed):
    svc, ds = streamed
    api = svc.api
    status = api.semantics()
    assert status["enabled"] is True and status["source"] == "auto"
    # every keyframe fused from the camera's labels, live or (queue full) by the back-fill
    deadline = time.monotonic() + 180
    while status["coverage"]["segmented"] < status["coverage"]["keyframes"] and time.monotonic() < deadline:
        time.sleep(0.5)
        status = api.semantics()
    assert status["coverage"]["segmented"] == status["coverage"]["keyframes"] > 0, status
    worker = status["worker"]
    assert worker["processed"] >= status["coverage"]["segmented"] and worker["errors"] == 0, worker  # merged: uncounted
    robot = api.robot("r1")
    at = np.array(robot["position"])
    doors = true_doors_in_map_frame(ds)
    d = np.linalg.norm(doors - at, axis=1)
    truth = doors[np.argmin(d)]
    answer = api.nearest_object("door", robot="r1")
    assert api.last_semantics == "on"
    print("nearest door off by", np.linalg.norm(np.array(answer["object"]["position"]) - truth))
    assert np.linalg.norm(np.array(answer["object"]["position"]) - truth) < 0.3, (answer, truth, sorted(d)[:3])
    assert answer["distance"] == pytest.approx(np.linalg.norm(np.array(answer["object"]["position"]) - at), abs=1e-6)
    # the same object by point, by id, in the list around the robot and among the labels
    assert api.nearest_object("door", point=tuple(at))["object"]["id"] == answer["object"]["id"]
    assert api.object(answer["object"]["id"])["label"] == "door"
    around = api.objects(label="door", point=tuple(at), limit=1)
    assert around["objects"][0]["id"] == answer["object"]["id"]
    assert {"door"} <= {x["label"] for x in api.labels()["labels"]}
    path = api.object_path(answer["object"]["id"], robot="r1")
    assert path["nodes"][0]["id"] == path["start_node"] and path["nodes"][-1]["id"] == path["goal_node"]
    assert path["goal_distance"] < 3.0
