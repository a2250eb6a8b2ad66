"""Benchmark: kbs at sensor rate. Per-frame latency of the loaded segmenter (``kbs.Segmenter``,
built once, then ``segment(points)`` frame after frame) on the real vehicle scans, with one
process (``jobs=1``) and with ``jobs=2``, against Patchwork++'s segmentation of the same points in
the same run; then the whole ``kbs run`` process (start-up, imports, reading, segmentation,
writing) against a whole Patchwork++ process that reads the same file; then one ``kbs run`` on a
folder of all the scans, per ``-j`` (several scans run ``-j`` at a time).

Prints markdown tables: medians over ``--repeats`` frames (after one warm-up frame that is not
counted), min and max, and the ratio to Patchwork++ measured in the same run. The machine is
shared: compare ratios, not absolute times across runs.

Usage: python benchmarks/bench_run.py [--repeats 5] [--jobs 1 2] [--process-repeats 5] [--batch-repeats 3]
Patchwork++ comes with ``pip install .[bench]``; without it the ratios are left out, saying why.
"""
from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import peers  # noqa: E402

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def kbs_command() -> list[str]:
    exe = shutil.which("kbs", path=str(Path(sys.executable).parent)) or shutil.which("kbs")
    return [exe] if exe else [sys.executable, "-m", "kbs.cli.main"]


def frames() -> list[tuple[str, Path, np.ndarray, np.ndarray]]:
    """(name, file, points in the sensor frame as kbs reads them, the sensor position)."""
    from kbs.io import read_cloud

    out = []
    p = DATA / "semantickitti" / "000001.points.npy"
    out.append(("SemanticKITTI 000001", p, read_cloud(p).xyz, np.zeros(3)))
    for s in ("000000", "000001"):
        p = DATA / "gndnet" / f"{s}.points.npy"
        # GndNet shifted its scans so that the ground is near z = 0: the sensor is 1.73 m up
        out.append((f"GndNet {s}", p, read_cloud(p).xyz, np.array([0.0, 0.0, 1.73])))
    for i in range(3):
        p = DATA / "semantickitti-seq00" / f"seq00_00000{i}.bin"
        out.append((f"SemanticKITTI seq00 {i} (full res.)", p, read_cloud(p).xyz, np.zeros(3)))
    return out


def _pw_points(X: np.ndarray, sensor: np.ndarray) -> np.ndarray:
    """Points for Patchwork++: its frame is the sensor's (z up, sensor at the origin)."""
    return X - sensor


def latency(repeats: int, jobs_list: list[int]) -> None:
    import kbs

    pw_missing = peers.available("pypatchworkpp")
    if pw_missing:
        print(f"> Patchwork++ is not available, no ratios: {pw_missing}\n")
    print(f"Loaded segmenter, rule base 'outdoor': ms per frame, median of {repeats} frames after one warm-up "
          "(min-max), and the ratio to Patchwork++'s segmentation of the same points, same run\n")
    head = "| scan | points |" + "".join(f" kbs -j {j} ms |" for j in jobs_list) + " Patchwork++ ms |" + \
        "".join(f" -j {j} / Patchwork++ |" for j in jobs_list)
    print(head)
    print("|---|---:|" + "---:|" * (2 * len(jobs_list) + 1))
    segs = {j: {} for j in jobs_list}
    for name, _, X, sensor in frames():
        cells = []
        meds = {}
        for j in jobs_list:
            seg = segs[j].get(tuple(sensor))
            if seg is None:
                seg = segs[j][tuple(sensor)] = kbs.Segmenter("outdoor", jobs=j, sensor=sensor)
            seg.segment(X)  # warm-up: compiled kernels loaded, worker processes started
            ts = []
            for _ in range(repeats):
                t0 = time.perf_counter()
                seg.segment(X)
                ts.append(1e3 * (time.perf_counter() - t0))
            meds[j] = statistics.median(ts)
            cells.append(f" {meds[j]:.0f} ({min(ts):.0f}-{max(ts):.0f}) |")
        if pw_missing:
            pw_cell, ratios = " - |", " - |" * len(jobs_list)
        else:
            P = _pw_points(X, sensor)
            frame = peers.Frame(np.eye(3), float(sensor[2]) if sensor[2] else 1.73)
            peers.patchworkpp(P, frame)
            ts = []
            for _ in range(repeats):
                t0 = time.perf_counter()
                peers.patchworkpp(P, frame)
                ts.append(1e3 * (time.perf_counter() - t0))
            pw = statistics.median(ts)
            pw_cell = f" {pw:.1f} |"
            ratios = "".join(f" {meds[j] / pw:.0f}x |" for j in jobs_list)
        print(f"| {name} | {len(X):,} |" + "".join(cells) + pw_cell + ratios, flush=True)
    for d in segs.values():
        for s in d.values():
            close = getattr(s, "close", None)
            if close is not None:
                close()


PW_PROCESS = """
import sys, numpy as np
sys.path.insert(0, {bench!r})
import peers
from kbs.io import read_cloud
X = read_cloud({path!r}).xyz
print(int(peers.patchworkpp(X, peers.Frame(np.eye(3), 1.73)).sum()))
"""


