import copy
import dataclasses
import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


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


def service_config(overrides: dict | None = None) -> dict:
    """The config overrides of a service a test starts (`ServiceProcess`) with semantics off, for
    the tests about tracking, storage, admission or the API: with the model found, the default
    (`semantics.source: auto`) segments the keyframes of a camera that streams no labels (~0.4 s
    of CPU each, live and then the back-fill) beside what they assert. The semantic service
    tests (tests/test_semantic_*.py, test_api, test_viewer) and test_service's SIGKILL test (a kill
    while the worker writes) keep the default."""
    from mnemoslam.service.config import merge_overrides

    return merge_overrides({"semantics": {"enabled": False}}, overrides or {})


def slam_config(overrides: dict | None = None):
    """The default configuration (plus `overrides`) with semantics off (`service_config`'s
    overrides): the real-data SLAM tests check tracking and the map, and with the model found the
    default (`semantics.source: auto`) would segment each of their keyframes (~0.3 s) for nothing
    they assert."""
    from mnemoslam.service.config import load_config

    return load_config(overrides=service_config(overrides))


def run_cli(*argv) -> str:
    """`mnemoslam run ARGV` in this process with semantics and the occupancy grid off (the
    multi-session and localization tests check poses and links), its standard output; exit
    code 0 asserted."""
    import contextlib
    import io

    from mnemoslam.service.cli import main

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = main(["run", *argv, "-q", "--set", "semantics.enabled=false", "--set", "grid.enabled=false"])
    assert code == 0, buf.getvalue()
    return buf.getvalue()


def require(path: Path) -> Path:
    """A sequence inside the data folder, skipped (or failed in CI) when missing."""
    if not path.exists():
        _missing(f"sequence {path} is missing")
    return path


def require_model() -> Path:
    """The default segmentation model (`semantics.model` under MNEMOSLAM_MODELS, default
    ../shared/models) and onnxruntime: skipped when missing, failed in CI."""
    from mnemoslam.service.config import SemanticsConfig
    from mnemoslam.service.semantics.segmentation import model_path, model_reason

    why = model_reason(SemanticsConfig())
    if why is not None:
        _missing(why)
    return model_path(SemanticsConfig().model)


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

from mnemoslam.client.synthetic import SyntheticDataset  # noqa: E402 (beside the fixtures that use it)
from mnemoslam.client.synthetic.dataset import CACHE_ENV  # noqa: E402

# The synthetic frames rendered are kept on disk for the session (client/synthetic/dataset.py
# CACHE_ENV: a folder the first process, xdist's controller or the single one, makes and removes)
# and read back by every process that plays them again: both xdist workers and the service, CLI
# and streamer processes the tests start (they inherit the environment). The loop at 30 Hz, the
# figure-8 and the walks are played by many modules on both workers. A frame costs ~25 ms of
# CPU to render, ~2 ms to read back. The renderer's own tests (RENDERER_TESTS) render every frame.
RENDERER_TESTS = {"test_synthetic.py", "test_synthetic_person.py", "test_synthetic_fastrot.py"}
_FRAME_CACHE: list[str] = []  # the folder this process made


def pytest_configure(config):
    import tempfile

    if not hasattr(config, "workerinput") and not os.environ.get(CACHE_ENV):
        _FRAME_CACHE.append(tempfile.mkdtemp(prefix="mnemoslam-frames-"))
        os.environ[CACHE_ENV] = _FRAME_CACHE[0]


def pytest_unconfigure(config):
    import shutil

    for folder in _FRAME_CACHE:
        os.environ.pop(CACHE_ENV, None)
        shutil.rmtree(folder, ignore_errors=True)


@pytest.fixture(autouse=True)
def _renderer_tests_render(request, monkeypatch):
    """The renderer's tests (RENDERER_TESTS) see frames rendered, never read back."""
    if request.path.name in RENDERER_TESTS:
        monkeypatch.delenv(CACHE_ENV, raising=False)


_RENDERED: dict = {}


