"""The `mnemoslam` command line."""
from __future__ import annotations

import argparse
import logging
import sys


def _cmd_run(args) -> int:
    from client.datasets import open_dataset

    from .config import load_config
    from .runner import run_dataset

    overrides = {}
    config = load_config(args.config, overrides)
    options = {"max_frames": args.max_frames} if args.max_frames else {}
    dataset = open_dataset(args.dataset, args.format, **options)
    out = run_dataset(dataset, config, args.out, progress=not args.quiet)
    print(out.summary.line())
    if dataset.ground_truth is not None and len(out.trajectory) >= 3:
        from .evaluation import evaluate

        try:
            r = evaluate(dataset.ground_truth, out.trajectory, align="se3")
            print(f"ATE RMSE {r.ate_rmse * 100:.2f} cm over {r.matched} poses "
                  f"({r.ate_percent_of_path:.2f}% of {r.path_length:.2f} m)")
        except ValueError as e:
            print(f"no ATE: {e}")
    return 0 if out.summary.tracked else 1


def _cmd_eval(args) -> int:
    from .evaluation import evaluate_files

    print(evaluate_files(args.groundtruth, args.estimate, args.align, args.max_dt, args.json))
    return 0


def _cmd_demo(args) -> int:
    """The embedded default: the synthetic loop through the pipeline, scored against its
    exact ground truth. (Streams over Zenoh into the service once issue #3 lands.)"""
    from client.datasets import open_dataset

    from .config import load_config
    from .evaluation import evaluate
    from .runner import run_dataset

    dataset = open_dataset(f"synthetic:{args.trajectory}", rate=args.rate, noise=not args.no_noise)
    print(f"demo: {dataset.name}, {len(dataset)} frames at {args.rate:g} Hz "
          f"({'Kinect-like depth noise' if not args.no_noise else 'noise-free'})")
    out = run_dataset(dataset, load_config(args.config), args.out, progress=not args.quiet)
    print(out.summary.line())
    r = evaluate(dataset.ground_truth, out.trajectory)
    print(f"ATE RMSE {r.ate_rmse * 100:.2f} cm over {r.matched} poses, {r.path_length:.1f} m path; "
          f"trajectory in {args.out}/trajectory.tum")
    return 0 if out.summary.lost == 0 else 1


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="mnemoslam", description="Long-term, memory-managed visual SLAM.")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = p.add_subparsers(dest="command", required=True)

    r = sub.add_parser("run", help="run a dataset offline through the SLAM pipeline")
    r.add_argument("dataset", help="dataset folder (TUM, EuRoC, KITTI, 7-Scenes) or synthetic[:loop|figure8|...]")
    r.add_argument("--out", required=True, help="output folder (trajectory.tum, keyframes.tum, summary.json)")
    r.add_argument("--format", choices=["tum", "euroc", "kitti", "7scenes", "synthetic"], help="override layout detection")
    r.add_argument("--config", help="YAML config file (default: built-in defaults)")
    r.add_argument("--max-frames", type=int, help="stop after this many frames")
    r.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    r.set_defaults(func=_cmd_run)

    d = sub.add_parser("demo", help="run the embedded synthetic scene and report its accuracy")
    d.add_argument("--trajectory", default="loop", help="synthetic camera path (loop, figure8, walk_a, walk_b, straight)")
    d.add_argument("--rate", type=float, default=15.0, help="frames per second of the synthetic camera")
    d.add_argument("--no-noise", action="store_true", help="exact depth instead of Kinect-like noise")
    d.add_argument("--out", default="out/demo", help="output folder")
    d.add_argument("--config", help="YAML config file")
    d.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    d.set_defaults(func=_cmd_demo)

    e = sub.add_parser("eval", help="ATE / RPE of an estimated trajectory against ground truth")
    e.add_argument("groundtruth", help="ground truth (TUM format, or KITTI poses)")
    e.add_argument("estimate", help="estimated trajectory (TUM format)")
    e.add_argument("--align", choices=["se3", "sim3", "none"], default="se3")
    e.add_argument("--max-dt", type=float, default=0.02, help="max timestamp difference for a match (s)")
    e.add_argument("--json", action="store_true", help="print JSON")
    e.set_defaults(func=_cmd_eval)
    return p


def main(argv: list[str] | None = None) -> int:
    from client.frames import DatasetError

    from .config import ConfigError

    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.WARNING,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        return args.func(args)
    except (DatasetError, ConfigError, ValueError, OSError) as e:
        print(f"mnemoslam {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
