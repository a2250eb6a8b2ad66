"""Predicate plugins that exit, interrupt or change what they are given: a plugin error (exit 7)
naming the plugin file and line, never a silent exit 0 nor a changed scene; Ctrl-C still stops
the run. Through the real command where a user meets it, and through the library for every kind
of mutation."""
from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np
import pytest

from kbs.knowledge import Cluster, Ground, PredicateError, PredicateRegistry, Scene
from kbs.geometry.groundmodel import LocalGround
from test_cli import EXAMPLE, ROOT, kbs

PLUGIN_HEAD = "import sys\nimport numpy as np\nfrom kbs.knowledge import predicate\n\n"


def _plugin(tmp_path: Path, name: str, body: str, *, needs_ground: bool = True) -> Path:
    """A plugin file declaring one predicate ``name`` (decorator on line 5) whose body is ``body``."""
    path = tmp_path / f"{name}_plugin.py"
    path.write_text(PLUGIN_HEAD + f"@predicate(unit='ratio', needs_ground={needs_ground})\n"
                    f"def {name}(cluster, scene) -> float:\n"
                    f"    \"\"\"A test predicate.\"\"\"\n" + textwrap.indent(textwrap.dedent(body), "    "))
    return path


def _rules(tmp_path: Path, predicate_name: str) -> Path:
    """A rule file measuring ``predicate_name`` on every cluster of the first partition."""
    path = tmp_path / f"{predicate_name}.yaml"
    path.write_text(textwrap.dedent(f"""\
        kbs_rules: 1
        name: plug
        units: m
        strategy: divisive
        scene:
          ground: {{normal: auto, candidate: planar, min_points: 500, fallback: [0, 0, 1]}}
        checks:
          planar: {{predicate: thickness, max: 0.05}}
          level: {{predicate: ground_angle, max: 22.5}}
          custom: {{predicate: {predicate_name}, max: 1}}
        rules:
          - {{name: odd, if: [not custom], then: reject}}
        labels:
          - {{name: ground, if: [planar, level]}}
          - {{name: obstacle}}
        """))
    return path


def _run(tmp_path: Path, plugin: Path, predicate_name: str, *extra: str):
    return kbs("run", "--rules", str(_rules(tmp_path, predicate_name)), str(EXAMPLE), "--plugin", str(plugin),
               "--out", str(tmp_path / "out"), "-j", "1", *extra)


# --- exiting and interrupting ------------------------------------------------------------------------


@pytest.mark.slow
def test_sys_exit_while_the_plugin_is_imported_is_a_plugin_error(tmp_path):
    plugin = tmp_path / "quitter.py"
    plugin.write_text("import sys\n\nsys.exit(0)\n")
    r = kbs("run", "--rules", "outdoor", str(EXAMPLE), "--plugin", str(plugin), "--out", str(tmp_path / "out"))
    assert r.returncode == 7, (r.returncode, r.stdout, r.stderr)
    assert f"{plugin}:3: the plugin called sys.exit(0) while being imported" in r.stderr
    assert "Traceback" not in r.stderr and not (tmp_path / "out").exists()


@pytest.mark.slow
def test_sys_exit_in_a_predicate_is_a_plugin_error_naming_the_file_and_line(tmp_path):
    plugin = _plugin(tmp_path, "quits", "sys.exit(0)\n")
    r = _run(tmp_path, plugin, "quits")
    assert r.returncode == 7, (r.returncode, r.stdout, r.stderr)
    assert f"predicate 'quits' ({plugin}:5) called sys.exit(0) at {plugin}:8 on cluster c0" in r.stderr
    assert "Traceback" not in r.stderr and "wrote" not in r.stdout


@pytest.mark.slow
def test_sys_exit_with_a_code_or_a_message_is_a_plugin_error_too(tmp_path):
    plugin = _plugin(tmp_path, "quits", "sys.exit('giving up')\n")
    r = _run(tmp_path, plugin, "quits")
    assert r.returncode == 7 and "called sys.exit('giving up')" in r.stderr, r.stderr


