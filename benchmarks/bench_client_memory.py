"""Benchmark: what the process that plans and stitches a tiled run holds per tile, what Dask's
scheduler holds per task in it, and what two processes get from this machine's cores.

    python benchmarks/bench_client_memory.py [--tiles 100000] [--tasks 200000] [--cpu]

1. Per tile (tracemalloc): the structures held while the tiles run, as lists of objects (a
   SpilledTile, a TileJob, a name and a (TileBrief, resumed) tuple per tile, as before a8a53fe)
   and as kbs holds them now (SpilledTiles and TileBriefs: arrays).
2. Per task (--tasks N, 0: skipped): a LocalCluster with one worker, its scheduler in this
   process; N trivial tasks submitted as kbs.tiles.run.submit_all does (8 in flight, each released
   when done); this process's anonymous resident memory after a collection at a few counts.
3. --cpu: the same CPU-bound work alone, then two copies at once in two processes (one thread
   each): how much of a second core two processes get (a pure Python loop; numpy's eigh).
"""
from __future__ import annotations

import argparse
import gc
import multiprocessing as mp
import os
import time
import tracemalloc
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")  # one thread a process (the CPU probe), set before numpy loads BLAS
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402


def per_tile(n: int) -> None:
    from kbs.tiles.grid import TileGrid
    from kbs.tiles.stream import SpilledTile, SpilledTiles
    from kbs.tiles.streamed import TileBrief, TileBriefs, TileJob

    side = int(np.ceil(np.sqrt(n)))
    folder = Path("/tmp/kbs-spill/a-spill-folder-abcdef")
    grid = TileGrid(150.0, 15.0, np.eye(3)[:2], (0.0, 0.0), (side, side))
    head = {"label_names": ["ground", "obstacle"], "rule_base": "airborne"}
    xyz, store = str(folder / "xyz.npy"), "/out/cloud.tiles"
    cells = [(k // side, k % side) for k in range(n)]

    def brief(name: str) -> TileBrief:
        return TileBrief(name=name, path=str(folder / f"{name}.summary.pkl"), n_clusters=100, n_ids=300,
                         n_limits=50, n_splits=120, label_counts=np.array([10, 20, 3, 0], dtype=np.int64),
                         root="root", notes=[], head=head)

    def objects() -> object:
        tiles = [SpilledTile(f"t{i}_{j}", i, j, (i * 150.0, j * 150.0, i * 150.0 + 150, j * 150.0 + 150), folder,
                             5000 + i, 4000 + j) for i, j in cells]
        jobs = [TileJob(xyz, t, grid, store, b"x" * 32, False) for t in tiles]
        return tiles, jobs, [t.name for t in tiles], [(brief(t.name), False) for t in tiles]

    def arrays() -> object:
        i, j = np.array([c[0] for c in cells]), np.array([c[1] for c in cells])
        tiles = SpilledTiles(grid, folder, i, j, 5000 + i, 4000 + j)
        briefs = TileBriefs(tiles.names, folder)
        for k in range(n):
            briefs.add(k, brief(tiles.names[k]))
        return tiles, briefs

    print(f"\nWhat the stitching process holds per tile while the tiles run ({n:,} synthetic tiles, tracemalloc)\n")
    print("| held as | bytes a tile | MB | GB at 2.1 million tiles (10^10 points) |")
    print("|---|---:|---:|---:|")
    for label, build in (("lists of objects (before a8a53fe)", objects), ("arrays (SpilledTiles, TileBriefs)", arrays)):
        gc.collect()
        tracemalloc.start()
        s0 = tracemalloc.get_traced_memory()[0]
        held = build()
        gc.collect()
        size = tracemalloc.get_traced_memory()[0] - s0
        tracemalloc.stop()
        del held
        print(f"| {label} | {size / n:,.0f} | {size / 1e6:,.1f} | {size / n * 2.1e6 / 1e9:.2f} |", flush=True)


def _anon_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("RssAnon"):
                return int(line.split()[1]) / 1024
    return float("nan")


def _trivial(k: int) -> tuple[int, None]:
    return k, None


def per_task(n: int) -> None:
    from distributed import Client, LocalCluster, as_completed

    marks = sorted({m for m in (2_000, n // 4, n // 2, 3 * n // 4, n) if m >= 2_000})
    seen: dict[int, float] = {}
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster, \
            Client(cluster) as client:
        def submit(k: int):
            return client.submit(_trivial, k, pure=False, key=f"kbs-tile-t{k // 150}_{k % 150}-{os.urandom(6).hex()}")

        window = 8
        pending = as_completed([submit(k) for k in range(min(window, n))])
        nxt, done = min(window, n), 0
        for future in pending:
            future.result()
            future.release()
            done += 1
            if nxt < n:
                pending.add(submit(nxt))
                nxt += 1
            if done in marks:
                gc.collect()
                seen[done] = _anon_mb()
    print("\nDask's scheduler in this process: anonymous RSS after N trivial tasks, 8 in flight\n")
    print("| tasks | anonymous MB | bytes a task since the previous row |")
    print("|---:|---:|---:|")
    last = None
    for m in marks:
        step = "" if last is None else f"{(seen[m] - seen[last]) * 2**20 / (m - last):,.0f}"
        print(f"| {m:,} | {seen[m]:.1f} | {step} |")
        last = m


def _loop(n: int = 30_000_000) -> int:
    s = 0
    for i in range(n):
        s += i * i
    return s


def _eigh(reps: int = 60) -> float:
    a = np.random.default_rng(0).random((400, 400))
    for _ in range(reps):
        a = np.linalg.eigh(a @ a.T / 400)[1]
    return float(a[0, 0])


def _timed(name: str) -> float:
    fn = {"python loop": _loop, "numpy eigh": _eigh}[name]
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def cpu() -> None:
    print("\nThe same CPU-bound work alone and two copies at once (two processes, one thread each)\n")
    print("| work | alone s (best of 2) | two at once s (slower) | work of two processes / one |")
    print("|---|---:|---:|---:|")
    for name in ("python loop", "numpy eigh"):
        alone = min(_timed(name) for _ in range(2))
        with mp.Pool(2) as pool:
            both = pool.map(_timed, [name, name])
        print(f"| {name} | {alone:.2f} | {max(both):.2f} | {2 * alone / max(both):.2f}x |", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tiles", type=int, default=100_000, help="synthetic tiles for the per-tile measure (0: skip)")
    ap.add_argument("--tasks", type=int, default=0, help="trivial Dask tasks for the per-task measure (0: skip)")
    ap.add_argument("--cpu", action="store_true", help="also the two-process CPU probe")
    args = ap.parse_args()
    print(f"load average {os.getloadavg()[0]:.1f}, {os.cpu_count()} cores")
    if args.tiles:
        per_tile(args.tiles)
    if args.tasks:
        per_task(args.tasks)
    if args.cpu:
        cpu()


if __name__ == "__main__":
    main()