class RenderedOnce(SyntheticDataset):
    """The synthetic dataset, each frame rendered once per test session (see `synthetic`); a
    test's own subclass (tests/test_semantics.py `_Recording`) shares the frames too. With the
    session's frames kept on disk (CACHE_ENV, as `pytest_configure` sets it) they are read back
    from there, else held in this process."""

    def frame(self, i: int):
        if os.environ.get(CACHE_ENV):  # kept on disk, read back (a copy of its own): no memory held
            return super().frame(i)
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
# Tracking played once, replayed by the runs that vary only what follows it

_TRACKS: dict = {}  # (sequence, tracking config) -> (frames of the run that recorded it, records)


def sequence_key(dataset) -> tuple | None:
    """What frames a dataset plays, for `run_tracked_once`: the synthetic sequences rendered
    once (`synthetic`, keyed as their frames; `max_frames` aside: a shorter run plays the first
    frames of a longer one) and `Passes` over them; None for any other dataset."""
    from mnemoslam.client.datasets.passes import Passes

    if isinstance(dataset, RenderedOnce):
        return ("synthetic", dataset.trajectory, dataset.path.duration, dataset.rate, dataset.camera, dataset.noise,
                dataset.exposure, dataset.seed, getattr(dataset.person, "walk", None))
    if isinstance(dataset, Passes):
        inner = sequence_key(dataset.dataset)
        return None if inner is None else ("passes", inner, len(dataset.dataset), dataset.passes)
    return None


def _light(features):
    """A copy of a frame's features without its images (the extractor's `depth` and `grey` are
    the frame's own: `_ReplayedTracking` takes them from the frame it replays), and which of
    the two it had."""
    kept = copy.deepcopy(dataclasses.replace(features, depth=None, grey=None))
    return kept, (features.depth is not None, features.grey is not None)


class _RecordedTracking:
    """In place of a pipeline's extractor and odometry: runs them and keeps, per frame, a copy
    of the features (without the images) and of the odometry's result."""

    def __init__(self, pipeline, records: list):
        self.extractor, self.odometry, self.records = pipeline.extractor, pipeline.odometry, records

    @property
    def disparity_offset(self):
        return self.odometry.disparity_offset

    def extract(self, frame):
        self.features = self.extractor.extract(frame)
        return self.features

    def track(self, features, stamp, depth_stamp=None):
        tracked = self.odometry.track(features, stamp, depth_stamp)
        self.records.append((*_light(self.features), copy.deepcopy(tracked), stamp))
        return tracked


class _ReplayedTracking:
    """In place of a pipeline's extractor and odometry: the recorded features (with the
    frame's images, as the extractor gives them) and odometry results, in order; copies, so
    that what the map update does to them stays in its run."""

    disparity_offset = None  # (monocular / RGB-D sequences only: `sequence_key`)

    def __init__(self, records: list):
        self.records, self.next = records, 0

    def extract(self, frame):
        features, (depth, grey) = self.records[self.next][:2]
        return dataclasses.replace(copy.deepcopy(features), depth=frame.depth if depth else None,
                                   grey=frame.grey if grey else None)

    def track(self, features, stamp, depth_stamp=None):
        _, _, tracked, recorded = self.records[self.next]
        assert stamp == recorded, f"replayed tracking: frame {self.next} at {stamp}, recorded at {recorded}"
        self.next += 1
        return copy.deepcopy(tracked)


def _tracking_key(dataset, config, key: tuple | None = None) -> tuple | None:
    key = key if key is not None else sequence_key(dataset)
    if key is None:
        return None
    return key, repr((config.features, config.odometry, config.keyframe, config.stereo, config.seed))


def recorded_frames(dataset, config, key: tuple | None = None) -> int:
    """How many frames of `dataset`'s sequence have their tracking recorded with `config`'s
    tracking configuration (`run_tracked_once` replays it for runs of at most that many)."""
    done = _TRACKS.get(_tracking_key(dataset, config, key))
    return 0 if done is None else done[0]


