"""Benchmark: a tiled run of a COPC file read by its octree against the same file read as a plain
LAZ file by the spill path (``KBS_COPC=0``), same run, tiles in process.

The cloud is bench_scale's (the six ISPRS reference samples laid side by side, each copy jittered
and turned), written as LAS to a temporary folder and converted to COPC by copc-lib
(``tests/copc_files.py``: an octree of ``--levels`` levels, at most 256 points a node above the
deepest level). Each run is ``kbs run --rules airborne --tile SIZE -j 1 FILE.copc.laz`` in a
fresh process (the tiles in that process: it is the client and the only process), the two paths
alternated ``--repeats`` times. Prints markdown: wall time, peak RSS (sampled every 0.2 s), kbs's
own read / segment / write split, and whether the two results are the same bytes (run id and
timing apart). Medians over the repeats.

Usage: python benchmarks/bench_copc.py [--points 1e6] [--tile 150] [--levels 6] [--repeats 1] [--keep DIR]
"""
from __future__ import annotations

import argparse
import re
import shutil
import statistics
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent / "tests"))

from bench_scale import run_measured, write_cloud  # noqa: E402
from copc_files import write_copc  # noqa: E402


def _normalised(path: Path) -> bytes:
    data = re.sub(rb"[0-9a-f]{32}", b"0" * 32, path.read_bytes())
    return re.sub(rb'"seconds":[0-9.e+-]+', b'"seconds":0', data)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--points", type=float, default=1e6)
    ap.add_argument("--tile", type=float, default=150.0)
    ap.add_argument("--levels", type=int, default=6)
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--keep", type=Path, default=None, help="write the files here and keep them")
    args = ap.parse_args()
    kbs = shutil.which("kbs", path=str(Path(sys.executable).parent)) or shutil.which("kbs")
    assert kbs, "the kbs command is not installed"
    folder = args.keep or Path(tempfile.mkdtemp(prefix="kbs-bench-copc-"))
    folder.mkdir(parents=True, exist_ok=True)
    try:
        las, copc = folder / "cloud.las", folder / "cloud.copc.laz"
        n = write_cloud(las, int(args.points))
        nodes = write_copc(las, copc, levels=args.levels)
        las.unlink()
        print(f"{n:,} points, {nodes:,} octree nodes ({args.levels} levels), {copc.stat().st_size / 1e6:.1f} MB COPC; "
              f"--tile {args.tile:g}, tiles in process (-j 1)\n")
        paths = {"spill (KBS_COPC=0)": ["env", "KBS_COPC=0"], "COPC octree": ["env", "KBS_COPC=1"]}
        rows: dict[str, list[tuple[float, float, str]]] = {k: [] for k in paths}
        for r in range(args.repeats):
            for name, prefix in paths.items():
                out = folder / f"out-{'spill' if 'spill' in name else 'copc'}-{r}"
                cmd = [*prefix, kbs, "run", "--rules", "airborne", "--tile", f"{args.tile:g}", "-j", "1", str(copc),
                       "--out", str(out)]
                wall, rss, _, code, text = run_measured(cmd)
                if code != 0:
                    raise SystemExit(f"{name} failed ({code}):\n{text[-3000:]}")
                split = re.search(r"time: [\d.]+ s \(read ([\d.]+), segment ([\d.]+), write ([\d.]+)\)", text)
                rows[name].append((wall, rss, "/".join(split.groups()) if split else "?"))
        same = all(_normalised(folder / f"out-spill-{r}" / f"cloud.copc.{ext}") ==
                   _normalised(folder / f"out-copc-{r}" / f"cloud.copc.{ext}")
                   for r in range(args.repeats) for ext in ("laz", "json"))
        print("| path | wall s | client peak RSS MB | read / segment / write s (kbs) | runs |")
        print("|---|---:|---:|---|---:|")
        for name, got in rows.items():
            print(f"| {name} | {statistics.median(g[0] for g in got):.1f} | {statistics.median(g[1] for g in got):.0f} "
                  f"| {', '.join(g[2] for g in got)} | {len(got)} |")
        print(f"\nsame bytes (LAZ and JSON, run id and timing apart): {'yes' if same else 'NO'}")
    finally:
        if args.keep is None:
            shutil.rmtree(folder, ignore_errors=True)


if __name__ == "__main__":
    main()
