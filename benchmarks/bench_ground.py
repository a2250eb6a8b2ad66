"""Benchmark: ground / obstacle segmentation, kbs (outdoor rules) against Patchwork++, CSF and a
RANSAC ground plane, on the real labelled scans of ../shared/data.

Prints markdown: one row per scan and method (precision, recall, F1, IoU of the ground class
with unlabelled points ignored, ISPRS total error, wall time), then the median over the scans of
each data set. Every method runs in this process on the same points.

Usage: python benchmarks/bench_ground.py [--sets kitti gndnet seq00 isprs las mosd] [--part tune|validate|all]
                                        [--jobs N] [--outdoor RULES] [--before outdoor|airborne RULES]
Each scan is in the tuning or the validation part of benchmarks/splits.yaml (the 'part' column);
``--part`` keeps one part, and the medians are given per data set and part.
kbs runs its splits in ``--jobs`` processes (default -1, one per core, as ``kbs run``); the peers
run as their libraries do by default. ``--outdoor`` runs the "kbs outdoor" rows with another rule
file (a variant of rules/outdoor.yaml, e.g. its connexity check with ``method: alpha_opening``).
Peers come with ``pip install .[bench]`` (open3d also needs the system library libusb-1.0);
a missing peer is named and skipped.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from collections.abc import Callable

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import peers  # noqa: E402

from kbs.evaluation import SEMANTICKITTI_GROUND, SEMANTICKITTI_IGNORED, ground_metrics, load_ground_truth  # noqa: E402
from kbs.io import read_cloud  # noqa: E402
from kbs.knowledge import Interpreter, load_rule_base  # noqa: E402
from kbs.units import scale_factors, unit  # noqa: E402

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
Z_UP = np.eye(3)
CAMERA_Y_DOWN = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])  # (x, y, z) -> (x, z, -y)


@dataclass
class Scan:
    dataset: str
    name: str
    xyz: np.ndarray
    truth: np.ndarray  # bool: ground
    valid: np.ndarray  # bool: labelled
    frame: peers.Frame
    sensor: np.ndarray  # for kbs, in the scan's own frame
    ransac_distance: float


def scans(sets: list[str]) -> list[Scan]:
    out = []
    if "kitti" in sets:
        X = np.load(DATA / "semantickitti" / "000001.points.npy").astype(np.float64)
        lab = np.load(DATA / "semantickitti" / "000001.labels.npy").ravel()
        out.append(Scan("SemanticKITTI", "000001", X, np.isin(lab, [9, 10, 11, 12, 17]), lab != 0,
                        peers.Frame(Z_UP, 1.73), np.zeros(3), 0.2))
    if "gndnet" in sets:
        for s in ("000000", "000001"):
            # GndNet shifted the scans so the ground is near z = 0: the sensor is 1.73 m up
            X = np.load(DATA / "gndnet" / f"{s}.points.npy")[:, :3].astype(np.float64)
            lab = np.load(DATA / "gndnet" / f"{s}.labels.npy")
            out.append(Scan("GndNet", s, X - [0, 0, 1.73], lab == 0, lab >= 0, peers.Frame(Z_UP, 1.73),
                            np.zeros(3), 0.2))
    if "seq00" in sets:
        for n in range(3):
            # full-resolution SemanticKITTI frames: raw classes in the .label (see kbs eval --help)
            path = DATA / "semantickitti-seq00" / f"seq00_00000{n}.bin"
            pc = read_cloud(path)
            cls = load_ground_truth(path.with_suffix(".label"), pc)
            out.append(Scan("SemanticKITTI-seq00", path.stem, pc.xyz, np.isin(cls, SEMANTICKITTI_GROUND),
                            ~np.isin(cls, SEMANTICKITTI_IGNORED), peers.Frame(Z_UP, 1.73), np.zeros(3), 0.2))
    if "isprs" in sets:
        items = [(f"samp{n}", DATA / "isprs" / f"samp{n}.txt", None) for n in ("11", "12")]
        items += [(f"samp{n}", DATA / "isprs" / f"samp{n}-utm.pcd", DATA / "isprs" / f"samp{n}-utm.labels.txt")
                  for n in ("21", "31", "51", "61")]
        for name, path, labels in items:
            pc = read_cloud(path)
            lab = (pc.fields["col3"] if labels is None else np.loadtxt(labels)[pc.index]).astype(int)
            X = pc.xyz - pc.xyz.mean(axis=0)
            # airborne: for kbs the 'sensor' is put below the scene so that the closest large
            # planar cluster is the lowest one (the paper's rover looks at the ground from 1.7 m)
            sensor = np.array([0.0, 0.0, X[:, 2].min() - 10.0])
            out.append(Scan("ISPRS", name, X, lab == 0, np.ones(len(X), bool), peers.Frame(Z_UP, 0.0, airborne=True),
                            sensor, 0.5))
    if "las" in sets:
        for name in ("autzen_trim", "4_6_crop", "sample_c"):
            pc = read_cloud(DATA / "las" / f"{name}.las")
            cls = pc.fields["classification"].astype(int)
            # in metres, as `kbs run` converts them for the metre rule bases (autzen_trim: feet,
            # 4_6_crop: US survey feet, by their CRS); the peers get the same metres
            X = (pc.xyz - pc.xyz.mean(axis=0)) * scale_factors(pc.units, unit("m"))
            # ASPRS 2 = ground; noise (7, 18) left out; the provider's classification, not hand-checked
            out.append(Scan("LAS", name, X, cls == 2, ~np.isin(cls, (7, 18)), peers.Frame(Z_UP, 0.0, airborne=True),
                            np.array([0.0, 0.0, X[:, 2].min() - 10.0]), 0.5))
    if "mosd" in sets:
        for n in (0, 5, 17, 25, 33):
            pc = read_cloud(DATA / "mosd" / f"learn{n}.pcd")
            lab = pc.fields["label"].astype(int)
            # Kinect camera frame (y down): the peers get it rotated to z up; the camera sits about
            # 0.12 m above the table plane along that axis (nominal, the same for every scene)
            out.append(Scan("mOSD table", f"learn{n}", pc.xyz, (lab >= 1) & (lab <= 9), lab != 0,
                            peers.Frame(CAMERA_Y_DOWN, 0.12), np.zeros(3), 0.01))
    return out


ROOT = Path(__file__).resolve().parents[1]
JOBS = {"kbs": -1}
SPLITS = ROOT / "benchmarks" / "splits.yaml"


def splits() -> dict[str, dict]:
    """benchmarks/splits.yaml: kind -> {rule_base, tune: [...], validate: [...]}."""
    import yaml

    doc = yaml.safe_load(SPLITS.read_text())
    return {k: v for k, v in doc.items() if isinstance(v, dict)}


def part_of(scan: Scan) -> str:
    """'tune' or 'validate' (benchmarks/splits.yaml), '-' for a scan it does not list."""
    key = f"{scan.dataset}/{scan.name}"
    for kind in splits().values():
        for part in ("tune", "validate"):
            if key in kind.get(part, []):
                return part
    return "-"


def kbs_with(rules: str, ground_label: str, only: str | tuple[str, ...] | None = None):
    """kbs with a rule base; ``only``: the data set it was written for (None: all)."""

    def run(scan: Scan) -> np.ndarray | None:
        if only is not None and scan.dataset not in ((only,) if isinstance(only, str) else only):
            return None
        rb = load_rule_base(rules)
        seg = Interpreter(rb, sensor=scan.sensor, jobs=JOBS["kbs"]).run(scan.xyz)
        return seg.label == rb.label_names.index(ground_label)

    return run


METHODS: dict[str, tuple[str | None, Callable[[Scan], np.ndarray | None]]] = {
    "kbs outdoor": (None, kbs_with("outdoor", "ground")),
    "kbs airborne": (None, kbs_with("airborne", "ground", only=("ISPRS", "LAS"))),
    "kbs tabletop": (None, kbs_with(str(ROOT / "examples" / "rules" / "tabletop.yaml"), "table", only="mOSD table")),
    "Patchwork++": ("pypatchworkpp", lambda s: peers.patchworkpp(s.xyz, s.frame)),
    "CSF": ("CSF", lambda s: peers.csf(s.xyz, s.frame)),
    "RANSAC plane": ("open3d", lambda s: peers.ransac_ground(s.xyz, s.frame, s.ransac_distance)),
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sets", nargs="+", default=["kitti", "gndnet", "seq00", "isprs", "las", "mosd"])
    ap.add_argument("--part", choices=["tune", "validate", "all"], default="all",
                    help="only the scans of this part of benchmarks/splits.yaml")
    ap.add_argument("--jobs", type=int, default=-1, help="kbs split processes (-1: one per core)")
    ap.add_argument("--outdoor", default="outdoor", help="rule file of the 'kbs outdoor' rows (default: the shipped one)")
    ap.add_argument("--before", nargs=2, action="append", default=[], metavar=("RULE_BASE", "FILE"),
                    help="also 'kbs RULE_BASE before' rows (outdoor or airborne) with another rule file, e.g. "
                         "the one before a change, in the same run (repeatable)")
    args = ap.parse_args()
    JOBS["kbs"] = args.jobs
    for base, path in args.before:
        name = f"kbs {base}"
        if name not in METHODS:
            ap.error(f"--before: no rows named '{name}'")
        only = ("ISPRS", "LAS") if base == "airborne" else None
        rows = {k: v for k, v in METHODS.items()}
        METHODS.clear()
        for k, v in rows.items():
            if k == name:
                METHODS[f"{name} before"] = (None, kbs_with(path, "ground", only=only))
            METHODS[k] = v
    if args.outdoor != "outdoor":
        METHODS["kbs outdoor"] = (None, kbs_with(args.outdoor, "ground"))
        print(f"> kbs outdoor: {args.outdoor}")
    if not DATA.is_dir():
        sys.exit(f"the benchmark needs the real scans in {DATA}")
    missing = {name: peers.available(mod) for name, (mod, _) in METHODS.items() if mod}
    for name, why in missing.items():
        if why:
            print(f"> {name} is not available and is skipped: {why}")
    methods = {k: v for k, v in METHODS.items() if not missing.get(k)}
    rows, per_set = [], {}
    print("| data set | scan | part | points | method | precision | recall | F1 | IoU | total error % | seconds |")
    print("|---|---|---|---:|---|---:|---:|---:|---:|---:|---:|")
    for scan in scans(args.sets):
        part = part_of(scan)
        if args.part != "all" and part != args.part:
            continue
        for name, (_, fn) in methods.items():
            t0 = time.perf_counter()
            pred = fn(scan)
            dt = time.perf_counter() - t0
            if pred is None:  # a rule base written for another data set
                continue
            m = ground_metrics(pred[scan.valid], np.where(scan.truth, 1, 0)[scan.valid], ground_values=(1,))
            rows.append((scan, name, m, dt))
            per_set.setdefault((scan.dataset, part, name), []).append((m, dt))
            print(f"| {scan.dataset} | {scan.name} | {part} | {len(scan.xyz):,} | {name} | {m.precision:.3f} | {m.recall:.3f} | "
                  f"{m.f1:.3f} | {m.iou:.3f} | {100 * m.total_error:.2f} | {dt:.3f} |", flush=True)
    print("\nMedian over the scans of each data set and part:\n")
    print("| data set | part | scans | method | precision | recall | F1 | IoU | total error % | seconds |")
    print("|---|---|---:|---|---:|---:|---:|---:|---:|---:|")
    for (ds, part, name), vals in per_set.items():
        med = {k: statistics.median(getattr(m, k) for m, _ in vals) for k in ("precision", "recall", "f1", "iou",
                                                                               "total_error")}
        print(f"| {ds} | {part} | {len(vals)} | {name} | {med['precision']:.3f} | {med['recall']:.3f} | {med['f1']:.3f} | "
              f"{med['iou']:.3f} | {100 * med['total_error']:.2f} | {statistics.median(d for _, d in vals):.3f} |")


if __name__ == "__main__":
    main()
