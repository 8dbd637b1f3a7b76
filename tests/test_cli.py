"""The `mnemoslam` command line: what it prints, its argument checks, --set, progress bars."""
from __future__ import annotations

import io
import os
import re
import selectors
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path
from types import SimpleNamespace

import pytest

from mnemoslam.service.cli import main

from conftest import service_config

ROOT = Path(__file__).resolve().parents[1]


class TtyIO(io.StringIO):
    """A stderr that says it is a terminal."""

    def isatty(self):
        return True


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def fake_run(monkeypatch):
    """mnemoslam.service.runner.run_dataset replaced by a recorder (no pipeline runs)."""
    calls = []

    def run_dataset(dataset, config, out_dir=None, progress=True, db=None):
        calls.append(SimpleNamespace(config=config, progress=progress, db=db, dataset=dataset))
        return SimpleNamespace(summary=SimpleNamespace(line=lambda: "fake run", map_line=lambda: None, tracked=1),
                               trajectory=[])

    monkeypatch.setattr("mnemoslam.service.runner.run_dataset", run_dataset)
    return calls


@pytest.fixture
def fake_demo(monkeypatch):
    calls = []

    def run_demo(trajectory="loop", rate=15.0, noise=True, out="out/demo", progress=True, overrides=None):
        calls.append(SimpleNamespace(progress=progress, overrides=overrides))
        return 0

    monkeypatch.setattr("mnemoslam.service.demo.run_demo", run_demo)
    return calls


# -- run ------------------------------------------------------------------------------------

def test_run_prints_no_progress_when_stderr_is_not_a_terminal(tmp_path, capsys):
    assert main(["run", "synthetic:straight", "--out", str(tmp_path / "o"), "--max-frames", "30"]) == 0
    out, err = capsys.readouterr()
    assert "30 frames" in out
    assert err == ""  # no progress bar lines (captured stderr is not a terminal)
    # no loop on a straight path: said plainly, no nan, no vacuous 1.000 (0/0)
    assert "no loop links" in out and "no true revisits" in out and "nan" not in out and "0/0" not in out
    # the graph's links against ground truth, per type, printed and written (links.csv, links.json)
    assert "links        odometry" in out and " beyond 5 cm or 3 deg" in out
    # the ATE aligned with scale too: exact synthetic depth, so the sizes agree
    sim3 = re.search(r"ATE RMSE ([0-9.]+) cm aligned with scale \(Sim\(3\)\): the ground truth is ([0-9.]+)x", out)
    assert sim3 and abs(float(sim3.group(2)) - 1.0) < 0.01, out
    rows = (tmp_path / "o" / "links.csv").read_text().splitlines()
    assert rows[0] == "from_id,to_id,type,error_cm,error_deg" and any(",odometry," in r for r in rows[1:])
    assert (tmp_path / "o" / "links.json").exists()


def test_progress_bars_only_on_a_terminal_and_not_with_quiet(tmp_path, monkeypatch, fake_run, fake_demo):
    out = str(tmp_path / "o")
    main(["run", "synthetic:loop", "--out", out, "--max-frames", "2"])
    main(["demo"])
    monkeypatch.setattr(sys, "stderr", TtyIO())
    main(["run", "synthetic:loop", "--out", out, "--max-frames", "2"])
    main(["run", "synthetic:loop", "--out", out, "--max-frames", "2", "-q"])
    main(["demo"])
    main(["demo", "-q"])
    assert [c.progress for c in fake_run] == [False, True, False]
    assert [c.progress for c in fake_demo] == [False, True, False]


