import dataclasses
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


CHROMIUM = Path(os.environ.get("MNEMOSLAM_CHROMIUM", "/usr/bin/chromium"))


def require_chromium() -> Path:
    """The headless browser of the viewer's test (the Debian chromium package; `make test`
    installs it when apt-get can) with Playwright to drive it: skipped with the reason when
    either is missing, or failed when MNEMOSLAM_REQUIRE_DATA is set (as in CI)."""
    if not os.access(CHROMIUM, os.X_OK):
        _missing(f"no Chromium at {CHROMIUM} (apt-get install chromium, or set MNEMOSLAM_CHROMIUM)")
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError as e:
        _missing(f"playwright is not installed ({e}; pip install -e '.[test]')")
    return CHROMIUM


# ------------------------------------------------------------------------------------------
# Synthetic frames rendered once per test session

from client.synthetic import SyntheticDataset  # noqa: E402 (after the sys.path insert)

_RENDERED: dict = {}


class RenderedOnce(SyntheticDataset):
    """The synthetic dataset, each frame rendered once per test session (see `synthetic`); a
    test's own subclass (tests/test_semantics.py `_Recording`) shares the frames too."""

    def frame(self, i: int):
        key = (self.trajectory, self.path.duration, self.rate, self.camera, self.noise, self.exposure, self.seed,
               getattr(self.person, "walk", None), i)
        f = _RENDERED.get(key) if 0 <= i < len(self) else None
        if f is None:
            f = super().frame(i)  # IndexError out of range, as the dataset's own
            _RENDERED[key] = f
        return dataclasses.replace(f, image=f.image.copy(), depth=f.depth.copy(),
                                   extras={k: v.copy() for k, v in f.extras.items()})


def synthetic(trajectory: str, **options) -> SyntheticDataset:
    """`open_dataset(f"synthetic:{trajectory}", **options)`, but each frame is rendered once per
    test session and shared by every test that opens the same sequence (same path, duration,
    rate, camera, noise and seed: frame i is then the same frame, whatever `max_frames`).
    Rendering is deterministic by (seed, frame index), so the frames are those a fresh dataset
    renders; every `frame` call returns its own copy of the arrays, so a consumer that writes
    into a frame cannot change another test's input. Meant for the sequences several tests
    play (figure-8 at 10 Hz in 40 s: its 401 frames hold ~1.5 GB; the loop at 10 Hz, 601 frames
    with or without depth noise, ~2.2 GB each). A frame costs ~30 ms of CPU to render."""
    assert "scene" not in options, "the cache is keyed on the default scene of the seed"
    return RenderedOnce(trajectory=trajectory, **options)


# ------------------------------------------------------------------------------------------
# Runs several test modules read

LOOP_NOISY = dict(rate=10, noise=True)  # the synthetic loop (60 s) at 10 Hz with depth noise: 601 frames
# the figure-8 walked in 40 s at 10 Hz with depth noise (401 frames): its second lap revisits the
# first. Several modules play it; its frames are rendered once (`synthetic`).
FIGURE8 = dict(rate=10, noise=True, duration=40)


@pytest.fixture(scope="session")
def loop_run(tmp_path_factory):
    """The synthetic loop at 10 Hz with depth noise through the offline runner once per session,
    default configuration (loop closure on): `(dataset, RunOutput, config, out_dir)`.
    tests/test_loop_closure.py (loop closure) and tests/test_synthetic_run.py (tracking,
    outputs) check the same run instead of each playing the loop again. Read-only."""
    from service.config import load_config
    from service.runner import run_dataset

    out_dir = tmp_path_factory.mktemp("loop_run")
    ds = synthetic("loop", **LOOP_NOISY)  # the frames tests/test_semantics.py's run plays too
    cfg = load_config()
    return ds, run_dataset(ds, cfg, out_dir, progress=False), cfg, out_dir


@pytest.fixture(scope="session")
def figure8_run(tmp_path_factory):
    """FIGURE8 through the offline runner once per session, default configuration (loop
    closure on, the map update inline in this process): `(dataset, RunOutput, config, out_dir)`.
    tests/test_loop_closure.py checks its loops, tests/test_mapping_process.py compares the
    mapping process with it. Read-only."""
    from service.config import load_config
    from service.runner import run_dataset

    out_dir = tmp_path_factory.mktemp("figure8_run")
    ds = synthetic("figure8", **FIGURE8)
    cfg = load_config()
    return ds, run_dataset(ds, cfg, out_dir, progress=False), cfg, out_dir