def tracked_once(pipeline, dataset, config, key: tuple | None = None):
    """Have `pipeline` (built for `dataset` with `config`) replay the tracking a previous run
    of the same frames with the same tracking configuration recorded (`run_tracked_once`), or
    record its own for the runs after it. Returns a function to call once the run has played
    every frame of `dataset` (it keeps the record)."""
    key = _tracking_key(dataset, config, key)
    if key is None:
        return lambda: None
    done = _TRACKS.get(key)
    if done is not None and done[0] >= len(dataset):
        pipeline.extractor = pipeline.odometry = _ReplayedTracking(done[1])
        return lambda: None
    records: list = []
    pipeline.extractor = pipeline.odometry = _RecordedTracking(pipeline, records)

    def keep():
        if len(records) and (done is None or done[0] < len(dataset)):
            _TRACKS[key] = (len(dataset), records)
    return keep


def run_tracked_once(dataset, config, out_dir=None, key: tuple | None = None, **options):
    """`run_dataset(dataset, config, out_dir, **options)` whose tracking (feature extraction and
    odometry; the keyframe decisions follow from it) is played once per test session for the same frames and
    tracking configuration (`features`, `odometry`, `keyframe`, `stereo`, `seed`), and replayed
    by the runs after it: for runs that differ in the map update or semantics only, of the
    sequences `sequence_key` knows or under an explicit `key` (a real sequence: its path).
    Tracking never reads the map update, so the replayed frames are those it would track again
    (tests/test_sequences.py checks the identity, bit for bit; tests/test_loop_closure.py's
    `test_replayed_tracking_is_the_tracking` checks a replayed run against a fresh one); a
    test about tracking itself runs `run_dataset`."""
    from mnemoslam.service import runner

    build, keep = runner.build_pipeline, []

    def build_and_replay(store, robot, calibration, cfg, **kw):
        pipeline = build(store, robot, calibration, cfg, **kw)
        keep.append(tracked_once(pipeline, dataset, cfg, key))
        return pipeline

    runner.build_pipeline = build_and_replay
    try:
        out = runner.run_dataset(dataset, config, out_dir, **options)
    finally:
        runner.build_pipeline = build
    for k in keep:
        k()
    return out


# ------------------------------------------------------------------------------------------
# Runs several test modules read

# The session's runs with semantics and the occupancy grid off (`slam_config` turns semantics off):
# what their tests check is the map's links, poses and outputs, which neither changes (the same
# trajectory.tum and keyframes.tum, byte for byte, on the noisy figure-8 and the noise-free loop),
# and they cost a third of a run's wall time (the figure-8: 40.3 -> 25.8 s). The grids are
# tests/test_grid*.py's, the objects tests/test_semantics.py's.
LEAN = {"grid": {"enabled": False}}
LOOP_NOISY = dict(rate=10, noise=True)  # the synthetic loop (60 s) at 10 Hz with depth noise: 601 frames
# the figure-8 walked in 40 s at 10 Hz with depth noise (401 frames): its second lap revisits the
# first. Several modules play it; its frames are rendered once (`synthetic`).
FIGURE8 = dict(rate=10, noise=True, duration=40)


@pytest.fixture(scope="session")
def loop_run(tmp_path_factory):
    """The synthetic loop at 10 Hz with depth noise through the offline runner once per session,
    default configuration (loop closure on) with semantics and the occupancy grid off (`LEAN`):
    `(dataset, RunOutput, config, out_dir)`. tests/test_loop_closure.py (loop closure) and
    tests/test_synthetic_run.py (tracking, outputs) check the same run instead of each playing
    the loop again; its tracking is recorded (`run_tracked_once`) for tests/test_semantics.py's
    run of the same frames. Read-only."""
    out_dir = tmp_path_factory.mktemp("loop_run")
    ds = synthetic("loop", **LOOP_NOISY)  # the frames tests/test_semantics.py's run plays too
    cfg = slam_config(LEAN)
    return ds, run_tracked_once(ds, cfg, out_dir, progress=False), cfg, out_dir


@pytest.fixture(scope="session")
def figure8_run(tmp_path_factory):
    """FIGURE8 through the offline runner once per session, default configuration (loop
    closure on, the map update inline in this process) with semantics and the occupancy grid off
    (`LEAN`): `(dataset, RunOutput, config, out_dir)`.
    tests/test_loop_closure.py checks its loops, tests/test_mapping_process.py compares the
    mapping process with it. Its tracking is recorded (`run_tracked_once`) for the other runs
    of these frames that vary the map update (link refinement off, the mapping process, a
    bounded working memory). Read-only."""
    out_dir = tmp_path_factory.mktemp("figure8_run")
    ds = synthetic("figure8", **FIGURE8)
    cfg = slam_config(LEAN)
    return ds, run_tracked_once(ds, cfg, out_dir, progress=False), cfg, out_dir


