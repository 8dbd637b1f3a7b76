"""The `mnemoslam` command line."""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path


def _overrides(args, options: dict | None = None) -> dict:
    """The config overrides of a command: its --set items, then its dedicated options
    (--db, --port, --odometry-only, ...), which win over --set."""
    from .config import merge_overrides, parse_sets

    return merge_overrides(parse_sets(getattr(args, "set", None)), options or {})


def _cmd_run(args) -> int:
    from mnemoslam.client.cliargs import dataset_options, want_progress
    from mnemoslam.client.datasets import open_dataset

    from .config import load_config
    from .runner import run_dataset

    config = load_config(args.config, _overrides(args, {"loop": {"enabled": False}} if args.odometry_only else {}))
    from mnemoslam.client.datasets.subrange import frame_range

    dataset = frame_range(open_dataset(args.dataset, args.format, **dataset_options(args)), args.frames,
                          args.max_frames)
    if args.passes > 1:
        from mnemoslam.client.datasets.passes import Passes

        dataset = Passes(dataset, args.passes)
    if args.db:
        check_db_folder(args.db)
    out = run_dataset(dataset, config, args.out, progress=want_progress(args.quiet), db=args.db)
    print(out.summary.line())
    if out.summary.map_line():
        print(out.summary.map_line())
    g = getattr(out, "grid", None)
    if g:
        line = f"grid: {g['width']}x{g['height']} cells, {g['observed']} observed"
        if "groundtruth_agree" in g:
            line += (f", {100 * g['groundtruth_agree']:.1f} % agree with the scene's floor plan (occupied "
                     f"{100 * g['groundtruth_occupied_agree']:.1f} %, free {100 * g['groundtruth_free_agree']:.1f} %)")
        print(line)
    trajectory, which = out.trajectory, ""
    if getattr(out.summary, "localization", False):  # the poses in the map's frame (before: its own frame)
        from mnemoslam.client.kernel.trajectory import Trajectory

        since = out.summary.relocalized_stamp if out.summary.relocalized_stamp is not None else float("inf")
        sel = trajectory.stamps >= since - 1e-9
        trajectory, which = Trajectory(trajectory.stamps[sel], trajectory.poses[sel]), " in the map's frame"
    if dataset.ground_truth is not None and len(trajectory) >= 3:
        from .evaluation import evaluate

        try:
            r = evaluate(dataset.ground_truth, trajectory, align="se3")
            print(f"ATE RMSE {r.ate_rmse * 100:.2f} cm over {r.matched} poses{which} "
                  f"({r.ate_percent_of_path:.2f}% of {r.path_length:.2f} m)")
            if r.path_length >= 0.1:  # a metric sensor's scale error shows here (on a short path the scale is noise)
                s = evaluate(dataset.ground_truth, trajectory, align="sim3")
                print(f"ATE RMSE {s.ate_rmse * 100:.2f} cm aligned with scale (Sim(3)): the ground truth is "
                      f"{s.scale:.4f}x the trajectory's size")
        except ValueError as e:
            print(f"no ATE: {e}")
        if args.out and config.loop.enabled and config.memory.incremental:  # (localization: no links of its own)
            from .evaluation import evaluate_map_loops

            print(evaluate_map_loops(dataset.ground_truth, Path(args.db) if args.db else Path(args.out) / "map.db",
                                     config.loop.min_age, session_id=out.summary.session).format())
        if out.links is not None:
            print(out.links.format())
    return 0 if out.summary.tracked else 1


def _cmd_eval(args) -> int:
    from .evaluation import evaluate_files

    print(evaluate_files(args.groundtruth, args.estimate, args.align, args.max_dt, args.json))
    return 0


def _cmd_demo(args) -> int:
    from mnemoslam.client.cliargs import want_progress

    from .demo import run_demo

    return run_demo(args.trajectory, args.rate, not args.no_noise, args.out, progress=want_progress(args.quiet),
                    overrides=_overrides(args), **({"frames": args.frames} if args.frames else {}))


