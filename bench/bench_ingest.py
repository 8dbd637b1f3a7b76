"""Loopback ingest throughput and latency: encode -> zenoh put -> receive -> decode.

    .venv/bin/python bench/bench_ingest.py [--frames 300] [--paced 150] [--rate 30] [--same-process] [--clean]

A receiver (the service side: a peer listening on a free 127.0.0.1 port, subscribed to
`<prefix>/*/camera/frame`, decoding every message with `mnemoslam.client.kernel.protocol.decode_frame`) runs
in a second process (default; zenoh uses shared memory between processes on one host) or,
with --same-process, in this process on a second session. The sender is a `CameraStreamer`
(CongestionControl.BLOCK) connecting to it, fed with pre-rendered 640x480 synthetic RGB-D
frames (Kinect-like noise unless --clean, so PNG sizes are realistic).

Per encoding (colour / depth) it prints:
- throughput: frames sent back to back, frames/s and MB/s of messages from the first send to
  the last decode (the slower of encode / transport / decode sets the pace: BLOCK
  back-pressure), and the one-way latency under that load (queueing included);
- paced latency: frames sent at --rate Hz, one-way latency p50 / p99 from just before
  encoding to just after decoding (the send time travels in the frame stamp; both ends read
  the same host clock).
"""
from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import socket
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

CASES = [("raw", "raw"), ("raw", "png"), ("png", "png"), ("jpeg", "png"), ("jpeg", "raw")]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def receiver(port: int, prefix: str, conn) -> None:
    """Subscribe to all frames, decode each, report latencies per armed batch over `conn`."""
    from mnemoslam.client.kernel.protocol import KeySpace, ProtocolError, decode_frame
    from mnemoslam.client.transport import ZenohSettings, open_session

    session = open_session(ZenohSettings.service([f"tcp/127.0.0.1:{port}"]))
    lock = threading.Lock()
    done = threading.Event()
    state = {"expected": 0, "lat": [], "bytes": 0, "last": 0.0, "errors": 0}

    def on_frame(sample) -> None:
        payload = sample.payload.to_bytes()
        try:
            w = decode_frame(payload)
        except ProtocolError:
            with lock:
                state["errors"] += 1
            return
        now = time.time()
        with lock:
            state["lat"].append(now - w.frame.stamp)
            state["bytes"] += len(payload)
            state["last"] = now
            if len(state["lat"]) >= state["expected"] > 0:
                done.set()

    sub = session.declare_subscriber(KeySpace(prefix).frames_wildcard(), on_frame)
    conn.send("ready")
    try:
        while True:
            n = conn.recv()
            if n is None:
                break
            with lock:
                state.update(expected=n, lat=[], bytes=0, last=0.0, errors=0)
                done.clear()
            conn.send("armed")
            done.wait(timeout=300)
            with lock:
                conn.send({"lat": list(state["lat"]), "bytes": state["bytes"], "last": state["last"],
                           "errors": state["errors"]})
    finally:
        sub.undeclare()
        session.close()


def _send_batch(cam, frames, n, conn, rate=None):
    from mnemoslam.client.kernel.frames import Frame

    conn.send(n)
    assert conn.recv() == "armed"
    t_first = None
    t0 = time.perf_counter()
    for k in range(n):
        if rate:
            delay = t0 + k / rate - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
        src = frames[k % len(frames)]
        stamp = time.time()
        if t_first is None:
            t_first = stamp
        cam.send(Frame(k, stamp, src.image, src.depth), k)
    result = conn.recv()
    result["first"] = t_first
    return result


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=300, help="frames per throughput run (default 300)")
    ap.add_argument("--paced", type=int, default=150, help="frames per paced latency run (default 150)")
    ap.add_argument("--rate", type=float, default=30.0, help="rate of the paced run in Hz (default 30)")
    ap.add_argument("--distinct", type=int, default=30, help="pre-rendered distinct frames (default 30)")
    ap.add_argument("--same-process", action="store_true", help="receiver on a second session in this process")
    ap.add_argument("--clean", action="store_true", help="noise-free synthetic frames (compress much better)")
    args = ap.parse_args()

    import importlib.metadata

    from mnemoslam.client.kernel.protocol import KeySpace
    from mnemoslam.client.streamer import CameraStreamer
    from mnemoslam.client.synthetic import SyntheticDataset
    from mnemoslam.client.transport import ZenohSettings, open_session

    ds = SyntheticDataset("loop", noise=not args.clean)
    step = max(1, len(ds) // args.distinct)
    frames = [ds.frame(i * step) for i in range(args.distinct)]
    print(f"zenoh {importlib.metadata.version('eclipse-zenoh')}, {os.cpu_count()} CPUs, "
          f"{'one process' if args.same_process else 'two processes'}, {len(frames)} distinct 640x480 RGB-D frames "
          f"({'clean' if args.clean else 'Kinect-like noise'})")

    port, prefix = _free_port(), f"bench{os.getpid()}"
    parent, child = mp.Pipe()
    if args.same_process:
        worker = threading.Thread(target=receiver, args=(port, prefix, child), daemon=True)
    else:
        worker = mp.get_context("spawn").Process(target=receiver, args=(port, prefix, child), daemon=True)
    worker.start()
    assert parent.recv() == "ready"
    session = open_session(ZenohSettings.client([f"tcp/127.0.0.1:{port}"]))
    rows = []
    try:
        for color, depth in CASES:
            cam = CameraStreamer(session, "bench", ds.calibration, KeySpace(prefix), color=color, depth=depth)
            if not cam.wait_for_subscriber(10.0):
                raise SystemExit("receiver did not subscribe")
            _send_batch(cam, frames, 20, parent)  # warm-up
            thr = _send_batch(cam, frames, args.frames, parent)
            paced = _send_batch(cam, frames, args.paced, parent, rate=args.rate)
            cam.close()
            n = len(thr["lat"])
            secs = thr["last"] - thr["first"]
            lat_t = np.array(thr["lat"]) * 1e3
            lat_p = np.array(paced["lat"]) * 1e3
            rows.append((f"{color}/{depth}", thr["bytes"] / max(n, 1) / 1e3, n / secs, thr["bytes"] / secs / 1e6,
                         np.percentile(lat_t, 50), np.percentile(lat_t, 99), np.percentile(lat_p, 50),
                         np.percentile(lat_p, 99), n == args.frames and len(lat_p) == args.paced))
            r = rows[-1]
            print(f"  {r[0]:<9} {r[1]:7.0f} kB/frame  {r[2]:7.1f} frames/s  {r[3]:7.1f} MB/s  "
                  f"loaded p50 {r[4]:6.1f} ms p99 {r[5]:6.1f} ms | "
                  f"{args.rate:g} Hz p50 {r[6]:5.2f} ms p99 {r[7]:5.2f} ms"
                  + ("" if r[8] else "  (frames missing!)"), flush=True)
    finally:
        parent.send(None)
        worker.join(timeout=10)
        session.close()
    print()
    print("| colour/depth | kB/frame | frames/s | MB/s | loaded p50 / p99 ms | paced p50 / p99 ms |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r[0]} | {r[1]:.0f} | {r[2]:.1f} | {r[3]:.1f} | {r[4]:.1f} / {r[5]:.1f} | {r[6]:.2f} / {r[7]:.2f} |")
    return 0 if all(r[8] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
