"""The `mnemoslam` command line: what it prints, its argument checks, progress bars."""
from __future__ import annotations

import io
import os
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

from service.cli import main

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
    """service.runner.run_dataset replaced by a recorder (no pipeline runs)."""
    calls = []

    def run_dataset(dataset, config, out_dir=None, progress=True):
        calls.append(SimpleNamespace(config=config, progress=progress))
        return SimpleNamespace(summary=SimpleNamespace(line=lambda: "fake run", tracked=1), trajectory=[])

    monkeypatch.setattr("service.runner.run_dataset", run_dataset)
    return calls


@pytest.fixture
def fake_demo(monkeypatch):
    calls = []

    def run_demo(trajectory="loop", rate=15.0, noise=True, out="out/demo", progress=True):
        calls.append(SimpleNamespace(progress=progress))
        return 0

    monkeypatch.setattr("service.demo.run_demo", run_demo)
    return calls


# -- run ------------------------------------------------------------------------------------

def test_run_prints_no_progress_when_stderr_is_not_a_terminal(tmp_path, capsys):
    assert main(["run", "synthetic:straight", "--out", str(tmp_path / "o"), "--max-frames", "12"]) == 0
    out, err = capsys.readouterr()
    assert "12 frames" in out
    assert err == ""  # no progress bar lines (captured stderr is not a terminal)
    # no loop on a straight path: said plainly, no nan, no vacuous 1.000 (0/0)
    assert "no loop links" in out and "no true revisits" in out and "nan" not in out and "0/0" not in out


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


# -- demo -----------------------------------------------------------------------------------

def test_demo_log_scan_reports_errors(tmp_path):
    from service.demo import log_errors, log_report

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
    assert main(["serve", "--db", str(tmp_path / "file" / "x.db")]) == 2
    assert "is not a folder" in capsys.readouterr().err


def _serve(tmp_path, *args) -> tuple[subprocess.Popen, str]:
    """`mnemoslam serve` in a child process and the first line it prints."""
    proc = subprocess.Popen([sys.executable, "-m", "service.cli", "serve", *args], cwd=ROOT, text=True,
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


def test_serve_prints_where_it_listens(tmp_path):
    db = tmp_path / "map.db"
    zenoh = f"tcp/127.0.0.1:{free_port()}"
    (tmp_path / "c.yaml").write_text("loop:\n  process: false\n")
    proc, line = _serve(tmp_path, "--db", str(db), "--listen", zenoh, "--port", "0", "--config", str(tmp_path / "c.yaml"))
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
    (tmp_path / "c.yaml").write_text("api:\n  enabled: false\nloop:\n  enabled: false\n")
    proc, line = _serve(tmp_path, "--db", str(tmp_path / "map.db"), "--listen", f"tcp/127.0.0.1:{free_port()}",
                        "--config", str(tmp_path / "c.yaml"))
    try:
        assert line.startswith("mnemoslam serve: REST off; Zenoh peer listen tcp/127.0.0.1:")
    finally:
        assert _stop(proc) == 0