@pytest.mark.slow
def test_ctrl_c_in_a_predicate_still_stops_the_run(tmp_path):
    plugin = _plugin(tmp_path, "interrupted", "raise KeyboardInterrupt\n")
    r = _run(tmp_path, plugin, "interrupted")
    assert r.returncode == 130 and "kbs: aborted" in r.stderr, (r.returncode, r.stderr)
    assert "plugin" not in r.stderr and "wrote" not in r.stdout


def test_ctrl_c_while_a_plugin_is_imported_still_stops_the_run(tmp_path):
    plugin = tmp_path / "slow.py"
    plugin.write_text("raise KeyboardInterrupt\n")
    r = kbs("predicates", "--plugin", str(plugin))
    assert r.returncode == 130 and "kbs: aborted" in r.stderr, (r.returncode, r.stderr)


# --- the plugin file, not an internal module name ------------------------------------------------------


@pytest.mark.slow
def test_a_failing_predicate_names_its_file_and_the_failing_line(tmp_path):
    plugin = _plugin(tmp_path, "broken", "x = 1.0\nreturn x / 0\n")
    r = _run(tmp_path, plugin, "broken")
    assert r.returncode == 7
    assert (f"predicate 'broken' ({plugin}:5) failed on cluster c0 (19,364 points) at {plugin}:9: "
            "ZeroDivisionError: float division by zero") in r.stderr, r.stderr
    assert "kbs_plugin_" not in r.stderr


def test_a_contract_error_names_the_file_and_line_not_a_module(tmp_path):
    plugin = tmp_path / "nodoc.py"
    plugin.write_text("from kbs.knowledge import predicate\n\n\n@predicate(unit='ratio')\n"
                      "def nodoc(cluster, scene):\n    return 1.0\n")
    r = kbs("predicates", "--plugin", str(plugin))
    assert r.returncode == 7
    assert f"{plugin}: predicate 'nodoc' (line 4): a docstring saying what it measures is required" in r.stderr
    assert "kbs_plugin_" not in r.stderr


def test_a_plugin_failing_to_import_names_the_line(tmp_path):
    plugin = tmp_path / "typo.py"
    plugin.write_text("import numpy as np\n\nX = np.nonexistent_function()\n")
    r = kbs("predicates", "--plugin", str(plugin))
    assert r.returncode == 7
    assert f"{plugin}:3: the plugin failed to import: AttributeError:" in r.stderr, r.stderr


def test_predicates_lists_where_a_plugin_predicate_is_declared():
    path = ROOT / "examples" / "plugins" / "elongation.py"
    r = kbs("predicates", "--plugin", str(path))
    assert r.returncode == 0
    assert f"from {path}:14\n" in r.stdout and f"from {path}:22\n" in r.stdout
    assert "kbs_plugin_" not in r.stdout


@pytest.mark.slow
def test_a_predicate_returning_nan_names_its_file(tmp_path):
    plugin = _plugin(tmp_path, "nan", "return float('nan')\n")
    r = _run(tmp_path, plugin, "nan")
    assert r.returncode == 7
    assert f"predicate 'nan' ({plugin}:5) returned nan for cluster c0, not a number" in r.stderr, r.stderr


@pytest.mark.slow
def test_a_predicate_returning_a_value_outside_its_declared_range_is_a_plugin_error(tmp_path):
    """value_range=(0, 1) declared, 2.5 returned: the rule file's thresholds were checked against the
    declared range when it was loaded, and the run went on judging the value with them (exit 0).
    Now a plugin error naming the predicate, its file and the value (exit 7); a value inside runs."""
    for name, value, code in (("over", 2.5, 7), ("inside", 0.5, 0)):
        plugin = tmp_path / f"{name}_plugin.py"
        plugin.write_text(PLUGIN_HEAD + "@predicate(unit='ratio', value_range=(0.0, 1.0))\n"
                          f"def {name}(cluster, scene) -> float:\n    \"\"\"A test predicate.\"\"\"\n"
                          f"    return {value}\n")
        r = _run(tmp_path, plugin, name, "--force")
        assert r.returncode == code, r.stderr
        if code:
            assert (f"predicate '{name}' ({plugin}:5) returned 2.5 for cluster c0, outside its declared "
                    "value_range [0, 1]") in r.stderr, r.stderr


