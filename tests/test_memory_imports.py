"""Memory is the map's store of nodes (RTAB-Map's Memory); the map update (`service.mapping`)
calls it, never the reverse: no module of `service/memory` imports `service.mapping`."""
import ast
from pathlib import Path

MEMORY = Path(service.memory.__file__).parent


def mapping_imports(source: str, package: str = "mnemoslam.service.memory") -> list[str]:
    """The modules of `service.mapping` that `source` (a module of `package`) imports."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = package.split(".")[:len(package.split(".")) - node.level + 1] if node.level else []
            module = ".".join(base + ([node.module] if node.module else []))
            names = [module] + [f"{module}.{a.name}" for a in node.names]
        else:
            continue
        found += [n for n in names if n == "mnemoslam.service.mapping" or n.startswith("mnemoslam.service.mapping.")]
    return found


def test_the_check_sees_every_form_of_import():
    assert mapping_imports("from ..mapping.graph import PoseGraph")
    assert mapping_imports("from .. import mapping")
    assert mapping_imports("import service.mapping.mapper")
    assert mapping_imports("def f():\n    from service.mapping import graph")
    assert not mapping_imports("from ..tracking.features import FrameFeatures\nfrom .views import DenseView")


def test_memory_imports_nothing_of_mapping():
    modules = sorted(MEMORY.glob("*.py"))
    assert len(modules) >= 5
    bad = {p.name: mapping_imports(p.read_text()) for p in modules}
    assert not {k: v for k, v in bad.items() if v}
