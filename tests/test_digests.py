"""Stored digests of what every shipped rule base writes on the shared scans: the PLY bytes and
the JSON's content (clusters, summary, explanation), with what changes from run to run taken out
(the run id, the input path, the seconds).

A refactor that keeps the behaviour keeps these digests. A change meant to move a result changes
them on purpose: rewrite them with ``python tests/test_digests.py --write`` and say in the commit
which digests moved and why.

The PLY's float32 memberships differ by one rounding step between the compiled kernels and their
numpy reference, so each case is digested twice, with ``KBS_JIT`` off and on. Floating-point
sums may also differ on another processor: the digests record the machine they were written on
(processor model and numpy's SIMD features) and the test skips, saying so, on a different one.
"""
from __future__ import annotations

import contextlib
import hashlib
import io
import json
import platform
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
STORE = ROOT / "tests" / "golden" / "digests.json"

#: (name, rules, scan relative to ../shared/data or 'synth:KIND:SEED', extra run options)
CASES = [
    ("outdoor-semantickitti", "outdoor", "semantickitti/000001.points.npy", []),
    ("outdoor-gndnet", "outdoor", "gndnet/000001.points.npy", []),
    ("outdoor-seq00", "outdoor", "semantickitti-seq00/seq00_000000.bin", []),
    ("airborne-samp21", "airborne", "isprs/samp21-utm.pcd", []),
    ("airborne-samp11", "airborne", "isprs/samp11.txt", []),
    ("airborne-4_6_crop", "airborne", "las/4_6_crop.las", []),
    ("airborne-sample_c", "airborne", "las/sample_c.las", []),
    ("planar_contest-learn0", "planar_contest", "mosd/learn0.pcd", []),
    ("planar_global-polyhedral", "planar_global", "synth:polyhedral:2", []),
    ("abw-synth", "abw", "synth:abw:3", []),
    ("indoor-room", "indoor", "unlabelled/room_scan1.pcd", []),
    ("tabletop-learn5", str(ROOT / "examples" / "rules" / "tabletop.yaml"), "mosd/learn5.pcd", []),
    ("poles-semantickitti", str(ROOT / "examples" / "rules" / "poles.yaml"), "semantickitti/000001.points.npy",
     ["--plugin", str(ROOT / "examples" / "plugins" / "elongation.py")]),
]
#: JSON keys that differ between two runs of the same thing
VOLATILE = {"run_id", "input", "points", "seconds", "kbs_version"}


def machine() -> dict[str, str]:
    """What floating-point results may depend on."""
    model = platform.processor() or ""
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    from numpy._core._multiarray_umath import __cpu_features__ as feats  # type: ignore[import-not-found]

    simd = ",".join(sorted(k for k, v in feats.items() if v))
    return {"cpu": model, "simd": simd, "numpy": np.__version__, "python": platform.python_version()}


def _strip(o):
    """The JSON without what differs between runs of the same thing; the repository's folder
    (in the paths of the examples' rule files) written as <ROOT>."""
    if isinstance(o, dict):
        return {k: _strip(v) for k, v in o.items() if k not in VOLATILE}
    if isinstance(o, list):
        return [_strip(v) for v in o]
    if isinstance(o, str) and str(ROOT) in o:
        return o.replace(str(ROOT), "<ROOT>")
    return o


def ply_digest(path: Path) -> str:
    """sha256 of the PLY's bytes, the run-id comment line left out (a LAS output: its points,
    which carry no run id)."""
    data = path.read_bytes()
    if path.suffix.lower() in (".las", ".laz"):
        import laspy

        las = laspy.read(str(path))
        h = hashlib.sha256()
        for name in las.point_format.dimension_names:
            h.update(name.encode() + np.ascontiguousarray(las[name]).tobytes())
        return h.hexdigest()
    head, sep, body = data.partition(b"end_header\n")
    lines = [ln for ln in head.split(b"\n") if not ln.startswith(b"comment kbs_run_id ")]
    return hashlib.sha256(b"\n".join(lines) + sep + body).hexdigest()


def json_digest(path: Path) -> str:
    doc = _strip(json.loads(path.read_text()))
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()


