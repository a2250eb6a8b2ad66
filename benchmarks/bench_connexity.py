"""Benchmark: the connexity measure of CAh, method 'graph' (the default) against 'alpha_opening'
(the paper's alpha-shape opened by a disc), per call and per LiDAR frame.

Prints markdown:

1. ms per call on synthetic clusters of 300, 3,000 and 30,000 points (two discs joined by a
   bridge, uniformly sampled), median of repeats, and the stages of 'alpha_opening': Delaunay and
   the alpha-complex, the alpha-shape (coverage union of the triangles), the opening (two shapely
   buffers), the points in each component; with the two ways of building the alpha-shape's
   polygons measured side by side (the union of the triangles, which is used, and shapely's
   ``polygonize`` / ``build_area`` of the boundary edges).
2. The calls of real frames: every connexity measure that ``rules/outdoor.yaml`` makes on the
   SemanticKITTI scan and the two GndNet scans (recorded from one run, ``jobs=1``), replayed with
   each method: calls, points, ms per frame, and in how many calls the two count a different
   number of significant components.
3. Whole frames: the outdoor rules as shipped against a copy whose connexity check says
   ``method: alpha_opening`` (``--opening-factor``), in one process with ``jobs=1``, taking turns
   ``--rounds`` times: median CPU and wall seconds per frame and the ground F1.

Usage: python benchmarks/bench_connexity.py [--rounds 3] [--opening-factor 1.0] [--skip-frames]
"""
from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_ground  # noqa: E402

import kbs.geometry.connexity as C  # noqa: E402
import kbs.knowledge.predicates as P  # noqa: E402
from kbs.evaluation import ground_metrics  # noqa: E402
from kbs.knowledge import Interpreter, load_rule_base  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
UP = np.array([0.0, 0.0, 1.0])
SHIPPED_PARAMS = "params: {alpha_factor: 3.0, min_fraction: 0.05}"


def synthetic(n: int, seed: int = 0) -> np.ndarray:
    """About n points: two discs of radius 1 (centres 3 apart) and a bridge 0.3 wide, at one density."""
    rng = np.random.default_rng(seed)
    area = 2 * np.pi + 1.0 * 0.3
    m = int(n * 1.3)
    P2 = rng.uniform([-1, -1], [4, 1], (m * 2, 2))
    inside = (np.hypot(P2[:, 0], P2[:, 1]) <= 1) | (np.hypot(P2[:, 0] - 3, P2[:, 1]) <= 1) | \
             ((P2[:, 0] >= 1) & (P2[:, 0] <= 2) & (np.abs(P2[:, 1]) <= 0.15))
    P2 = P2[inside][:n]
    assert abs(len(P2) - n) <= 1, (len(P2), n, area)
    return np.c_[P2, rng.normal(0, 0.01, len(P2))]


def timed(fn, repeats: int) -> float:
    """Median CPU ms of ``repeats`` calls (after one warm-up call). CPU time of this process: both
    methods run on one thread, and other jobs on a shared machine inflate it much less than the
    wall time."""
    fn()
    out = []
    for _ in range(repeats):
        t0 = time.process_time()
        fn()
        out.append(time.process_time() - t0)
    return 1e3 * statistics.median(out)


def per_call() -> None:
    import shapely

    print("## Per call (synthetic clusters: two discs and a bridge)\n")
    print("| points | graph CPU ms | alpha_opening CPU ms | ratio | of which: Delaunay + alpha-complex | alpha-shape union "
          "| opening | points in components | polygonize of boundary edges (alone) | build_area of boundary edges |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for n in (300, 3000, 30000):
        X = synthetic(n)
        reps = {300: 60, 3000: 15, 30000: 5}[n]
        center = X.mean(axis=0)
        g = timed(lambda: C.connexity(X, center, UP), reps)
        a = timed(lambda: C.connexity(X, center, UP, method="alpha_opening"), reps)
        D = C._distinct(C.project_on_plane(X, center, UP))
        alpha = 3.0 * D.spacing
        t_complex = timed(lambda: C.alpha_complex(D.points, alpha), reps)
        t_shape = timed(lambda: C.alpha_shape(D.points, alpha), reps) - t_complex
        shape = C.alpha_shape(D.points, alpha)
        t_open = timed(lambda: C.alpha_opening(shape, alpha), reps)
        parts = C.alpha_opening(shape, alpha)
        t_points = timed(lambda: C._points_in_parts(D.points, parts, alpha, alpha), reps)
        T = C.alpha_complex(D.points, alpha)
        E = np.sort(np.concatenate([T[:, [0, 1]], T[:, [1, 2]], T[:, [2, 0]]]), axis=1)
        E, count = np.unique(E, axis=0, return_counts=True)
        lines = shapely.linestrings(D.points[E[count == 1]])
        t_poly = timed(lambda: shapely.polygonize(lines), reps)
        t_build = timed(lambda: shapely.build_area(shapely.multilinestrings(lines)), reps)
        print(f"| {len(X):,} | {g:.2f} | {a:.2f} | {a / g:.1f} | {t_complex:.2f} | {t_shape:.2f} | {t_open:.2f} | "
              f"{t_points:.2f} | {t_poly:.2f} | {t_build:.2f} |", flush=True)
    print("\n(`polygonize` returns the holes as faces too, and `build_area`, which sorts them out, fills some "
          "holes that touch the outline at a vertex; the union of the triangles is exact, see "
          "tests/test_connexity.py.)\n")


def record_calls(scan) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, dict]]:
    """The connexity calls of one outdoor run (jobs=1) on a scan."""
    calls = []
    real = C.connexity

    def spy(X, center, normal, **kw):
        calls.append((np.array(X), np.array(center), np.array(normal), dict(kw)))
        return real(X, center, normal, **kw)

    P._connexity = type("Spy", (), {"connexity": staticmethod(spy)})
    try:
        Interpreter(load_rule_base("outdoor"), sensor=scan.sensor, jobs=1).run(scan.xyz)
    finally:
        P._connexity = C
    return calls


