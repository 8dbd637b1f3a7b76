"""Leaving a process whose work is done without Python's finalization.

`mnemoslam serve` and its mapping child end with everything they own closed explicitly (the
database, the Zenoh session, the child joined, every committed row on disk: a kill -9 at any
moment leaves a consistent database anyway). What Python's finalization then does (tearing
down the modules of OpenCV, GTSAM, FAISS, onnxruntime, NumPy, and collecting their objects)
took ~0.6 s of CPU for each of the two processes on the 2-core AVX2 machine: a service's stop
(SIGTERM to exit) 1.0-1.2 s with it, 0.19-0.38 s without (issue 27: the test suite starts ~50
services). `exit_process` flushes the logs and the standard streams and leaves with `os._exit`;
`serve` first closes the Zenoh sessions left open, as client/transport.py's exit hook would.
"""
from __future__ import annotations

import logging
import os
import sys
from typing import NoReturn


def exit_process(code: int) -> NoReturn:
    """Flush the log handlers and the standard streams, then end the process with `code` at
    once (no atexit handlers, no module teardown). Only for a process whose resources are all
    closed already."""
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # closed or gone (a pipe whose reader left)
            pass
    os._exit(code)