def check_db_folder(path: str | Path) -> Path:
    """The database's folder must exist: `serve` opens (or creates) the file but never
    creates folders, so a typo in --db / storage.path is an error, not a new empty map
    somewhere. ConfigError naming the folder otherwise."""
    from .config import ConfigError

    path = Path(path)
    folder = path.parent
    if not folder.is_dir():
        what = "is not a folder" if folder.exists() else "does not exist"
        raise ConfigError(f"database {path}: the folder {folder} {what} (create it first, or fix --db / storage.path)")
    return path


def _listen_socket(host: str, port: int):
    """The REST server's socket, bound here so that the address printed at start is the one
    listening (port 0: a free port) and a taken port is a one-line error."""
    import socket

    # IPPROTO_TCP explicitly: asyncio sets TCP_NODELAY only on connections accepted from a socket
    # whose proto says TCP (proto 0 does not); without it every response on a kept-alive
    # connection waits ~40 ms (uvicorn writes headers and body apart: Nagle + delayed ACK)
    sock = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM, socket.IPPROTO_TCP)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
    except OSError as e:
        sock.close()
        raise OSError(e.errno, f"REST API cannot listen on {host}:{port}: {e.strerror}") from None
    sock.set_inheritable(True)
    return sock


def serve_banner(config, rest_port: int | None) -> str:
    """The line `serve` prints at start: REST address, Zenoh endpoints, database."""
    z = config.zenoh
    if rest_port is None:
        rest = "REST off"
    else:
        host = config.api.host
        rest = f"REST http://{f'[{host}]' if ':' in host else host}:{rest_port}"
    ros = ""
    if config.ros.enabled:
        robots = ', '.join(str(r.get('robot')) for r in config.ros.robots if isinstance(r, dict))
        ros = f"ROS 2 robots {robots or 'none'}; "
    return (f"mnemoslam serve: {rest}; Zenoh {z.mode} listen {', '.join(z.listen) or 'none'}, "
            f"connect {', '.join(z.connect) or 'none'}, prefix {z.prefix}; {ros}"
            f"database {Path(config.storage.path).resolve()}"
            + (" (read-only: localization only, memory.incremental false)" if not config.memory.incremental else ""))


def _cmd_serve(args) -> int:
    import signal

    import uvicorn

    from .api import ApiServer, create_app
    from .config import load_config
    from .server import SlamService

    overrides: dict = {}  # the dedicated options win over --set
    if args.db:
        overrides.setdefault("storage", {})["path"] = args.db
    if args.listen:
        overrides.setdefault("zenoh", {})["listen"] = args.listen
    if args.port is not None:
        overrides.setdefault("api", {})["port"] = args.port
    config = load_config(args.config, _overrides(args, overrides))
    check_db_folder(config.storage.path)
    logging.getLogger("mnemoslam").setLevel(logging.INFO)
    stop: list[int] = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        # uvicorn re-raises the signal it shut down on, into this handler: we then flush
        # the database and exit 0 instead of dying by the signal.
        signal.signal(sig, lambda signum, _frame: stop.append(signum))
    service = SlamService(config).start()
    try:
        sock = _listen_socket(config.api.host, config.api.port) if config.api.enabled else None
        print(serve_banner(config, sock.getsockname()[1] if sock is not None else None), flush=True)
        if sock is not None:
            server = ApiServer(uvicorn.Config(create_app(service), host=config.api.host, port=config.api.port,
                                                   log_level="warning", access_log=False))
            server.run(sockets=[sock])  # returns on SIGINT / SIGTERM
        else:
            while not stop:
                signal.pause()
    finally:
        service.stop()
    return 0