def _scan(spec: str, tmp: Path) -> Path:
    from kbs.cli.main import main

    if not spec.startswith("synth:"):
        return SHARED / spec
    _, kind, seed = spec.split(":")
    out = tmp / (f"{kind}.synth.{seed}" + ("" if kind == "abw" else ".ply"))  # abw writes NAME.range
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["synth", kind, "--seed", seed, "--out", str(out), "--force"]) == 0  # the test's own file
    rng = out.with_name(out.name + ".range")
    return rng if rng.exists() else out


def run_case(case, tmp: Path, jit: bool) -> dict[str, str]:
    """Run one case through the real CLI (in this process) and digest what it wrote."""
    import kbs.inference._flags as flags
    from kbs.cli.main import main

    name, rules, spec, extra = case
    old = flags.JIT
    flags.JIT = jit
    try:
        scan = _scan(spec, tmp)
        out = tmp / f"{name}-{int(jit)}"
        with contextlib.redirect_stdout(io.StringIO()):
            rc = main(["run", "--rules", rules, str(scan), "--out", str(out), "-j", "1", *extra])
    finally:
        flags.JIT = old
    assert rc == 0, f"{name}: kbs run exited {rc}"
    cloud = next(p for p in sorted(out.iterdir()) if p.suffix != ".json")
    return {"cloud": ply_digest(cloud), "json": json_digest(cloud.with_suffix(".json"))}


def _jits() -> list[bool]:
    try:
        import numba  # noqa: F401
    except ImportError:
        return [False]
    return [False, True]


def _stored() -> dict:
    return json.loads(STORE.read_text()) if STORE.exists() else {}


@pytest.mark.slow
@pytest.mark.parametrize("jit", [False, True], ids=["numpy", "compiled"])
@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_outputs_match_the_stored_digests(case, jit, tmp_path):
    if not SHARED.is_dir():
        pytest.skip("../shared/data is absent: the digests are of the shared scans")
    if jit and jit not in _jits():
        pytest.skip("numba is not installed: no compiled kernels to digest")
    store = _stored()
    if store.get("machine") != machine():
        pytest.skip(f"digests written on another machine ({store.get('machine', {}).get('cpu')}); "
                    "rewrite them here with python tests/test_digests.py --write")
    key = f"{case[0]}|{'compiled' if jit else 'numpy'}"
    assert key in store["cases"], f"no stored digest for {key}: python tests/test_digests.py --write"
    assert run_case(case, tmp_path, jit) == store["cases"][key]


def test_digest_normalisation_keeps_what_matters(tmp_path):
    """The digests leave out only the run id, paths and seconds: a changed membership byte or a
    changed label name changes them."""
    head = b"ply\nformat binary_little_endian 1.0\ncomment kbs_run_id %s\nend_header\n"
    a, b = tmp_path / "a.ply", tmp_path / "b.ply"
    a.write_bytes(head % b"1" + b"\x00\x01")
    b.write_bytes(head % b"2" + b"\x00\x01")
    assert ply_digest(a) == ply_digest(b)
    b.write_bytes(head % b"2" + b"\x00\x02")
    assert ply_digest(a) != ply_digest(b)
    ja, jb = tmp_path / "a.json", tmp_path / "b.json"
    ja.write_text(json.dumps({"run_id": "x", "summary": {"seconds": 1.0}, "label_names": ["ground"]}))
    jb.write_text(json.dumps({"run_id": "y", "summary": {"seconds": 2.0}, "label_names": ["ground"]}))
    assert json_digest(ja) == json_digest(jb)
    jb.write_text(json.dumps({"run_id": "y", "summary": {"seconds": 2.0}, "label_names": ["floor"]}))
    assert json_digest(ja) != json_digest(jb)


def write(names: list[str]) -> None:
    import tempfile

    store = _stored()
    cases = store.get("cases", {}) if store.get("machine") == machine() else {}
    with tempfile.TemporaryDirectory() as tmp:
        for case in CASES:
            if names and case[0] not in names:
                continue
            for jit in _jits():
                key = f"{case[0]}|{'compiled' if jit else 'numpy'}"
                cases[key] = run_case(case, Path(tmp), jit)
                print(key, cases[key]["cloud"][:12], cases[key]["json"][:12], flush=True)
    STORE.write_text(json.dumps({"machine": machine(), "cases": dict(sorted(cases.items()))}, indent=1) + "\n")


if __name__ == "__main__":
    if sys.argv[1:2] != ["--write"]:
        sys.exit("usage: python tests/test_digests.py --write [CASE ...]")
    sys.path.insert(0, str(ROOT.parent))
    write(sys.argv[2:])