@pytest.mark.parametrize("value", ["0", "-1", "x"])
def test_run_max_frames_must_be_positive(tmp_path, capsys, value):
    with pytest.raises(SystemExit) as e:
        main(["run", "synthetic:loop", "--out", str(tmp_path / "o"), "--max-frames", value])
    assert e.value.code == 2
    assert "--max-frames" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_run_depth_registration_reaches_the_7scenes_player(tmp_path, fake_run, capsys):
    """--depth-registration auto|on|off: the 7-Scenes player's `register` (None, True, False);
    any other dataset refuses on/off in one line."""
    import cv2
    import numpy as np

    seq = tmp_path / "scene" / "seq-01"
    seq.mkdir(parents=True)
    for k in range(2):
        cv2.imwrite(str(seq / f"frame-{k:06d}.color.png"), np.full((12, 16, 3), 100 + k, np.uint8))
        cv2.imwrite(str(seq / f"frame-{k:06d}.depth.png"), np.full((12, 16), 1500, np.uint16))
        np.savetxt(seq / f"frame-{k:06d}.pose.txt", np.eye(4))
    (tmp_path / "scene" / "camera-intrinsics.txt").write_text("20 0 8\n0 20 6\n0 0 1\n")  # not the Kinect's
    out = str(tmp_path / "o")
    for option, registered in ((None, False), ("auto", False), ("on", True), ("off", False)):
        extra = ["--depth-registration", option] if option else []
        assert main(["run", str(seq.parent), "--out", out, *extra]) == 0
        assert (fake_run[-1].dataset.registration is not None) == registered, option
    assert main(["run", "synthetic:loop", "--out", out, "--max-frames", "2", "--depth-registration", "off"]) == 2
    assert "applies to 7-Scenes only" in capsys.readouterr().err


def test_run_set_overrides_config_keys(tmp_path, fake_run):
    out = str(tmp_path / "o")
    assert main(["run", "synthetic:loop", "--out", out, "--max-frames", "2", "--set", "loop.enabled=false",
                 "--set", "service.queue_size=30", "--set", "loop.threshold=1", "--set", "seed=7",
                 "--set", "zenoh.listen=[tcp/127.0.0.1:1, tcp/127.0.0.1:2]"]) == 0
    c = fake_run[-1].config
    assert c.loop.enabled is False and c.service.queue_size == 30 and c.seed == 7
    assert c.loop.threshold == 1.0 and isinstance(c.loop.threshold, float)
    assert c.zenoh.listen == ["tcp/127.0.0.1:1", "tcp/127.0.0.1:2"]
    # a --config file, then --set, then the dedicated options
    cfg = tmp_path / "c.yaml"
    cfg.write_text("service:\n  queue_size: 5\nmemory:\n  stm_size: 4\n")
    main(["run", "synthetic:loop", "--out", out, "--config", str(cfg), "--set", "service.queue_size=6",
          "--set", "loop.enabled=true", "--odometry-only"])
    c = fake_run[-1].config
    assert (c.service.queue_size, c.memory.stm_size, c.loop.enabled) == (6, 4, False)


def test_run_db_and_frames_reach_the_run(tmp_path, capsys, fake_run):
    out = str(tmp_path / "o")
    assert main(["run", "synthetic:walk_a?rate=5", "--out", out, "--db", str(tmp_path / "m.db"),
                 "--frames", "10:20", "--max-frames", "4"]) == 0
    c = fake_run[-1]
    assert c.db == str(tmp_path / "m.db") and len(c.dataset) == 4 and c.dataset.origin(0) == 10
    assert main(["run", "synthetic:walk_a?rate=5", "--out", out, "--frames", "170:"]) == 0
    assert fake_run[-1].db is None and len(fake_run[-1].dataset) == 11
    # a missing folder for --db and a bad range are one-line errors before any run
    assert main(["run", "synthetic:loop", "--out", out, "--db", str(tmp_path / "no" / "m.db")]) == 2
    assert "does not exist" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["run", "synthetic:loop", "--out", out, "--frames", "9:3"])
    assert "START < END" in capsys.readouterr().err and len(fake_run) == 2


@pytest.mark.parametrize("item, message", [
    ("loop.enable=false", "unknown config key 'loop.enable'"),
    ("nosuch.key=1", "unknown config key 'nosuch'"),
    ("service.queue_size=lots", "'service.queue_size': expected int"),
    ("loop.enabled=[1, 2]", "'loop.enabled': expected bool"),
    ("loop=false", "loop: expected a mapping"),
    ("loop.enabled", "expected KEY=VALUE"),
    ("loop.enabled=[1", "not valid YAML"),
])
def test_run_bad_set_is_a_clear_error(tmp_path, capsys, fake_run, item, message):
    assert main(["run", "synthetic:loop", "--out", str(tmp_path / "o"), "--set", item]) == 2
    err = capsys.readouterr().err
    assert err.startswith("mnemoslam run: error: ") and message in err and len(err.splitlines()) == 1
    assert fake_run == []


