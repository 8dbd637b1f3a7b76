"""Command-line helpers shared by `mnemoslam stream` (client/streamer.py) and the service's
commands (service/cli.py): one argparse type for counts, one rule for progress bars."""
from __future__ import annotations

import argparse
import sys


def positive_int(text: str) -> int:
    """argparse `type=` for options such as --max-frames: an integer >= 1 (0 and negative
    numbers are errors, never 'unlimited'; leave the option out for no limit)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer (leave the option out for no limit), got {value}")
    return value


def frame_range_arg(text: str) -> tuple[int, int | None]:
    """argparse `type=` for --frames START:END (client.datasets.subrange.parse_frames)."""
    from .datasets.subrange import parse_frames

    try:
        return parse_frames(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


FRAMES_HELP = ("play only frames START to END-1 of the dataset (either may be left out: 300: or :500), each with "
               "its stamp and ground truth as in the full run; --max-frames then counts from START")

TOPICS_HELP = ("ROS bags: the topics to play, e.g. color=/camera/rgb/image_raw,depth=/camera/depth/image_raw,"
               "info=/camera/rgb/camera_info[,pose=/groundtruth] (roles color, depth, info, pose; repeatable). "
               "Needed only for a role the bag has several topics of; the others are found by message type")


def want_progress(quiet: bool = False, stream=None) -> bool:
    """Progress bars only on an interactive terminal: not with -q/--quiet, and not when
    `stream` (default stderr, where tqdm draws) is a pipe or a file, where every update would
    be a line of its own."""
    if quiet:
        return False
    stream = sys.stderr if stream is None else stream
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return False


__all__ = ["FRAMES_HELP", "TOPICS_HELP", "frame_range_arg", "positive_int", "want_progress"]
