"""Benchmark: kbs run --tile on Dask at 10^6 to 10^8 points: wall time, peak memory, throughput.

The clouds are real airborne scans (the six ISPRS reference samples of ../shared/data) laid side by
side on a grid, each copy jittered (a few cm of noise, a random quarter turn) so that no two are
the same, written as one LAS file per size to a temporary folder (never committed; removed at the
end). Each size runs as ``kbs run --rules airborne --tile SIZE --scheduler local -j W`` in a fresh
process, for W = 1 and 2 workers; the LAS is read in chunks (the default ``--chunk-points``).

Prints markdown: points, tiles, workers, wall time, peak RSS of the client (the kbs process) and
of the largest worker (sampled every 0.2 s over the process tree; in brackets the peak of its
anonymous part, without the resident pages of memory-mapped files), points per second, kbs's own
split of its time (read, segment, write: the summary's time line), the speed-up
against one worker (when it ran) and the machine's 1-minute load average at the run's start and
end (the machine may be shared: the other processes' load is part of the measure). A size and worker
count whose estimated time (from the largest size measured with as many workers) exceeds
``--budget`` minutes is printed as "not run: estimated N minutes".

Usage: python benchmarks/bench_scale.py [--sizes 1e6 1e7 1e8] [--workers 1 2] [--tile 150] [--budget 30]
                                        [--timeout MINUTES] [--keep DIR]
"""
from __future__ import annotations

import argparse
import math
import os
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_ground import scans  # noqa: E402