# -- demo -----------------------------------------------------------------------------------

def test_demo_set_goes_to_its_service(fake_demo):
    assert main(["demo", "--set", "loop.enabled=false", "--set", "service.queue_size=30"]) == 0
    assert fake_demo[-1].overrides == {"loop": {"enabled": False}, "service": {"queue_size": 30}}


@pytest.mark.parametrize("item, message", [
    ("loop.bogus=1", "unknown config key 'loop.bogus'"),
    ("api.port=9999", "the demo sets it"),
    ("storage.path=x.db", "the demo sets it"),
])
def test_demo_bad_set_fails_before_anything_starts(tmp_path, capsys, item, message):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--set", item]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_service_process_takes_nested_and_top_level_keys(tmp_path):
    import yaml

    from mnemoslam.service.demo import ServiceProcess

    svc = ServiceProcess(tmp_path / "m.db",
                         service_config({"service": {"queue_size": 3}, "loop": {"enabled": False}, "seed": 2}))
    cfg = yaml.safe_load(svc.config_path.read_text())
    assert cfg["service"] == {"queue_size": 3} and cfg["loop"] == {"enabled": False} and cfg["seed"] == 2
    assert cfg["zenoh"]["listen"] == [svc.endpoint] and cfg["api"]["port"] == svc.http_port


def test_service_process_picks_other_ports_when_its_port_was_taken(tmp_path):
    """The API port `free_port` picked is taken by another process before the child binds it:
    the child exits ("address already in use"), and `start` picks other ports and starts it."""
    import socket

    import yaml

    from mnemoslam.service.demo import ServiceProcess

    svc = ServiceProcess(tmp_path / "m.db", service_config())
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        cfg = yaml.safe_load(svc.config_path.read_text())
        cfg["api"]["port"] = svc.http_port = port  # as if another process had taken it meanwhile
        svc.config_path.write_text(yaml.safe_dump(cfg))
        svc.start()
        try:
            assert svc.http_port != port and svc.api.health()["status"] == "ok"
        finally:
            svc.stop()
    with pytest.raises(RuntimeError, match="exited with 2"):  # no attempt left: the log's reason is raised
        with socket.socket() as taken:
            taken.bind(("127.0.0.1", 0))
            taken.listen()
            other = ServiceProcess(tmp_path / "n.db", service_config({"api": {"port": taken.getsockname()[1]}}))
            other.start(attempts=1)


def test_demo_log_scan_reports_errors(tmp_path):
    from mnemoslam.service.demo import log_errors, log_report

    log = tmp_path / "service.log"
    log.write_text("mnemoslam serve: REST http://127.0.0.1:1; ...\n"
                   "2026-01-01 10:00:00,000 INFO mnemoslam.service: service started\n"
                   "2026-01-01 10:00:01,000 ERROR mnemoslam.session: robot demo: frame 3 failed\n"
                   "Traceback (most recent call last):\n"
                   '  File "x.py", line 1, in <module>\n'
                   "ValueError: boom\n"
                   "2026-01-01 10:00:02,000 INFO mnemoslam.service: service stopped\n")
    assert len(log_errors(log)) == 2
    report = log_report(log)
    assert "2 error lines" in report and str(log) in report and "frame 3 failed" in report
    clean = tmp_path / "clean.log"
    clean.write_text("2026-01-01 10:00:00,000 INFO mnemoslam.service: service started\n")
    assert log_report(clean) is None and log_report(tmp_path / "missing.log") is None
    one = tmp_path / "one.log"
    one.write_text("Traceback (most recent call last):\n  File ...\nRuntimeError: x\n")
    assert "1 error line (" in log_report(one)


# -- serve ----------------------------------------------------------------------------------