WALK_A = dict(rate=10, noise=True, duration=12, width=320, height=240)  # walk_a's frames, rendered once
WALK_A_PASSES = 3


def walk_a_passes(cfg, out_dir) -> dict:
    """walk_a there, back and there again (`WALK_A_PASSES`) through the offline runner with
    `cfg`, its tracking recorded once for the session (`run_tracked_once`): `{"ds", "out",
    "dir", "cfg", "rows" (updates.csv), "pass1" (the first pass's rows)}`."""
    import csv

    from mnemoslam.client.datasets.passes import Passes

    base = synthetic("walk_a", **WALK_A)  # tests/test_startup.py plays the same frames
    ds = Passes(base, WALK_A_PASSES)
    out = run_tracked_once(ds, cfg, out_dir, progress=False)
    rows = list(csv.DictReader(open(out_dir / "updates.csv")))
    first_pass_end = ds.stamps[len(base) - 1]
    return {"ds": ds, "out": out, "dir": out_dir, "cfg": cfg, "rows": rows,
            "pass1": [r for r in rows if float(r["stamp"]) <= first_pass_end]}


@pytest.fixture(scope="session")
def walked(tmp_path_factory):
    """`walk_a_passes` with rehearsal on (the default) and an unbounded working memory,
    semantics and the occupancy grid off. tests/test_rehearsal.py checks its merges,
    tests/test_memory_revisits.py compares a bounded working memory with it. Read-only."""
    return walk_a_passes(slam_config({"memory": {"rehearsal": True}, **LEAN}), tmp_path_factory.mktemp("rehearsal"))


