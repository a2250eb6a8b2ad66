"""The indoor rule base (rules/indoor.yaml) and the examples installed with kbs (issue 14, item 9),
through the real commands."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from test_cli import kbs

ROOT = Path(__file__).resolve().parents[1]


def _room(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A 6 x 4 x 2.6 m room, 1 cm noise: floor 0, ceiling 1, walls 2, a table and a cabinet 3."""
    def plane(n, lo, hi):
        return rng.uniform(lo, hi, (n, 3)) + rng.normal(0, 0.004, (n, 3))
    parts = [(plane(30000, [0, 0, 0], [6, 4, 0]), 0), (plane(20000, [0, 0, 2.6], [6, 4, 2.6]), 1),
             (plane(12000, [0, 0, 0], [6, 0, 2.6]), 2), (plane(12000, [0, 4, 0], [6, 4, 2.6]), 2),
             (plane(8000, [0, 0, 0], [0, 4, 2.6]), 2), (plane(8000, [6, 0, 0], [6, 4, 2.6]), 2),
             (plane(4000, [2, 1.5, 0.75], [3.2, 2.3, 0.75]), 3),  # table top
             (plane(800, [2.05, 1.55, 0], [2.1, 1.6, 0.74]), 3), (plane(800, [3.1, 2.2, 0], [3.15, 2.25, 0.74]), 3),
             (plane(3000, [4.5, 3.4, 0.02], [5.5, 3.4, 1.2]), 3),  # a cabinet's front, 60 cm from the wall
             (plane(1500, [4.5, 3.4, 1.2], [5.5, 3.95, 1.2]), 3)]  # and its top
    X = np.vstack([p for p, _ in parts])
    return X, np.concatenate([np.full(len(p), k) for p, k in parts])


@pytest.mark.slow
def test_indoor_rule_base_labels_a_room_floor_walls_ceiling_furniture(tmp_path):
    X, truth = _room(np.random.default_rng(0))
    np.savetxt(tmp_path / "room.xyz", X, fmt="%.4f")
    r = kbs("run", "--rules", "indoor", str(tmp_path / "room.xyz"), "--out", str(tmp_path / "o"))
    assert r.returncode == 0, r.stderr
    from kbs.io import read_cloud

    names = json.loads((tmp_path / "o" / "room.json").read_text())["label_names"]
    assert names == ["floor", "ceiling", "wall", "furniture"]
    lab = np.asarray(read_cloud(tmp_path / "o" / "room.ply").fields["scalar_label"]).astype(int)
    for k, name in enumerate(names):
        right = float((lab[truth == k] == k).mean())
        assert right > 0.9, (name, right)


@pytest.mark.slow
def test_indoor_rule_base_on_the_bobkov_room_scan(shared_data, tmp_path):
    """Bobkov room1 (real, labelled: 0 = the room's structure, walls mostly; > 0 furniture parts).
    The F1 of structure (floor, wall, ceiling) against GT 0 and of furniture against GT > 0:
    0.688 and 0.804 when the rule base was written, 0.740 and 0.813 since the walls absorb the
    pieces in their planes (session 22; the half x >= 0, not tuned on: 0.412 -> 0.514)
    (docs/BENCHMARKS.md, indoor)."""
    from kbs.io import read_cloud

    scan = shared_data / "bobkov" / "room1_gt_fine.pcd"
    r = kbs("run", "--rules", "indoor", str(scan), "--out", str(tmp_path))
    assert r.returncode == 0, r.stderr
    gt = np.asarray(read_cloud(scan).fields["label"]).astype(int) == 0
    names = json.loads((tmp_path / "room1_gt_fine.json").read_text())["label_names"]
    lab = np.asarray(read_cloud(tmp_path / "room1_gt_fine.ply").fields["scalar_label"]).astype(int)
    pred = np.isin(lab, [names.index(n) for n in ("floor", "wall", "ceiling")])

    def f1(p, g):
        return 2 * (p & g).sum() / (p.sum() + g.sum())

    assert f1(pred, gt) > 0.72 and f1(~pred, ~gt) > 0.80, (f1(pred, gt), f1(~pred, ~gt))
    half = read_cloud(scan).xyz[:, 0] >= 0
    assert f1(pred[half], gt[half]) > 0.49, f1(pred[half], gt[half])  # 0.412 without merge_coplanar's absorb
    wall = lab == names.index("wall")
    assert gt[wall].mean() > 0.89  # what is called wall is structure (0.90; 0.95 before the pieces joined)


@pytest.mark.slow
def test_the_examples_are_installed_listed_and_runnable_without_the_source_tree(tmp_path):
    """A non-editable install (pip install --target, away from the repository): `kbs rules list`
    lists examples/tabletop, examples/poles (with its plugin's installed path), `kbs rules show
    examples/tabletop` prints it, and `kbs run --rules examples/poles --plugin ...` runs."""
    src = tmp_path / "src"
    skip = shutil.ignore_patterns(".venv*", "build", "dist", "__pycache__", ".git", "*.egg-info", "tests", "benchmarks",
                                  "docs")
    shutil.copytree(ROOT, src, ignore=skip)
    target = tmp_path / "site"
    pip = subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--target", str(target),
                          str(src)], capture_output=True, text=True, timeout=600)
    assert pip.returncode == 0, pip.stderr[-3000:]
    env = {**os.environ, "PYTHONPATH": str(target)}
    away = tmp_path / "elsewhere"
    away.mkdir()

    def run(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-c", "import sys; from kbs.cli.main import main; sys.exit(main())",
                               *args], capture_output=True, text=True, cwd=away, env=env, timeout=300)

    where = subprocess.run([sys.executable, "-c", "import kbs; print(kbs.__file__)"], capture_output=True, text=True,
                           cwd=away, env=env)
    assert where.stdout.strip().startswith(str(target)), where.stdout  # the installed copy, not the repository
    r = run("rules", "list")
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert any(x.startswith("indoor ") for x in lines)
    assert any(x.startswith("examples/tabletop ") for x in lines)
    poles = next(x for x in lines if x.startswith("examples/poles "))
    plugin = target / "kbs" / "examples" / "plugins" / "elongation.py"
    assert f"--plugin {plugin}" in poles and plugin.is_file()
    r = run("rules", "show", "examples/tabletop")
    assert r.returncode == 0 and "name: tabletop" in r.stdout
    data = target / "kbs" / "examples" / "data" / "outdoor.ply"
    r = run("run", "--rules", "examples/poles", "--plugin", str(plugin), str(data), "--out", str(away / "o"))
    assert r.returncode == 0, r.stderr
    assert (away / "o" / "outdoor.json").is_file()


def test_the_readme_test_command_is_what_ci_runs_and_runs_the_slow_tests():
    """The README's test command and .ci/run's are one command, and it runs the slow tests on two
    worker processes (pytest-xdist: one per core of CI's machine)."""
    import re

    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8").strip().splitlines()[-1]
    documented = re.search(r'```sh\n(python3 -m venv \.venv && \.venv/bin/pip install "\.\[test\]" && [^\n]+)\n```',
                           readme).group(1)
    assert documented == ci.replace(" --quiet", "") and documented.endswith("pytest --runslow -n 2")