def test_serve_db_in_a_missing_folder_is_an_error(tmp_path, capsys):
    db = tmp_path / "typo" / "dir" / "x.db"
    assert main(["serve", "--db", str(db)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("mnemoslam serve: error: ") and str(db.parent) in err and "does not exist" in err
    assert not (tmp_path / "typo").exists()
    (tmp_path / "file").write_text("")
    assert main(["serve", "--set", f"storage.path={tmp_path / 'file' / 'x.db'}"]) == 2
    assert "is not a folder" in capsys.readouterr().err


def _serve(tmp_path, *args) -> tuple[subprocess.Popen, str]:
    """`mnemoslam serve` in a child process and the first line it prints."""
    proc = subprocess.Popen([sys.executable, "-m", "mnemoslam.service.cli", "serve", *args], cwd=ROOT, text=True,
                            stdout=subprocess.PIPE, stderr=open(tmp_path / "stderr", "w"),
                            env=dict(os.environ, PYTHONPATH=str(ROOT)))
    sel = selectors.DefaultSelector()
    sel.register(proc.stdout, selectors.EVENT_READ)
    line = proc.stdout.readline() if sel.select(timeout=60) else ""
    sel.close()
    if not line:
        proc.kill()
        proc.wait()
        pytest.fail(f"serve printed nothing; stderr: {(tmp_path / 'stderr').read_text()}")
    return proc, line


def _stop(proc: subprocess.Popen) -> int:
    proc.send_signal(signal.SIGTERM)
    try:
        return proc.wait(30)
    finally:
        proc.kill()
        proc.stdout.close()


def test_exit_process_flushes_what_was_written_and_skips_finalization():
    """`serve` and its mapping child end with `exit_process` (service/shutdown.py): what the
    process logged and printed reaches its pipes, the exit code is the one given, and nothing of
    Python's finalization runs (an atexit handler would)."""
    code = ("import atexit, logging; from mnemoslam.service.shutdown import exit_process; "
            "logging.basicConfig(); logging.getLogger('x').warning('the last line'); print('out', end=''); "
            "atexit.register(lambda: print(' atexit ran')); exit_process(3)")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}  # a pipe's stdout is then buffered
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, env=env)
    assert p.returncode == 3 and p.stdout == "out" and "the last line" in p.stderr, p


def test_serve_prints_where_it_listens(tmp_path):
    db = tmp_path / "map.db"
    zenoh = f"tcp/127.0.0.1:{free_port()}"
    proc, line = _serve(tmp_path, "--db", str(db), "--listen", zenoh, "--set", "api.port=0",
                        "--set", "loop.process=false")
    try:
        assert line.startswith("mnemoslam serve: REST http://127.0.0.1:")
        assert f"listen {zenoh}" in line and "connect none" in line and f"database {db}" in line
        url = line.split("REST ")[1].split(";")[0]
        port = int(url.rsplit(":", 1)[1])
        assert port > 0  # port 0 in the config: the line names the port actually bound
        deadline = time.monotonic() + 20
        while True:
            try:
                with urllib.request.urlopen(url + "/health", timeout=2) as r:
                    assert r.status == 200
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.1)
    finally:
        code = _stop(proc)
    assert code == 0
    assert "INFO mnemoslam.service: service started" in (tmp_path / "stderr").read_text()  # the log lines stay


def test_serve_rest_off(tmp_path):
    proc, line = _serve(tmp_path, "--db", str(tmp_path / "map.db"), "--listen", f"tcp/127.0.0.1:{free_port()}",
                        "--set", "api.enabled=false", "--set", "loop.enabled=false")
    try:
        assert line.startswith("mnemoslam serve: REST off; Zenoh peer listen tcp/127.0.0.1:")
    finally:
        assert _stop(proc) == 0


def test_rest_sockets_are_tcp_so_responses_are_not_held_back():
    """asyncio sets TCP_NODELAY only on connections accepted from a socket whose proto is TCP;
    with proto 0 every response on a kept-alive connection waited ~40 ms (uvicorn writes the
    headers and the body apart: Nagle's algorithm holds the body until the client's delayed ACK)."""
    import socket

    from fastapi import FastAPI

    from mnemoslam.service.api import ApiThread
    from mnemoslam.service.cli import _listen_socket

    sock = _listen_socket("127.0.0.1", 0)
    api = ApiThread(FastAPI())
    try:
        assert sock.proto == api.sock.proto == socket.IPPROTO_TCP
    finally:
        sock.close()
        api.sock.close()


def test_demo_noise_is_the_paths_own_model_where_it_has_one():
    """`mnemoslam demo --trajectory fastrot` streams fastrot as the bench runs it (Kinect
    disparity noise and motion blur), the other paths with the axial model."""
    from mnemoslam.service.demo import _has_noise

    assert _has_noise("fastrot") and not _has_noise("loop") and not _has_noise("figure8")
    assert not _has_noise("no-such-path")