def test_a_value_range_with_a_nan_bound_or_not_numbers_is_refused_when_declared():
    from kbs.knowledge import predicate

    def p(cluster, scene) -> float:
        """A test predicate."""
        return 0.0

    with pytest.raises(PredicateError, match="NaN bound"):
        predicate(unit="ratio", value_range=(float("nan"), 1.0))(p)
    with pytest.raises(PredicateError, match="value_range must be"):
        predicate(unit="ratio", value_range=("low", 1.0))(p)
    assert predicate(unit="ratio", value_range=(0, None))(p).value_range == (0.0, None)


# --- read-only views -----------------------------------------------------------------------------------


@pytest.mark.slow
def test_a_predicate_changing_the_ground_normal_is_a_plugin_error_and_labels_do_not_move(tmp_path):
    plugin = _plugin(tmp_path, "tilt", "scene.ground.normal[:] = [1.0, 0.0, 0.0]\nreturn 0.0\n")
    r = _run(tmp_path, plugin, "tilt")
    assert r.returncode == 7, (r.returncode, r.stdout, r.stderr)
    assert f"predicate 'tilt' ({plugin}:5) failed on cluster c0 (19,364 points) at {plugin}:8: ValueError: " \
           "assignment destination is read-only" in r.stderr, r.stderr
    assert "must not change the cluster or the scene" in r.stderr
    assert "wrote" not in r.stdout


MUTATIONS = {
    "ground normal": "scene.ground.normal[0] = 1.0",
    "ground point": "scene.ground.point += 1.0",
    "sensor": "scene.sensor[:] = 0.0",
    "scene attribute": "setattr(scene, 'ground', None)",
    "points": "cluster.X[0, 0] = 1e9",
    "points in place": "cluster.X -= cluster.geometry.center",
    "weights": "cluster.weights[:] = 0.0",
    "cluster attribute": "cluster.X = cluster.X * 2",
    "eigenvalues": "cluster.geometry.eigenvalues.sort()",
    "eigenvectors": "cluster.geometry.eigenvectors[:, 0] = 0.0",
    "centre": "cluster.geometry.center[2] = 0.0",
    "covariance": "cluster.geometry.covariance[:] = 0.0",
    "local ground heights": "scene.ground_model.heights[:] = 0.0",
    "local ground attribute": "scene.ground_model.radius = 100.0",
}


@pytest.mark.parametrize("what", list(MUTATIONS))
def test_every_mutation_of_what_a_predicate_sees_is_a_plugin_error(tmp_path, what):
    reg = PredicateRegistry.default(entry_points_too=False)
    plugin = _plugin(tmp_path, "meddler", f"{MUTATIONS[what]}\nreturn 0.0\n")
    reg.add_plugin_file(plugin)
    rng = np.random.default_rng(0)
    X = np.column_stack([rng.uniform(-5, 5, 400), rng.uniform(-5, 5, 400), rng.normal(0, 0.01, 400)])
    X_before = X.copy()
    ground = Ground(np.array([0.0, 0.0, 1.0]), np.zeros(3), "fixed")
    model = LocalGround.build(X, np.arange(400), ground.normal, ground.point, neighbours=8, radius=3.0)
    heights = model.heights.copy()
    sensor = np.array([0.0, 0.0, 1.5])
    scene = Scene(sensor, ground, "m", ground_model=model)
    cluster = Cluster("c3", X, np.ones(400))
    geometry = cluster.geometry
    snapshot = [a.copy() for a in (geometry.center, geometry.covariance, geometry.eigenvalues, geometry.eigenvectors)]
    with pytest.raises(PredicateError) as info:
        reg.get("meddler").measure(cluster, scene, {})
    message = str(info.value)
    assert message.startswith(f"predicate 'meddler' ({plugin}:5) failed on cluster c3 (400 points) at {plugin}:8: ")
    assert "must not change the cluster or the scene" in message
    # nothing changed: not the caller's arrays, not the scene, not the cached geometry
    np.testing.assert_array_equal(X, X_before)
    np.testing.assert_array_equal(cluster.X, X_before)
    np.testing.assert_array_equal(sensor, [0.0, 0.0, 1.5])
    np.testing.assert_array_equal(scene.sensor, [0.0, 0.0, 1.5])
    np.testing.assert_array_equal(scene.ground.normal, [0.0, 0.0, 1.0])
    np.testing.assert_array_equal(scene.ground.point, np.zeros(3))
    np.testing.assert_array_equal(model.heights, heights)
    assert model.radius == 3.0 and scene.ground is ground
    for a, b in zip(snapshot, (geometry.center, geometry.covariance, geometry.eigenvalues, geometry.eigenvectors)):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(cluster.weights, np.ones(400))


