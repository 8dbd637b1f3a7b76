"""The `mnemoslam` command line: what it prints, its argument checks."""
from __future__ import annotations

import os
import selectors
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

from service.cli import main

ROOT = Path(__file__).resolve().parents[1]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


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