# -- rough edges of a first use (issue 24) ------------------------------------------------------

def _cli(*args, cwd, **kw) -> subprocess.Popen:
    """`mnemoslam ...` (this checkout's) as a user runs it, in the folder `cwd`."""
    return subprocess.Popen([sys.executable, "-m", "mnemoslam.service.cli", *args], cwd=cwd, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            env=dict(os.environ, PYTHONPATH=str(ROOT)), **kw)


def test_demo_runs_from_an_empty_folder(tmp_path):
    """`mnemoslam demo` outside the checkout: it makes its output folder where it runs and
    says where the map is (it failed: "the folder out/demo does not exist"). --frames keeps it
    short; `make demo` streams the whole path."""
    proc = _cli("demo", "--frames", "45", "-q", cwd=tmp_path)
    try:
        out, err = proc.communicate(timeout=300)
    finally:
        proc.kill()
    assert proc.returncode == 0, out + err
    db = tmp_path / "out" / "demo" / "map.db"
    lines = out.splitlines()
    assert lines[0] == f"demo: starting the service (database {db})"
    assert lines[1].startswith("demo: streaming synthetic-loop (45 frames) over Zenoh")
    assert lines[2].startswith("demo: service processed 45 frames (45 tracked, ")
    assert re.match(r"demo: keyframe ATE RMSE [0-9.]+ cm over \d+ keyframes", lines[3])
    assert lines[4].startswith("demo: REST GET /sessions/1/nodes?bbox=")
    assert lines[-1] == f"demo: service stopped (exit 0); map in {db}"
    assert db.is_file() and (tmp_path / "out" / "demo" / "service.log").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_stream_to_an_address_where_nothing_listens_fails_fast(tmp_path):
    """Nothing listens at the address: `stream` exits non-zero within ~10 s naming it (it
    streamed on at ~1.6 s a frame and failed only at the end)."""
    address = f"tcp/127.0.0.1:{free_port()}"
    t0 = time.monotonic()
    proc = _cli("stream", "synthetic:loop", "--max-frames", "100", "--connect", address, "-q", cwd=tmp_path)
    try:
        out, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    took = time.monotonic() - t0
    assert proc.returncode != 0 and took < 12, (took, out, err)
    assert f"nothing listens at {address}" in err and "--wait" in err and "streamed" not in out


def test_stream_wait_waits_for_a_service_started_later(tmp_path):
    """`stream --wait`: a camera started before the service says that it waits, then streams
    once the service is up."""
    from mnemoslam.service.demo import ServiceProcess

    svc = ServiceProcess(tmp_path / "map.db", service_config({"service": {"idle_timeout": 3600.0}}))
    proc = _cli("stream", "synthetic:loop", "--robot", "early", "--max-frames", "10", "--connect", svc.endpoint,
                "--wait", "-q", cwd=tmp_path)
    try:
        sel = selectors.DefaultSelector()
        sel.register(proc.stderr, selectors.EVENT_READ)
        line = proc.stderr.readline() if sel.select(timeout=30) else ""
        sel.close()
        assert line.startswith(f"stream: waiting for the service at {svc.endpoint} (nothing subscribes to "
                               f"mnemoslam/early/camera/frame yet)"), line
        time.sleep(6.0)  # longer than the wait without --wait
        assert proc.poll() is None
        svc.start()
        out, err = proc.communicate(timeout=120)
        assert proc.returncode == 0, out + err
        assert "streamed 10 frames" in out and "the service answered 10" in out
        assert svc.wait_processed("early", 10)["frames_processed"] == 10
    finally:
        proc.kill()
        svc.stop()


@pytest.mark.parametrize("argv, message", [
    (["--wait", "synthetic:loop"], "expected seconds, got 'synthetic:loop'"),
    (["synthetic:loop", "--wait", "-1"], "expected seconds >= 0"),
    (["synthetic:loop", "--max-rejected", "0"], "expected a share in (0, 1]"),
])
def test_stream_wait_and_max_rejected_arguments(capsys, argv, message):
    with pytest.raises(SystemExit) as e:
        main(["stream", *argv, "--max-frames", "1", "--connect", f"tcp/127.0.0.1:{free_port()}", "-q"])
    assert e.value.code == 2 and message in capsys.readouterr().err
