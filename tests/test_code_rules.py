"""Rules of the code's layout (issue 27), checked on the source so that they cannot regress:

- the map's file is opened by `storage/` only: nothing else imports sqlite3 (or sqlite_utils);
- no private name (`_x`) of a project module is used by another module: what one module
  needs of another is public (storage's encodings are `storage.codec`'s public functions).

Related rules tested elsewhere: `service/memory` imports nothing of `service/mapping`
(tests/test_memory_imports.py); the map update reaches the store through memory only, and
each caller of the store calls only the methods of its role (tests/test_storage.py).
"""
import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FIRST_PARTY = ("service", "client", "storage", "bench")
# bench/bench_startup.py builds its 100,000-node fixture map with batched raw inserts (hours
# through the store's one transaction per keyframe); it measures the store on the result.
RAW_SQLITE_ALLOWED = {"bench/bench_startup.py"}


def sqlite_imports(source: str) -> list[int]:
    """Lines of `source` that import sqlite3 or sqlite_utils (any form, anywhere)."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and not node.level:
            names = [node.module or ""]
        else:
            continue
        if any(n.split(".")[0] in ("sqlite3", "sqlite_utils") for n in names):
            found.append(node.lineno)
    return found


def private_uses(source: str) -> list[str]:
    """Private names of project modules that `source` uses: `from x import _y`, and `m._y`
    where `m` was imported from the project (relative or service / client / storage / bench)."""
    tree = ast.parse(source)
    found, modules = [], set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.split(".")[0] in FIRST_PARTY:
                    modules.add(a.asname or a.name.split(".")[0])
        elif isinstance(node, ast.ImportFrom) and (node.level or (node.module or "").split(".")[0] in FIRST_PARTY):
            for a in node.names:
                if a.name.startswith("_") and not a.name.startswith("__"):
                    found.append(f"{node.lineno}: from {'.' * node.level}{node.module or ''} import {a.name}")
                modules.add(a.asname or a.name)
    for node in ast.walk(tree):
        if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in modules
                and node.attr.startswith("_") and not node.attr.endswith("__")):
            found.append(f"{node.lineno}: {node.value.id}.{node.attr}")
    return found


def _sources(*folders: str) -> list[Path]:
    return sorted(p for f in folders for p in (ROOT / f).rglob("*.py"))


def test_the_checks_see_every_form():
    assert sqlite_imports("import sqlite3") == [1]
    assert sqlite_imports("import os\ndef f():\n    import sqlite3 as db") == [3]
    assert sqlite_imports("from sqlite3 import connect") == [1]
    assert sqlite_imports("from sqlite_utils.db import ForeignKey") == [1]
    assert not sqlite_imports("from storage import MapStore\nimport rosbags  # sqlite3 bags")
    assert private_uses("from .records import _pack") and private_uses("from storage.codec import _x")
    assert private_uses("from service import runner\nrunner._frames()")
    assert private_uses("import service.runner as r\nr._frames()")
    assert not private_uses("import os\nos._exit(0)")  # (the standard library's are its own business)
    assert not private_uses("from .records import LinkType\nclass A:\n    def f(self):\n        self._x = LinkType")
    assert not private_uses("from storage import MapStore\nMapStore.__doc__")


def test_only_storage_opens_the_map_file():
    sources = _sources("service", "client", "bench")
    assert len(sources) > 50
    bad = {str(p.relative_to(ROOT)): lines for p in sources if (lines := sqlite_imports(p.read_text()))}
    assert set(bad) == RAW_SQLITE_ALLOWED, bad
    assert sqlite_imports((ROOT / "storage" / "connection.py").read_text())  # (where it is opened)


def test_no_private_name_crosses_a_module():
    sources = _sources(*FIRST_PARTY)
    bad = {str(p.relative_to(ROOT)): found for p in sources if (found := private_uses(p.read_text()))}
    assert not bad