def _cmd_db(args) -> int:
    from mnemoslam.storage.cli import db_export, db_info

    if args.db_command == "info":
        print(db_info(args.db))
    else:
        print(db_export(args.db, args.out, args.session))
        if not args.no_grid:  # the maps' occupancy grids and clouds (service/grid/files.py)
            from mnemoslam.storage import MapStore

            from .config import load_config
            from .grid.files import write_map_files

            with MapStore(args.db, create=False) as store:
                for m in write_map_files(store, args.out, load_config(args.config).grid).values():
                    print("\n".join(f"wrote {p}" for p in m["files"]))
    return 0


def default_yaml() -> str:
    from .config import default_yaml as text

    return text()


QUIET_HELP = "no progress bar (there is one only when stderr is a terminal)"


def _add_set(parser, whose: str = "") -> None:
    parser.add_argument("--set", action="append", metavar="KEY=VALUE",
                        help=f"override one config key {whose + ' ' if whose else ''}(dotted path, VALUE in YAML), "
                             "e.g. --set loop.enabled=false --set service.queue_size=30; repeatable; "
                             "`mnemoslam config` lists the keys")


def build_parser() -> argparse.ArgumentParser:
    from mnemoslam.client.cliargs import (
        DEPTH_REGISTRATION,
        DEPTH_REGISTRATION_HELP,
        FRAMES_HELP,
        TOPICS_HELP,
        frame_range_arg,
        positive_int,
    )
    from mnemoslam.client.datasets import FORMATS

    p = argparse.ArgumentParser(prog="mnemoslam", description="Long-term, memory-managed visual SLAM.")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = p.add_subparsers(dest="command", required=True)

    r = sub.add_parser("run", help="run a dataset offline through the SLAM pipeline")
    r.add_argument("dataset", help="dataset folder (TUM, EuRoC, KITTI, 7-Scenes), ROS bag (rosbag2 folder, .db3, "
                                   ".mcap, ROS 1 .bag) or synthetic[:loop|figure8|...]")
    r.add_argument("--out", required=True, help="output folder (trajectory.tum, keyframes.tum, summary.json, map.db "
                                                "unless --db, "
                                                "grid.pgm + grid.yaml, cloud.ply)")
    r.add_argument("--format", choices=list(FORMATS), help="override layout detection")
    r.add_argument("--topics", action="append", metavar="ROLE=TOPIC,...", help=TOPICS_HELP)
    r.add_argument("--depth-registration", choices=list(DEPTH_REGISTRATION), default="auto",
                   help=DEPTH_REGISTRATION_HELP)
    r.add_argument("--config", help="YAML config file (default: built-in defaults)")
    r.add_argument("--passes", type=positive_int, default=1, metavar="N",
                   help="play the sequence forward, backward, forward... N passes in all, stamps continuing at its "
                        "frame rate (long runs from any dataset; groundtruth.tum follows the same stamps)")
    r.add_argument("--max-frames", type=positive_int, metavar="N",
                   help="stop after this many frames (a positive integer; default: all)")
    r.add_argument("--frames", type=frame_range_arg, metavar="START:END", help=FRAMES_HELP)
    r.add_argument("--db", metavar="MAP.db",
                   help="add the run as a session to this map database (made when absent) instead of a new "
                        "DIR/map.db; its trajectories are in the map's frame once it joined the map")
    r.add_argument("--odometry-only", action="store_true", help="no loop closure (loop.enabled: false), the baseline")
    _add_set(r)
    r.add_argument("-q", "--quiet", action="store_true", help=QUIET_HELP)
    r.set_defaults(func=_cmd_run)

    d = sub.add_parser("demo", help="start the service, stream the synthetic scene into it over Zenoh, "
                                    "report ATE and a REST query")
    d.add_argument("--trajectory", default="loop",
                   help="synthetic camera path (loop, figure8, walk_a, walk_b, straight)")
    d.add_argument("--rate", type=float, default=15.0, help="frames per second of the synthetic camera")
    d.add_argument("--no-noise", action="store_true",
                   help="exact depth instead of Kinect-like noise (the path's own model where it has one: "
                        "fastrot's disparity noise)")
    d.add_argument("--out", default="out/demo", help="output folder, made when missing (default out/demo in the "
                                                    "current folder): the map database and the service's log")
    d.add_argument("--frames", type=positive_int, metavar="N",
                   help="stream only the path's first N frames (default: all of it, e.g. 901 for the loop at 15 Hz)")
    _add_set(d, "of the service the demo starts")
    d.add_argument("-q", "--quiet", action="store_true", help=QUIET_HELP)
    d.set_defaults(func=_cmd_demo)

    sv = sub.add_parser("serve", help="run the SLAM service: Zenoh ingest, SQLite map, REST API")
    sv.add_argument("--config", help="YAML config file (default: built-in defaults)")
    sv.add_argument("--db", help="SQLite database (overrides storage.path)")
    sv.add_argument("--listen", action="append",
                    help="Zenoh endpoint to listen on, e.g. tcp/127.0.0.1:7447 (repeatable)")
    sv.add_argument("--port", type=int, help="REST port (overrides api.port; 0 = a free port, printed at start)")
    _add_set(sv)
    sv.set_defaults(func=_cmd_serve)

    from mnemoslam.client.streamer import add_stream_arguments

    add_stream_arguments(sub.add_parser(
        "stream", help="stream a dataset, the synthetic scene or a camera to the service over Zenoh"))

    db = sub.add_parser("db", help="inspect or export a map database")
    dbs = db.add_subparsers(dest="db_command", required=True)
    di = dbs.add_parser("info", help="schema, sessions, counts, integrity")
    di.add_argument("db")
    dx = dbs.add_parser("export", help="trajectory (TUM), graph (JSON), each map's grid (PGM + YAML) and cloud (PLY)")
    dx.add_argument("db")
    dx.add_argument("--out", required=True, help="output folder")
    dx.add_argument("--session", type=int, help="only this session")
    dx.add_argument("--no-grid", action="store_true", help="no grid.pgm / grid.yaml / cloud.ply")
    dx.add_argument("--config", help="YAML config file for the grid.* keys (default: built-in defaults)")
    db.set_defaults(func=_cmd_db)

    cf = sub.add_parser("config", help="print every configuration key with its default")
    cf.set_defaults(func=lambda a: print(default_yaml(), end="") or 0)

    e = sub.add_parser("eval", help="ATE / RPE of an estimated trajectory against ground truth")
    e.add_argument("groundtruth", help="ground truth (TUM format, or KITTI poses)")
    e.add_argument("estimate", help="estimated trajectory (TUM format)")
    e.add_argument("--align", choices=["se3", "sim3", "none"], default="se3")
    e.add_argument("--max-dt", type=float, default=0.02, help="max timestamp difference for a match (s)")
    e.add_argument("--json", action="store_true", help="print JSON")
    e.set_defaults(func=_cmd_eval)
    return p


def main(argv: list[str] | None = None) -> int:
    from mnemoslam.client.kernel.frames import DatasetError
    from mnemoslam.storage import StoreError

    from .config import ConfigError

    owns_process = argv is None  # the console script or `python -m`: nothing of this process outlives main
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.WARNING,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        code = args.func(args)
    except (DatasetError, ConfigError, StoreError, ValueError, OSError) as e:
        print(f"mnemoslam {args.command}: error: {e}", file=sys.stderr)
        code = 2
    except KeyboardInterrupt:
        code = 130
    if owns_process and args.command == "serve" and code == 0:
        # a clean stop: everything the service owned is closed (SlamService.stop), so Python's finalization
        # is skipped (service/shutdown.py); a service that failed to start exits as usual (multiprocessing's
        # exit hook then ends a mapping child it may have spawned)
        from mnemoslam.client.transport import close_all_sessions

        from .shutdown import exit_process

        close_all_sessions()  # (what its exit hook would have done: none is left open)
        exit_process(code)
    return code


if __name__ == "__main__":
    sys.exit(main())