# ------------------------------------------------------------------------------------------
# Tiers: `make test` runs every test; `make check` (`pytest -m "not slow"`) is the fast tier for
# the edit loop. Slow are the tests marked `@pytest.mark.slow` in their module and those named
# here (kept in one place so that the modules need no edit): what plays a sequence through the
# pipeline or the CLI (the rosbag players' runs on 7-Scenes frames, a run's files), streams a long
# one through the service, paces frames in real time, checks a figure at scale (100k objects),
# builds the wheel, or drives the viewer's browser (so `make check` needs no Chromium). A
# module's name with "*" marks every test in it. `make check`'s wall time is in the closing note
# of the change that last moved it (issue 27: 90 s on the 2 cores).
SLOW: dict[str, str | set[str]] = {
    "test_loop_closure.py": "*", "test_synthetic_run.py": "*", "test_mapping_process.py": "*",
    "test_recovery.py": "*", "test_semantic_service.py": "*", "test_semantic_robots.py": "*",
    "test_memory_crash.py": "*", "test_rehearsal.py": "*", "test_startup.py": "*", "test_semantic_dynamic.py": "*",
    "test_multisession.py": "*", "test_semantic_model_service.py": "*", "test_memory_revisits.py": "*",
    "test_packaging.py": {"test_the_wheel_holds_only_the_mnemoslam_namespace"},
    "test_storage.py": {"test_object_arrays_at_100k_objects"},
    "test_grid_api.py": {"test_viewer_draws_the_grid_in_chromium"},
    "test_grid.py": {"test_run_out_writes_grid_cloud_and_groundtruth"},
    "test_sequences.py": {"test_cli_run_with_corrupt_image_names_file_and_goes_on",
                          "test_7scenes_redkitchen_no_frame_lost_and_revisits_closed",
                          "test_tum_fr1_desk_loops_help_and_link_refinement_never_hurts",
                          "test_tum_cabinet_keyframes_all_tracked", "test_tum_cabinet_loop_back_to_the_start_is_closed",
                          "test_kitti_stereo", "test_euroc_stereo_still_vehicle",
                          "test_same_input_same_trajectory_bit_for_bit"},
    "test_semantics.py": {"test_a_saturated_robot_still_gets_live_keyframes_after_max_wait",
                          "test_doors_seen_are_door_objects_at_their_place",
                          "test_objects_persist_and_survive_their_anchor_moving_to_ltm",
                          "test_an_object_moves_with_its_anchor_when_poses_are_corrected",
                          "test_labels_survive_30_percent_corrupted_frames",
                          "test_real_model_on_redkitchen_finds_table_and_cabinet",
                          "test_service_fuses_streamed_labels_into_stored_objects",
                          "test_keyframes_the_worker_could_not_take_are_backfilled",
                          "test_deferred_camera_labels_wait_for_the_backfill"},
    "test_service.py": {"test_loop_closed_and_map_corrected_events_are_published",
                        "test_sigkill_mid_stream_keeps_every_reported_keyframe",
                        "test_three_robots_three_sessions_no_cross_talk",
                        "test_camera_restart_ends_the_session_and_the_same_sequence_maps_again",
                        "test_streamed_run_matches_offline_run_and_every_keyframe_is_stored",
                        "test_malformed_flood_is_counted_and_valid_robot_unaffected",
                        "test_config_hides_the_environment_token_and_no_lock_file_stays"},
    "test_viewer.py": {"test_viewer_shows_the_stream_live_in_chromium", "test_viewer_pans_and_zooms_in_chromium"},
    "test_working_memory.py": {"test_a_bounded_working_memory_retrieves_old_nodes_and_closes_loops_to_them"},
    "test_detection_models.py": {"test_a_perfect_detector_on_the_synthetic_scene_finds_the_doors"},
    "test_synthetic_fastrot.py": {"test_fastrot_tracked_without_loss",
                                  "test_kinect_depth_noise_grows_with_z_squared_in_disparity_steps"},
    "test_streamer.py": {"test_stream_skips_unreadable_frames_like_run", "test_stream_synthetic_loop",
                         "test_capture_source_streams_over_zenoh",
                         "test_stream_synthetic_labels"},
    "test_api.py": {"test_openapi_fuzz_finds_no_server_error"},
    "test_cli.py": {"test_stream_wait_waits_for_a_service_started_later", "test_demo_runs_from_an_empty_folder",
                    "test_stream_to_an_address_where_nothing_listens_fails_fast"},
    "test_vocabulary.py": {"test_offline_run_leaves_the_live_vocabulary_in_map_db"},
    "test_admission.py": {"test_slots_are_bounded_and_idle_ones_expire",
                          "test_frames_of_unknown_robots_take_no_slot_and_a_camera_then_maps_normally",
                          "test_the_camera_sees_the_services_drops_and_flow_control_avoids_them"},
    "test_local_ba.py": {"test_the_database_holds_the_links_local_ba_refined",
                         "test_map_update_runs_local_ba_on_a_synthetic_run"},
    "test_stereo_odometry.py": {"test_disparity_offset_estimated_online", "test_kitti_every_frame_tracked"},
    "test_loop_detection.py": {"test_revisit_accepted_and_no_false_accepts"},
    "test_ros2.py": {"test_ros_robots_map_exactly_as_the_native_robot"},
    "test_grid_real.py": {"test_desk_grid_up_is_the_accelerometers_and_agrees_with_the_floor"},
    "test_depth_time.py": {"test_streamed_tum_frames_bring_their_depth_stamp_and_accelerometer",
                           "test_tum_fr1_desk_fast_turn_odometry"},
    "test_rosbag.py": {"test_bag_frames_are_the_folder_frames", "test_run_cli_on_rosbag2_sqlite3_gives_the_folder_ate",
                       "test_run_on_mcap_and_ros1_bags_gives_the_folder_ate",
                       "test_stream_bag_through_the_service_maps_like_the_folder_run",
                       "test_fr1_desk_as_a_bag_with_its_distortion_tracks_as_the_folder"},
}


def _check_slow_names():
    """Each name in SLOW is a module of tests/ with that test function (a renamed test would
    otherwise fall into the fast tier unnoticed)."""
    here = Path(__file__).parent
    for module, names in SLOW.items():
        path = here / module
        if not path.is_file():
            raise pytest.UsageError(f"tests/conftest.py SLOW names {module}, which does not exist")
        text = path.read_text()
        for name in sorted(names) if names != "*" else ():
            if f"def {name}(" not in text:
                raise pytest.UsageError(f"tests/conftest.py SLOW names {module}::{name}, which does not exist")


