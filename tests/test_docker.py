"""docker/: the service image and the compose file (service, Zenoh router, demo camera).

Images are not built here (that needs a Docker daemon and the network); the files are checked
for what they promise instead: the compose file validates with `docker compose config` where
the tool exists, its services run commands our CLI accepts with a configuration that loads,
and the Dockerfile installs with the README's set-up (the Makefile's `venv` recipe)."""
from __future__ import annotations

import re
import shlex
import shutil
import subprocess
import tomllib
from importlib.metadata import version
from pathlib import Path

import pytest
import yaml

from mnemoslam.service.cli import build_parser
from mnemoslam.service.config import load_config, merge_overrides, parse_sets

ROOT = Path(__file__).resolve().parents[1]
DOCKER = ROOT / "docker"
COMPOSE = DOCKER / "compose.yaml"
DOCKERFILE = DOCKER / "Dockerfile"
ROUTER = "tcp/zenoh-router:7447"


@pytest.fixture(scope="module")
def compose() -> dict:
    return yaml.safe_load(COMPOSE.read_text())


def _instructions(path: Path) -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) of a Dockerfile, continuation lines joined, comments dropped."""
    text = re.sub(r"\\\n", " ",
                  "\n".join(ln for ln in path.read_text().splitlines() if not ln.lstrip().startswith("#")))
    out = []
    for line in text.splitlines():
        if line.strip():
            word, _, rest = line.strip().partition(" ")
            out.append((word.upper(), rest.strip()))
    return out


def _exec_form(args: str) -> list[str]:
    return yaml.safe_load(args)  # a JSON array


def _serve_config(argv: list[str]):
    """The configuration `mnemoslam serve argv` runs with (as service/cli.py builds it)."""
    args = build_parser().parse_args(argv)
    assert args.command == "serve"
    options: dict = {}
    if args.db:
        options.setdefault("storage", {})["path"] = args.db
    if args.listen:
        options.setdefault("zenoh", {})["listen"] = args.listen
    return load_config(args.config, merge_overrides(parse_sets(args.set), options))


def test_compose_has_the_service_the_router_and_a_camera(compose):
    services = compose["services"]
    assert set(services) == {"mnemoslam", "zenoh-router", "camera"}
    svc, router, camera = services["mnemoslam"], services["zenoh-router"], services["camera"]
    # the router: zenohd of the Zenoh release the service and cameras are pinned to
    image, tag = router["image"].rsplit(":", 1)
    assert image == "eclipse/zenoh" and tag == version("eclipse-zenoh")
    assert "tcp/0.0.0.0:7447" in router["command"]
    # service and camera: the image of docker/Dockerfile
    for s in (svc, camera):
        assert (COMPOSE.parent / s["build"]["context"] / s["build"]["dockerfile"]).resolve() == DOCKERFILE
        assert s["image"] == svc["image"]
    # volumes: maps (named) at /data, models read-only where MNEMOSLAM_MODELS points
    volumes = svc["volumes"]
    assert "maps:/data" in volumes and "maps" in compose["volumes"]
    models = [v for v in volumes if v.split(":")[-2:] == ["/models", "ro"]]
    assert len(models) == 1 and svc["environment"]["MNEMOSLAM_MODELS"] == "/models"
    # health: /health over HTTP, from the container itself; the camera waits for it
    test = svc["healthcheck"]["test"]
    assert test[0] == "CMD" and "http://127.0.0.1:8080/health" in " ".join(test)
    assert camera["healthcheck"] == {"disable": True}  # the image's check is the service's
    assert camera["depends_on"]["mnemoslam"]["condition"] == "service_healthy"
    assert svc["stop_grace_period"]  # SIGTERM finishes the map update's backlog


def test_compose_commands_are_ones_the_cli_takes(compose):
    svc, camera = compose["services"]["mnemoslam"], compose["services"]["camera"]
    config = _serve_config(svc["command"])
    assert config.api.host == "0.0.0.0" and config.api.port == 8080
    assert config.zenoh.connect == [ROUTER] and "tcp/0.0.0.0:7447" in config.zenoh.listen
    assert config.storage.path.startswith("/data/")
    assert any(p.endswith(":8080") for p in svc["ports"])
    args = build_parser().parse_args(camera["command"])
    assert args.command == "stream" and args.dataset.startswith("synthetic")
    assert args.connect == [ROUTER] and args.labels
    assert config.semantics.enabled and config.semantics.source == "camera"  # it uses the camera's labels


def test_dockerfile_installs_with_the_readme_commands():
    steps = _instructions(DOCKERFILE)
    kinds = [k for k, _ in steps]
    runs = [a for k, a in steps if k == "RUN"]
    # the install is the Makefile's `venv` recipe, the one `make demo` / `make test` run first
    assert "make venv" in runs
    make = (ROOT / "Makefile").read_text()
    assert re.search(r"^venv: \$\(STAMP\)$", make, re.M)
    recipe = re.search(r"^\$\(STAMP\): pyproject.toml\n((?:\t.*\n)+)", make, re.M).group(1)
    assert "-m venv $(VENV)" in recipe and "pip install -q -e '.[test]'" in recipe
    readme = (ROOT / "README.md").read_text()
    assert "make demo" in readme and "make test" in readme and "docker compose -f docker/compose.yaml" in readme
    # the Python pyproject.toml asks for
    base = next(a for k, a in steps if k == "FROM")
    requires = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["requires-python"]
    minor = re.search(r">=\s*(3\.\d+)", requires).group(1)
    assert base.startswith(f"python:{minor}-")
    # the code is copied before the install, which runs as the non-root user that runs the service
    user, last_run = kinds.index("USER"), len(kinds) - 1 - kinds[::-1].index("RUN")
    assert steps[last_run][1] == "make venv" and kinds.index("COPY") < user < last_run
    assert steps[user][1] not in ("root", "0") and kinds.count("USER") == 1
    assert "ENV" in kinds and "/app/.venv/bin" in " ".join(a for k, a in steps if k == "ENV")
    # health on /health without curl; the default command serves on every interface
    check = next(a for k, a in steps if k == "HEALTHCHECK")
    assert "urllib.request" in check and "127.0.0.1:8080/health" in check
    assert _exec_form(next(a for k, a in steps if k == "ENTRYPOINT")) == ["mnemoslam"]
    config = _serve_config(_exec_form(next(a for k, a in steps if k == "CMD")))
    assert config.api.host == "0.0.0.0" and config.storage.path.startswith("/data/")
    # a .venv or .git of the build's checkout never reaches the image (make venv creates it)
    ignored = (ROOT / ".dockerignore").read_text().split()
    assert ".venv" in ignored and ".git" in ignored


def _compose_plugin() -> str | None:
    docker = shutil.which("docker")
    if docker is None:
        return None
    try:
        ok = subprocess.run([docker, "compose", "version"], capture_output=True, timeout=30).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        return None
    return docker if ok else None


def test_docker_compose_config_validates():
    docker = _compose_plugin()
    if docker is None:
        pytest.skip("the docker compose plugin is not installed here (`docker compose version` fails); "
                    "the compose file is checked by the tests above")
    r = subprocess.run([docker, "compose", "-f", str(COMPOSE), "config", "--quiet"], capture_output=True, text=True,
                       timeout=60, cwd=ROOT)
    assert r.returncode == 0, f"{shlex.join(r.args)}: {r.stderr}"
