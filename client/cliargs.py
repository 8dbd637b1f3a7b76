"""Command-line helpers shared by `mnemoslam stream` (client/streamer.py) and the service's
commands (service/cli.py): one argparse type for counts, the dataset options, one rule for
progress bars."""
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
               "info=/camera/rgb/camera_info[,pose=/groundtruth][,imu=/imu/data] (roles color, depth, info, pose, imu; "
               "repeatable). Needed only for a role the bag has several topics of; the others are found by message "
               "type. imu_axes=optical|body|A:B:C: the IMU's axes in the camera's when the bag has no /tf_static "
               "between them (default: by the IMU frame's name)")


DEPTH_REGISTRATION = {"auto": None, "on": True, "off": False}  # --depth-registration: the 7-Scenes player's register
DEPTH_REGISTRATION_HELP = (
    "7-Scenes layout: register depth into the Kinect v1 colour camera (on), play colour and depth as given with "
    "camera-intrinsics.txt (off), or auto (the default): on for Microsoft's 7-Scenes data only, whose "
    "camera-intrinsics.txt is the Kinect v1 depth camera's 585 px (or absent); the log says which")


def dataset_options(args) -> dict:
    """The dataset players' options of `run` and `stream` arguments (max_frames, topics, register)."""
    options = {}
    max_frames = getattr(args, "max_frames", None)
    if max_frames and getattr(args, "frames", None) is None:
        options["max_frames"] = max_frames
    if getattr(args, "topics", None):
        options["topics"] = args.topics
    register = DEPTH_REGISTRATION[getattr(args, "depth_registration", None) or "auto"]
    if register is not None:
        options["register"] = register
    return options


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


__all__ = ["DEPTH_REGISTRATION", "DEPTH_REGISTRATION_HELP", "FRAMES_HELP", "TOPICS_HELP", "dataset_options",
           "frame_range_arg", "positive_int", "want_progress"]
