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