def process(repeats: int, jobs_list: list[int]) -> None:
    p = DATA / "semantickitti" / "000001.points.npy"
    cmds = {f"kbs run -j {j}": kbs_command() + ["-q", "run", "--rules", "outdoor", str(p), "--out", "{out}", "-j",
                                                 str(j)] for j in jobs_list}
    if not peers.available("pypatchworkpp"):
        code = PW_PROCESS.format(bench=str(Path(__file__).resolve().parent), path=str(p))
        cmds["Patchwork++ process (read with kbs.io)"] = [sys.executable, "-c", code]
    times: dict[str, list[float]] = {k: [] for k in cmds}
    # as an installed kbs runs: pip compiles the package's bytecode when it installs it, an editable
    # install (or PYTHONDONTWRITEBYTECODE) leaves the sources to be compiled at every import (about
    # 0.1-0.2 s of a kbs run); the untimed first run of each command writes the bytecode
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    with tempfile.TemporaryDirectory() as out:
        for k, cmd in cmds.items():
            r = subprocess.run([c.replace("{out}", out) for c in cmd], capture_output=True, text=True, env=env)
            if r.returncode != 0:
                sys.exit(f"{k} failed ({r.returncode}): {r.stderr}")
        for _ in range(repeats):  # alternate, so that a busy spell hits all alike
            for k, cmd in cmds.items():
                t0 = time.perf_counter()
                r = subprocess.run([c.replace("{out}", out) for c in cmd], capture_output=True, text=True, env=env)
                dt = time.perf_counter() - t0
                if r.returncode != 0:
                    sys.exit(f"{k} failed ({r.returncode}): {r.stderr}")
                times[k].append(dt)
    print(f"\nWhole process on `{p.name}` ({repeats} runs each after an untimed one, wall time; kbs writes the PLY "
          "and the JSON; the package's bytecode compiled, as pip installs it)\n")
    ref = next((k for k in times if k.startswith("Patchwork")), None)
    print("| command | median s | min s | max s |" + (" ratio to Patchwork++ |" if ref else ""))
    print("|---|---:|---:|---:|" + ("---:|" if ref else ""))
    for k, ts in times.items():
        med = statistics.median(ts)
        ratio = f" {med / statistics.median(times[ref]):.1f}x |" if ref else ""
        print(f"| {k} | {med:.2f} | {min(ts):.2f} | {max(ts):.2f} |{ratio}")


def batch(repeats: int, jobs_list: list[int]) -> None:
    """`kbs run` on a folder of the six vehicle scans, with each -j: the scans one after the other
    (-j 1) or -j at a time, each in a process of its own (the same outputs)."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    with tempfile.TemporaryDirectory() as tmp:
        scans = Path(tmp) / "scans"
        scans.mkdir()
        for name, path, _, _ in frames():  # links with distinct stems (000001 is in two data sets)
            stem = name.split(" (")[0].replace(" ", "_")
            (scans / f"{stem}{path.suffix}").symlink_to(path)
        cmds = {f"kbs run -j {j} FOLDER": kbs_command() + ["-q", "run", "--rules", "outdoor", str(scans), "--out",
                                                           str(Path(tmp) / f"out{j}"), "-j", str(j)]
                for j in jobs_list}
        times: dict[str, list[float]] = {k: [] for k in cmds}
        for r in range(repeats + 1):  # the first round untimed (bytecode, kernel caches)
            for k, cmd in (cmds.items() if r % 2 == 0 else reversed(cmds.items())):
                t0 = time.perf_counter()
                out = subprocess.run(cmd, capture_output=True, text=True, env=env)
                dt = time.perf_counter() - t0
                if out.returncode != 0:
                    sys.exit(f"{k} failed ({out.returncode}): {out.stderr}")
                if r:
                    times[k].append(dt)
    print(f"\nSeveral scans in one `kbs run`: a folder of the {len(list(frames()))} vehicle scans above ({repeats} runs "
          "each after an untimed one, alternating; with -j > 1 that many scans at a time, each in a process of its own)\n")
    first = next(iter(times))
    print("| command | median s | min s | max s | against the first row |")
    print("|---|---:|---:|---:|---:|")
    for k, ts in times.items():
        med = statistics.median(ts)
        print(f"| {k} | {med:.2f} | {min(ts):.2f} | {max(ts):.2f} | {statistics.median(times[first]) / med:.2f}x |")


def kernels() -> str:
    """Which compiled kernels this process and the ``kbs run`` processes it starts use: the module
    built ahead of time (kbs.inference._aot), numba's, or the numpy reference (KBS_JIT, the warm-up)."""
    from kbs.inference import _aot, _compiled, _flags

    if not _flags.JIT:
        return "the numpy reference (KBS_JIT=0, or the warm-up has not cached the compiled kernels yet)"
    if _compiled._aot() is not None:
        return f"built ahead of time ({_aot.paths()[0].name}); KBS_AOT=0 or KBS_JIT=1 runs numba's"
    if _aot.ready():
        return "numba's (KBS_JIT=1 or KBS_AOT=0: the module built ahead of time is not used)"
    return "numba's (no module built ahead of time for these kernels and this CPU: kbs warmup builds it)"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5, help="frames timed per scan and setting")
    ap.add_argument("--process-repeats", type=int, default=5, help="whole-process runs per command (0: skip)")
    ap.add_argument("--batch-repeats", type=int, default=3, help="runs of kbs run on a folder of all the scans, "
                    "per -j (0: skip)")
    ap.add_argument("--jobs", type=int, nargs="+", default=[1, 2])
    args = ap.parse_args()
    if not DATA.is_dir():
        sys.exit(f"the benchmark needs the real scans in {DATA}")
    print(f"Kernels: {kernels()}\n")
    latency(args.repeats, args.jobs)
    if args.process_repeats:
        process(args.process_repeats, args.jobs)
    if args.batch_repeats:
        batch(args.batch_repeats, args.jobs)


if __name__ == "__main__":
    main()