def write_cloud(path: Path, n_points: int, seed: int = 0) -> int:
    """Write ``n_points`` (rounded up to whole copies) of jittered ISPRS samples side by side to
    the LAS ``path``, copy by copy (the whole cloud is never in memory); returns the points written."""
    import laspy

    rng = np.random.default_rng(seed)
    samples = [s.xyz - s.xyz.min(axis=0) for s in scans(["isprs"])]
    cell = max(float(np.ptp(s[:, :2], axis=0).max()) for s in samples) + 5.0
    per_copy = np.mean([len(s) for s in samples])
    n_copies = math.ceil(n_points / per_copy)
    side = math.ceil(math.sqrt(n_copies))
    header = laspy.LasHeader(point_format=1, version="1.2")
    header.offsets, header.scales = np.zeros(3), np.array([0.01, 0.01, 0.01])
    written = 0
    with laspy.open(str(path), mode="w", header=header) as writer:
        for k in range(n_copies):
            X = samples[k % len(samples)].copy()
            turn = rng.integers(4)
            c, s = np.cos(turn * np.pi / 2), np.sin(turn * np.pi / 2)
            X[:, :2] = (X[:, :2] - cell / 2) @ np.array([[c, -s], [s, c]]).T + cell / 2
            X += rng.normal(0.0, 0.03, X.shape)
            X[:, 0] += (k % side) * cell
            X[:, 1] += (k // side) * cell
            X = X[: n_points - written] if written + len(X) > n_points else X
            rec = laspy.ScaleAwarePointRecord.zeros(len(X), header=header)
            rec.x, rec.y, rec.z = X[:, 0], X[:, 1], X[:, 2]
            writer.write_points(rec)
            written += len(X)
            if written >= n_points:
                break
    return written


def _anonymous(info) -> int:
    """The part of a process's resident memory that is its own (heap, stacks, anonymous maps):
    RSS minus the resident pages of mapped files and shared memory (``shared``, Linux's RssFile +
    RssShmem). The client memory-maps the spill folder's coordinates and per-point results, and
    the pages of those files it has touched count in its RSS while the kernel may drop them at
    any time (they are the page cache, written back to the files): they grow with the cloud and
    are not memory the process holds."""
    return info.rss - getattr(info, "shared", 0)


def run_measured(cmd: list[str], timeout: float | None = None) -> tuple[float, dict[str, float], int | None, str]:
    """Run ``cmd``; wall seconds, the peaks in MB (``client``/``worker``: RSS of the process itself
    and of its largest descendant, a Dask worker; ``client_anon``/``worker_anon``: the same
    without the resident pages of mapped files, :func:`_anonymous`), the exit code (None: stopped
    after ``timeout`` seconds) and what it printed."""
    import psutil

    t0 = time.perf_counter()
    env = {**os.environ, "KBS_PROGRESS_SECONDS": "10"}
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    peak = {"client": 0, "worker": 0, "client_anon": 0, "worker_anon": 0}
    done = threading.Event()

    def sample() -> None:
        p = psutil.Process(proc.pid)
        while not done.is_set():
            try:
                info = p.memory_info()
                peak["client"] = max(peak["client"], info.rss)
                peak["client_anon"] = max(peak["client_anon"], _anonymous(info))
                for child in p.children(recursive=True):
                    try:
                        info = child.memory_info()
                        peak["worker"] = max(peak["worker"], info.rss)
                        peak["worker_anon"] = max(peak["worker_anon"], _anonymous(info))
                    except psutil.Error:
                        pass
            except psutil.Error:
                pass
            done.wait(0.2)

    thread = threading.Thread(target=sample, daemon=True)
    thread.start()
    try:
        out, err = proc.communicate(timeout=timeout)
        code: int | None = proc.returncode
    except subprocess.TimeoutExpired:
        for child in psutil.Process(proc.pid).children(recursive=True):
            child.kill()
        proc.kill()
        out, err = proc.communicate()
        code = None
    done.set()
    thread.join()
    return time.perf_counter() - t0, {k: v / 1e6 for k, v in peak.items()}, code, out + err


def mem(peaks: dict[str, float], who: str) -> str:
    """``RSS (anonymous)``: the two peaks of one process, in MB."""
    return f"{peaks[who]:,.0f} ({peaks[who + '_anon']:,.0f})"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", nargs="+", type=float, default=[1e6, 1e7, 1e8])
    ap.add_argument("--workers", nargs="+", type=int, default=[1, 2])
    ap.add_argument("--tile", type=float, default=150.0, help="tile size in m (airborne: 100-250 m)")
    ap.add_argument("--budget", type=float, default=30.0, help="minutes: a size estimated longer is not run")
    ap.add_argument("--keep", type=Path, default=None, help="write the clouds here and keep them")
    ap.add_argument("--timeout", type=float, default=None,
                    help="minutes: stop a run after this long and print how far it got and its peak memory so far")
    args = ap.parse_args()
    kbs = str(Path(sys.executable).with_name("kbs"))
    print(f"kbs run --rules airborne --tile {args.tile:g} --scheduler local -j W, LAS read in chunks; "
          f"{os.cpu_count()} cores")
    print()
    print("| points | tiles | workers | wall s | kbs's read / segment / write s | client peak RSS MB (anonymous) | "
          "largest worker peak RSS MB (anonymous) | points/s | speed-up vs 1 worker | load avg start / end |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    rate: dict[int, float] = {}
    with tempfile.TemporaryDirectory(prefix="kbs-scale-") as tmp:
        folder = args.keep or Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        for size in sorted(args.sizes):
            n = int(size)
            estimates = {w: n / rate[w] / 60 for w in args.workers if w in rate}
            run = [w for w in args.workers if estimates.get(w, 0.0) <= args.budget]
            for w in args.workers:
                if w not in run:
                    print(f"| {n:,} | | {w} | not run: estimated {estimates[w]:.0f} minutes | | | | | | |", flush=True)
            if not run:
                continue
            cloud = folder / f"isprs-{n}.las"
            n = write_cloud(cloud, n)
            walls: dict[int, float] = {}
            for w in run:
                out = folder / f"out-{n}-{w}"
                load0 = os.getloadavg()[0]
                wall, peaks, code, tail = run_measured(
                    [kbs, "run", "--rules", "airborne", "--tile", f"{args.tile:g}", "--scheduler", "local",
                     "-j", str(w), str(cloud), "--out", str(out), "--force"],
                    timeout=None if args.timeout is None else args.timeout * 60)
                if code is None:  # stopped: how far it got, from its progress lines ('N tiles done')
                    done = [int(m.replace(",", "")) for m in re.findall(r"([\d,]+) tiles? done", tail)]
                    print(f"| {n:,} | | {w} | stopped after {wall:.0f} s, {max(done, default=0):,} tiles done | | "
                          f"{mem(peaks, 'client')} | {mem(peaks, 'worker')} | | | |", flush=True)
                    shutil.rmtree(out, ignore_errors=True)
                    continue
                if code != 0:
                    print(f"| {n:,} | | {w} | failed (exit {code}): {tail.strip().splitlines()[-1] if tail.strip() else ''} | | | | | | |",
                          flush=True)
                    continue
                tiles = next((line.split("tiles: ")[1].split(" of ")[0] for line in tail.splitlines()
                              if "tiles: " in line), "?")
                rate[w], walls[w] = n / wall, wall
                speedup = f"{walls[1] / wall:.2f}" if 1 in walls else ""
                split = re.search(r"time: [\d.]+ s \(read ([\d.]+), segment ([\d.]+), write ([\d.]+)\)", tail)
                parts = " / ".join(f"{float(v):.0f}" for v in split.groups()) if split else "?"
                print(f"| {n:,} | {tiles} | {w} | {wall:.0f} | {parts} | {mem(peaks, 'client')} | {mem(peaks, 'worker')} | {n / wall:,.0f} | "
                      f"{speedup} | {load0:.1f} / {os.getloadavg()[0]:.1f} |", flush=True)
                shutil.rmtree(out, ignore_errors=True)
            if args.keep is None:
                cloud.unlink()


if __name__ == "__main__":
    main()