def test_a_predicate_that_only_reads_still_works_and_the_caller_keeps_writable_arrays(tmp_path):
    reg = PredicateRegistry.default(entry_points_too=False)
    reg.add_plugin_file(_plugin(tmp_path, "reader", "P = cluster.X - cluster.geometry.center\n"
                                "return float(np.abs(P @ scene.ground.normal).max() + 0 * scene.sensor.sum())\n"))
    X = np.array([[0.0, 0, 0], [1, 0, 0.5], [0, 1, 0], [1, 1, -0.5]])
    sensor = np.zeros(3)
    cluster = Cluster("c0", X, np.ones(4))
    scene = Scene(sensor, Ground(np.array([0, 0, 1.0]), np.zeros(3), "fixed"), "m")
    assert reg.get("reader").measure(cluster, scene, {}).value == pytest.approx(0.5)
    assert X.flags.writeable and sensor.flags.writeable  # the read-only views are views, not the caller's arrays


@pytest.mark.slow
def test_a_plugin_raising_a_kbs_error_is_still_named(tmp_path):
    plugin = _plugin(tmp_path, "picky", "from kbs.errors import FitError\nraise FitError('too few points for me')\n")
    r = _run(tmp_path, plugin, "picky")
    assert r.returncode == 7
    assert f"predicate 'picky' ({plugin}:5) failed on cluster c0 (19,364 points) at {plugin}:9: FitError: " \
           "too few points for me" in r.stderr, r.stderr


@pytest.mark.slow
def test_a_relative_plugin_path_is_named_as_given(tmp_path):
    (tmp_path / "plugins").mkdir()
    (tmp_path / "plugins" / "nodoc.py").write_text("from kbs.knowledge import predicate\n\n\n@predicate(unit='ratio')\n"
                                                   "def nodoc(cluster, scene):\n    return 1.0\n")
    r = kbs("predicates", "--plugin", "plugins/nodoc.py", cwd=tmp_path)
    assert r.returncode == 7
    assert r.stderr.startswith("kbs: error: plugins/nodoc.py: predicate 'nodoc' (line 4): a docstring"), r.stderr
    assert str(tmp_path) not in r.stderr
    _plugin(tmp_path, "broken", "return 1 / 0\n")
    r = kbs("run", "--rules", str(_rules(tmp_path, "broken")), str(EXAMPLE), "--plugin", "broken_plugin.py",
            "--out", "out", "-j", "1", cwd=tmp_path)
    assert r.returncode == 7
    assert "predicate 'broken' (broken_plugin.py:5) failed on cluster c0 (19,364 points) at broken_plugin.py:8: " \
           "ZeroDivisionError" in r.stderr, r.stderr


def test_a_cluster_s_view_is_made_once_and_not_sent_to_workers():
    """Predicates share one read-only view of a cluster; a cluster sent to a worker process
    (pickled) leaves it behind and makes its own there."""
    import pickle

    rng = np.random.default_rng(0)
    cl = Cluster("c0", rng.normal(size=(50, 3)), np.ones(50))
    seen = cl.view()
    assert cl.view() is seen and not seen.X.flags.writeable
    back = pickle.loads(pickle.dumps(cl))
    assert "_view" not in back.__dict__
    assert np.array_equal(back.view().X, cl.X) and not back.view().X.flags.writeable