def replay(scans) -> None:
    print("## The connexity calls of real frames (outdoor rules), replayed\n")
    print("| scan | calls | points (min / median / max per call) | graph CPU ms per frame | alpha_opening CPU ms per frame "
          "| ratio | calls counting other components |")
    print("|---|---:|---|---:|---:|---:|---:|")
    for scan in scans:
        calls = record_calls(scan)
        sizes = sorted(len(c[0]) for c in calls)
        ms, counts = {}, {}
        for method in ("graph", "alpha_opening"):
            for X, c, n, kw in calls[:3]:  # warm-up
                C.connexity(X, c, n, **{**kw, "method": method})
            t0 = time.process_time()
            counts[method] = [C.connexity(X, c, n, **{**kw, "method": method}).n_significant for X, c, n, kw in calls]
            ms[method] = 1e3 * (time.process_time() - t0)
        differ = sum(a != b for a, b in zip(counts["graph"], counts["alpha_opening"]))
        print(f"| {scan.dataset} {scan.name} | {len(calls)} | {sum(sizes):,} ({sizes[0]} / {sizes[len(sizes) // 2]} / "
              f"{sizes[-1]:,}) | {ms['graph']:.0f} | {ms['alpha_opening']:.0f} | "
              f"{ms['alpha_opening'] / ms['graph']:.1f} | {differ} |", flush=True)
    print()


def frames(scans, rounds: int, factor: float) -> None:
    text = (ROOT / "rules" / "outdoor.yaml").read_text()
    assert SHIPPED_PARAMS in text
    alpha = tempfile.NamedTemporaryFile("w", suffix=".yaml", prefix="outdoor-alpha-", delete=False)
    alpha.write(text.replace(SHIPPED_PARAMS, SHIPPED_PARAMS[:-1] + f", method: alpha_opening, opening_factor: {factor}}}"))
    alpha.close()
    sides = {"shipped (graph)": "outdoor", f"alpha_opening x {factor:g}": alpha.name}
    print(f"## Whole frames, jobs=1, {rounds} rounds taking turns\n")
    print("| scan | rules | ground F1 | CPU s per frame (median) | wall s per frame (median) | clusters |")
    print("|---|---|---:|---:|---:|---:|")
    for scan in scans:
        cpu, wall, f1, nc = {s: [] for s in sides}, {s: [] for s in sides}, {}, {}
        for _ in range(rounds):
            for side, rules in sides.items():
                rb = load_rule_base(rules)
                c0, w0 = time.process_time(), time.perf_counter()
                seg = Interpreter(rb, sensor=scan.sensor, jobs=1).run(scan.xyz)
                cpu[side].append(time.process_time() - c0)
                wall[side].append(time.perf_counter() - w0)
                pred = seg.label == rb.label_names.index("ground")
                f1[side] = ground_metrics(pred[scan.valid], np.where(scan.truth, 1, 0)[scan.valid], ground_values=(1,)).f1
                nc[side] = len(seg.clusters)
        for side in sides:
            print(f"| {scan.dataset} {scan.name} | {side} | {f1[side]:.4f} | {statistics.median(cpu[side]):.2f} | "
                  f"{statistics.median(wall[side]):.2f} | {nc[side]} |", flush=True)
    Path(alpha.name).unlink()
    print()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--opening-factor", type=float, default=1.0)
    ap.add_argument("--skip-frames", action="store_true", help="only the per-call tables")
    args = ap.parse_args()
    per_call()
    if not bench_ground.DATA.is_dir():
        sys.exit(f"the frame tables need the real scans in {bench_ground.DATA}")
    scans = bench_ground.scans(["kitti", "gndnet"])
    replay(scans)
    if not args.skip_frames:
        frames(scans, args.rounds, args.opening_factor)


if __name__ == "__main__":
    main()
