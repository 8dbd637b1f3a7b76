"""One installed namespace: `pip install` puts `mnemoslam.service`, `mnemoslam.client` and
`mnemoslam.storage` into site-packages (the folders stay at the top level, mapped by
pyproject.toml), never modules named `service`, `client` or `storage`; the shared kernel
(`mnemoslam.client.kernel`) imports nothing else of mnemoslam."""
import ast
import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TOP = {"service": "mnemoslam.service", "client": "mnemoslam.client", "storage": "mnemoslam.storage"}


def _pyproject() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]


def test_every_package_folder_is_listed_under_its_namespace():
    listed = set(_pyproject()["packages"])
    found = {".".join([TOP[init.relative_to(ROOT).parts[0]], *init.relative_to(ROOT).parts[1:-1]])
             for top in TOP for init in (ROOT / top).rglob("__init__.py")}
    assert found == listed, f"pyproject.toml packages: missing {found - listed}, stale {listed - found}"
    assert _pyproject()["package-dir"] == {name: folder for folder, name in TOP.items()}


def test_the_wheel_holds_only_the_mnemoslam_namespace(tmp_path):
    """The wheel `pip install .` would install: every module under mnemoslam/, the viewer's page
    beside its module, the `mnemoslam` command on mnemoslam.service.cli. Built from a copy of the
    sources, so no build/ folder of the checkout's can add to it."""
    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, src / name)
    for top in TOP:
        shutil.copytree(ROOT / top, src / top, ignore=shutil.ignore_patterns("__pycache__"))
    out = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(tmp_path), str(src)],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    (wheel,) = tmp_path.glob("mnemoslam-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/")[0] for n in names}
    assert {t for t in tops if not t.endswith(".dist-info")} == {"mnemoslam"}, tops
    assert "mnemoslam/service/cli.py" in names and "mnemoslam/client/kernel/frames.py" in names
    assert "mnemoslam/storage/store.py" in names and "mnemoslam/service/static/viewer.html" in names
    (entry,) = [n for n in names if n.endswith("entry_points.txt")]
    assert "mnemoslam = mnemoslam.service.cli:main" in zipfile.ZipFile(wheel).read(entry).decode()


def test_outside_the_checkout_only_the_namespace_imports(tmp_path):
    code = ("import importlib.util as u, mnemoslam.service.cli, mnemoslam.client.kernel.protocol, mnemoslam.storage\n"
            "print([n for n in ('service', 'client', 'storage') if u.find_spec(n) is not None])")
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "[]"


def test_the_kernel_imports_nothing_else_of_mnemoslam():
    for path in (ROOT / "client" / "kernel").glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.level:
                assert node.level == 1, f"{path.name} imports {'.' * node.level}{node.module} (outside the kernel)"
            elif isinstance(node, ast.ImportFrom | ast.Import):
                names = [node.module] if isinstance(node, ast.ImportFrom) else [a.name for a in node.names]
                assert not any(n.split(".")[0] in {"mnemoslam", *TOP} for n in names), f"{path.name} imports {names}"
