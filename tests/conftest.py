import os
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _data_root() -> Path:
    return Path(os.environ.get("MNEMOSLAM_DATA", ROOT.parent / "shared" / "data")).resolve()


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """The real sequences (MNEMOSLAM_DATA, default ../shared/data). Tests using it skip with a
    reason when it is absent, or fail when MNEMOSLAM_REQUIRE_DATA is set (as in CI)."""
    root = _data_root()
    if not root.is_dir():
        _missing(f"real data not found at {root} (set MNEMOSLAM_DATA)")
    return root


def require(path: Path) -> Path:
    """A sequence inside the data folder, skipped (or failed in CI) when missing."""
    if not path.exists():
        _missing(f"sequence {path} is missing")
    return path


def _missing(msg: str):
    if os.environ.get("MNEMOSLAM_REQUIRE_DATA"):
        pytest.fail(msg + " and MNEMOSLAM_REQUIRE_DATA is set")
    pytest.skip(msg)