# With pytest-xdist's workers (`make test`: `-n 2 --dist loadfile`) each module runs on one worker,
# so that its module-scoped fixtures run once, and the modules of a group in XDIST_GROUPS share a
# worker: they check the same session-scoped runs (`loop_run`, `figure8_run`), replay the
# tracking those runs recorded (`run_tracked_once`) or play the same frames rendered once
# (`synthetic`), which a second worker would compute again ("walk-a": the walk_a frames played
# three times, tracked once for test_rehearsal and test_memory_revisits, rendered once for
# test_startup too). The groups and modules in XDIST_FIRST start first, longest first
# (measured: fresh-clone CI's --durations and each module's --durations=0), so that no long one
# is left for the end while the other worker idles; the rest follow in collection order. The
# scheduler hands a worker its next unit when its current one has 2 tests left, in this order.
XDIST_GROUPS = {
    "test_loop_closure.py": "shared-runs", "test_synthetic_run.py": "shared-runs",
    "test_mapping_process.py": "shared-runs", "test_semantics.py": "shared-runs",
    "test_working_memory.py": "shared-runs",
    "test_rehearsal.py": "walk-a", "test_memory_revisits.py": "walk-a", "test_startup.py": "walk-a",
}
# Long tests of a grouped module that share none of its runs or frames' tracking (each plays a
# sequence no other test of the group plays): a unit of their own (`module::test`), which either
# worker takes, instead of lengthening the group's worker by their time.
XDIST_ALONE = {"test_synthetic_run.py::test_synthetic_loop_noise_free",
               "test_loop_closure.py::test_repeated_texture_walk_makes_no_false_link"}
XDIST_FIRST = ["shared-runs", "test_sequences.py", "test_recovery.py", "test_multisession.py", "test_service.py",
               "walk-a", "test_semantic_service.py", "test_viewer.py", "test_api.py",
               "test_synthetic_run.py::test_synthetic_loop_noise_free", "test_semantic_model_service.py",
               "test_loop_closure.py::test_repeated_texture_walk_makes_no_false_link", "test_memory_crash.py",
               "test_cli.py"]


def _check_xdist_names():
    """Each module and test the xdist units name exists (a renamed one would otherwise fall back
    to its module's unit unnoticed)."""
    here = Path(__file__).parent
    units = set(XDIST_GROUPS.values())
    for name in [*XDIST_GROUPS, *XDIST_ALONE, *(n for n in XDIST_FIRST if n not in units)]:
        module, _, test = name.partition("::")
        path = here / module
        if not path.is_file() or (test and f"def {test}(" not in path.read_text()):
            raise pytest.UsageError(f"tests/conftest.py's xdist units name {name}, which does not exist")


def _xdist_group(module: str, test: str = "") -> str:
    """The unit of work of a test (its module's name, `test` its function's name): its group
    in XDIST_GROUPS, itself when XDIST_ALONE names it, else its module."""
    alone = f"{module}::{test}"
    return alone if alone in XDIST_ALONE else XDIST_GROUPS.get(module, module)


def _nodeid_group(nodeid: str) -> str:
    path, _, rest = nodeid.partition("::")
    return _xdist_group(Path(path).name, rest.split("[", 1)[0])


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
    """`--dist loadfile` with the modules of an XDIST_GROUPS group as one file (and the tests
    XDIST_ALONE names as units of their own)."""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class _ByGroup(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return _nodeid_group(nodeid)

    config.option.loadscopereorder = False  # the collection's order: XDIST_FIRST first
    return _ByGroup(config, log)


def pytest_collection_modifyitems(config, items):
    _check_slow_names()
    _check_xdist_names()
    for item in items:
        names = SLOW.get(item.path.name)
        if names == "*" or (names and getattr(item, "originalname", item.name) in names):
            item.add_marker(pytest.mark.slow)
    if hasattr(config, "workerinput"):  # an xdist worker: the long groups first (a stable sort)
        rank = {g: i for i, g in enumerate(XDIST_FIRST)}
        items.sort(key=lambda item: rank.get(_nodeid_group(item.nodeid), len(rank)))
