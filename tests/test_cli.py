"""End-to-end tests of the ``kbs`` command, run as a real subprocess."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from plyfile import PlyData

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "data" / "outdoor.ply"


def kbs(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    exe = shutil.which("kbs", path=str(Path(sys.executable).parent)) or shutil.which("kbs")
    assert exe, "the kbs command is not installed"
    env = {k: v for k, v in os.environ.items() if k != "COLUMNS"}
    return subprocess.run([exe, *args], capture_output=True, text=True, cwd=cwd, env=env, timeout=300)


def test_version_and_help():
    r = kbs("--version")
    assert r.returncode == 0 and "kbs" in r.stdout
    r = kbs("cluster", "--help")
    assert r.returncode == 0 and "--k-max" in r.stdout


@pytest.mark.slow
def test_cluster_bundled_example_writes_cluster_and_membership(tmp_path):
    out = tmp_path / "clustered.ply"
    r = kbs("cluster", str(EXAMPLE), "--k-max", "6", "--out", str(out))
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    table = [ln for ln in lines if ln[:4].strip().rstrip("*").isdigit()]
    assert [int(ln[:4].strip().rstrip("*")) for ln in table] == list(range(1, len(table) + 1))
    assert sum("*" in ln[:4] for ln in table) == 1
    assert "chosen K =" in r.stdout
    v = PlyData.read(str(out))["vertex"]
    names = [p.name for p in v.properties]
    assert {"x", "y", "z", "scalar_cluster", "scalar_membership", "label"} <= set(names)  # the input's label is kept
    assert v["scalar_cluster"].dtype == np.int32
    chosen = int(r.stdout.split("chosen K = ")[1].split()[0])
    assert set(np.unique(v["scalar_cluster"])) <= set(range(chosen))
    assert ((v["scalar_membership"] >= 1.0 / chosen - 1e-6) & (v["scalar_membership"] <= 1.0)).all()


@pytest.mark.slow  # whole real scans / a browser: pytest --runslow (CI) runs it
@pytest.mark.parametrize("scan", ["semantickitti/000001.points.npy", "isprs/samp11.txt"])
def test_cluster_runs_on_real_scans(shared_data, scan):
    r = kbs("cluster", str(shared_data / scan))
    assert r.returncode == 0, r.stderr
    assert "chosen K =" in r.stdout
    assert sum(1 for ln in r.stdout.splitlines() if ln[:4].strip().rstrip("*").isdigit()) == 10


def _bad_inputs(tmp: Path) -> dict[str, tuple[Path, str]]:
    (tmp / "adir.ply").mkdir()
    text = tmp / "letters.xyz"
    text.write_text("1 2 3\n4 5 6\nfoo bar baz\n")
    good = tmp / "good.ply"
    from kbs.io import write_ply

    write_ply(good, np.random.default_rng(0).normal(size=(500, 3)))
    trunc = tmp / "truncated.ply"
    trunc.write_bytes(good.read_bytes()[: len(good.read_bytes()) // 2])
    unknown = tmp / "scan.foo"
    unknown.write_text("1 2 3\n")
    nan = tmp / "nan.npy"
    np.save(nan, np.full((10, 3), np.nan))
    return {
        "directory": (tmp / "adir.ply", "directory"),
        "letters": (text, "line 3"),
        "truncated": (trunc, ""),
        "unknown extension": (unknown, ".foo"),
        "missing": (tmp / "nope.pcd", ""),
        "all NaN": (nan, "NaN"),
    }


@pytest.mark.parametrize("case", ["directory", "letters", "truncated", "unknown extension", "missing", "all NaN"])
def test_bad_input_is_one_line_with_file_and_exit_code_3(tmp_path, case):
    path, needle = _bad_inputs(tmp_path)[case]
    r = kbs("cluster", str(path))
    assert r.returncode == 3, (r.returncode, r.stderr)
    err = r.stderr.strip().splitlines()
    assert len(err) == 1, r.stderr
    assert err[0].startswith("kbs: error: ") and path.name in err[0] and needle in err[0]
    assert "Traceback" not in r.stderr


def test_bad_option_is_a_usage_error():
    r = kbs("cluster", str(EXAMPLE), "--k-max", "0")
    assert r.returncode == 2
    assert "Traceback" not in r.stderr


def test_unwritable_output_is_a_clean_error(tmp_path):
    r = kbs("cluster", str(EXAMPLE), "--k-max", "2", "--out", str(tmp_path / "no" / "such" / "dir" / "o.ply"))
    assert r.returncode == 3 and "cannot write" in r.stderr and "Traceback" not in r.stderr


@pytest.mark.slow  # kbs subprocesses: pytest --runslow (CI) runs it
def test_commands_that_do_not_segment_load_neither_numba_nor_scipy(tmp_path):
    """`kbs explain`, `kbs rules show` and `kbs predicates` read and print: they do not pay for
    the compiled kernels (numba) or the k-d trees (scipy), which only a segmentation loads (issue
    9: start-up). Before, importing kbs.knowledge loaded both (connexity, ground direction)."""
    assert kbs("-q", "run", "--rules", "outdoor", str(EXAMPLE), "--out", str(tmp_path / "o")).returncode == 0
    code = ("import sys, io, contextlib; from kbs.cli.main import main\n"
            "with contextlib.redirect_stdout(io.StringIO()):\n    code = main(sys.argv[1:])\n"
            "print(sorted(m for m in ('numba', 'scipy', 'sklearn') if m in sys.modules)); sys.exit(code)")
    for args in (["explain", str(tmp_path / "o" / "outdoor.json")], ["rules", "show", "outdoor"], ["predicates"]):
        r = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, r.stderr
        assert r.stdout.strip().splitlines()[-1] == "[]", (args, r.stdout)
    # and a segmentation still loads them when it needs them
    code = ("import sys; import numpy as np, kbs; kbs.Segmenter('outdoor').segment(np.random.default_rng(0)"
            ".normal(size=(3000, 3)) * [5, 5, 0.05]); print(sorted(m for m in ('numba', 'scipy') if m in sys.modules))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "'scipy'" in r.stdout.strip().splitlines()[-1]  # numba too when the compiled kernels are on


def test_the_command_ends_without_the_teardown_but_as_sys_exit_would():
    """The console script (cli.main:entry) ends the process with os._exit once main() returned
    (issue 9: Python's teardown of numba's and scipy's objects took 0.4-0.6 s after a run): its
    exit code, everything written to stdout and stderr, the exit handlers run; with a thread that
    is not a daemon still running, it waits for it (sys.exit)."""
    import importlib.metadata

    scripts = importlib.metadata.distribution("kbs").entry_points.select(group="console_scripts")
    assert [ep.value for ep in scripts if ep.name == "kbs"] == ["kbs.cli.main:entry"]
    code = ("import atexit, sys, threading, time; from kbs.cli.main import entry\n"
            "atexit.register(lambda: print('handler ran'))\n"
            "if sys.argv[1] == 'thread':\n"
            "    threading.Thread(target=lambda: (time.sleep(0.3), print('thread done'))).start()\n"
            "sys.argv = ['kbs', *sys.argv[2:]]; entry(); print('not reached')")
    runs = {"plain": ["predicates"], "thread": ["predicates"], "error": ["rules", "show", "no_such_rule_base"]}
    for name, args in runs.items():
        r = subprocess.run([sys.executable, "-c", code, name, *args], capture_output=True, text=True, timeout=120)
        assert "not reached" not in r.stdout and "Traceback" not in r.stderr, (name, r.stderr)
        if name == "error":
            assert r.returncode == 4 and "no_such_rule_base" in r.stderr, (r.returncode, r.stderr)
        else:  # the whole table, then the handler (after the thread, which Python waits for)
            assert r.returncode == 0, r.stderr
            assert "point_count" in r.stdout and r.stdout.rstrip().endswith("handler ran"), (name, r.stdout[-300:])
            assert ("thread done" in r.stdout) == (name == "thread")
    r = kbs("--version")  # the installed script itself
    assert r.returncode == 0 and "kbs, version" in r.stdout


def test_help_lists_the_commands_without_importing_them():
    """`kbs --help` writes the commands' table from cli.main.SHORT_HELP: the same text click writes
    from the commands' own docstrings (at any width), without importing the commands' modules."""
    import click
    from click.testing import CliRunner

    from kbs.cli.main import COMMANDS, SHORT_HELP, cli

    ctx = click.Context(cli)
    assert list(SHORT_HELP) == list(COMMANDS)
    for name in COMMANDS:
        cmd = cli.get_command(ctx, name)
        for limit in (30, 45, 60, 120, 400):
            assert click.Command(name, help=SHORT_HELP[name]).get_short_help_str(limit) == \
                cmd.get_short_help_str(limit), (name, limit)
    # the table as click's own Group writes it from the imported commands
    class Imported(click.Group):  # click's own table, in kbs's order
        def list_commands(self, ctx):
            return list(COMMANDS)

    group = Imported("kbs", commands={name: cli.get_command(ctx, name) for name in COMMANDS})
    for width in (60, 80, 120):
        expected = click.HelpFormatter(width=width)
        group.format_commands(ctx, expected)
        got = click.HelpFormatter(width=width)
        cli.format_commands(ctx, got)
        assert got.getvalue() == expected.getvalue()
    assert "run " in CliRunner().invoke(cli, ["--help"]).output
    code = ("import sys; from kbs.cli.main import main; sys.argv = ['kbs', '--help']\n"
            "try:\n    main()\nexcept SystemExit:\n    pass\n"
            "print(sorted(m for m in sys.modules if m.startswith('kbs.cli.') or m in ('scipy', 'numba')))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip().splitlines()[-1] == "['kbs.cli.main']", r.stdout


@pytest.mark.parametrize("fault", ["bug", "bug shown", "out of memory"])
def test_a_bug_is_one_line_naming_its_report_not_a_traceback(tmp_path, fault):
    """A bug in kbs (an exception no part of kbs raised on purpose) ends `kbs run` with exit code 1,
    one line saying it is a bug and one naming the file its traceback was written to, not a
    traceback; KBS_TRACEBACK=1 prints it. Running out of memory is exit code 8, one line saying
    what to do. The fault is put into the real command, run as the console script runs it."""
    exc = "MemoryError()" if fault == "out of memory" else "IndexError('index 7 is out of bounds for axis 0')"
    code = ("import sys, kbs.knowledge.segmenter as s\n"
            f"def boom(self, *a, **k):\n    raise {exc}\n"
            "s.Segmenter.segment = boom\n"
            "from kbs.cli.main import entry; sys.argv = ['kbs', *sys.argv[1:]]; entry()")
    env = {k: v for k, v in os.environ.items() if k != "KBS_TRACEBACK"}
    env["TMPDIR"] = str(tmp_path)
    if fault == "bug shown":
        env["KBS_TRACEBACK"] = "1"
    out = tmp_path / "o"
    r = subprocess.run([sys.executable, "-c", code, "run", "--rules", "outdoor", str(EXAMPLE), "--out", str(out)],
                       capture_output=True, text=True, timeout=300, env=env)
    lines = [line for line in r.stderr.splitlines() if not line.startswith("kbs: run ")]
    reports = sorted(tmp_path.glob("kbs-internal-error-*.txt"))
    assert not list(out.glob("outdoor.*")), "a failed run wrote a result"
    if fault == "out of memory":
        assert r.returncode == 8, r.stderr
        assert lines[-1].startswith("kbs: error: out of memory") and "--tile" in lines[-1], r.stderr
        assert "Traceback" not in r.stderr and not reports
        return
    assert r.returncode == 1, r.stderr
    assert len(reports) == 1, r.stderr
    report = reports[0].read_text()
    assert "Traceback" in report and "IndexError: index 7 is out of bounds" in report and "in boom" in report
    assert "command: kbs run --rules outdoor" in report
    said = [line for line in lines if line.startswith("kbs: internal error")]
    assert said == ["kbs: internal error (a bug in kbs, not in the input): IndexError: index 7 is out of bounds for axis 0"]
    assert lines[-1] == f"kbs: the traceback is in {reports[0]}: please report it with the command line " \
                        "(KBS_TRACEBACK=1 prints it here)", r.stderr
    assert ("Traceback" in r.stderr) == (fault == "bug shown"), r.stderr


@pytest.mark.parametrize("tiled", [False, True])
def test_ctrl_c_inside_a_compiled_kernel_is_an_abort_not_a_failure(tmp_path, tiled):
    """A Ctrl-C that arrives while a compiled kernel runs comes out of the kernel's call as a
    SystemError caused by the KeyboardInterrupt (numba's dispatcher: "returned a result with an
    exception set"). Put into the ground surface's k-NN, which a predicate calls, it was reported
    as that predicate's failure (exit 7), and a tiled run went on to its other tiles; now it is
    the command's abort, exit code 130, and nothing is written."""
    code = ("import sys, kbs.geometry.groundmodel as g\n"
            "def knn(self, *a, **k):\n"
            "    try:\n        raise KeyboardInterrupt\n"
            "    except KeyboardInterrupt as exc:\n"
            "        raise SystemError('CPUDispatcher(<function grid_knn>) returned a result with an exception set') from exc\n"
            "g.LocalGround._knn = knn\n"
            "from kbs.cli.main import entry; sys.argv = ['kbs', *sys.argv[1:]]; entry()")
    out = tmp_path / "o"
    args = ["run", "--rules", "outdoor", "-j", "1", str(EXAMPLE), "--out", str(out)]
    if tiled:
        args[5:5] = ["--tile", "6"]
    r = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=300)
    assert r.returncode == 130, r.stderr
    assert r.stderr.strip().splitlines()[-1].startswith("kbs: aborted"), r.stderr
    assert "Traceback" not in r.stderr and "failed" not in r.stderr and "internal error" not in r.stderr
    assert not list(out.glob("outdoor.*")), "an aborted run wrote a result"


def test_sigterm_stops_the_command_as_ctrl_c_does_with_exit_code_143(tmp_path):
    """`kill PID` (a batch scheduler's notice) while `kbs run` segments: one line, exit code 143
    (128 + SIGTERM), nothing written, as Ctrl-C; before, the process died at once (-15) and a
    tiled run on Dask left multiprocessing's warning of leaked semaphores."""
    import signal
    import time

    started = tmp_path / "started"
    code = ("import sys, time, pathlib, kbs.knowledge.segmenter as s\n"
            "def slow(self, *a, **k):\n"
            f"    pathlib.Path({str(started)!r}).write_text('')\n"
            "    time.sleep(120)\n"
            "s.Segmenter.segment = slow\n"
            "from kbs.cli.main import entry; sys.argv = ['kbs', *sys.argv[1:]]; entry()")
    out = tmp_path / "o"
    p = subprocess.Popen([sys.executable, "-c", code, "run", "--rules", "outdoor", str(EXAMPLE), "--out", str(out)],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    t0 = time.monotonic()
    while not started.exists() and p.poll() is None and time.monotonic() - t0 < 120:
        time.sleep(0.02)
    assert p.poll() is None, p.communicate()[1]
    p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=60)
    assert p.returncode == 143, (p.returncode, err)
    assert err.strip().splitlines()[-1] == "kbs: terminated (SIGTERM)", err
    assert "Traceback" not in err
    assert not list(out.glob("outdoor.*"))


@pytest.mark.parametrize("args, option", [
    (["synth", "outdoor", "--noise", "inf"], "--noise"),
    (["synth", "outdoor", "--sensor-height", "inf"], "--sensor-height"),
    (["run", "--rules", "outdoor", "--tile", "inf", str(EXAMPLE)], "--tile"),
    (["run", "--rules", "outdoor", "--tile", "5", "--buffer", "nan", str(EXAMPLE)], "--buffer"),
    (["tune", "--rules", "outdoor", "--time-limit", "nan", str(EXAMPLE), "field:label"], "--time-limit"),
])
def test_an_option_that_is_not_a_finite_number_is_a_usage_error(tmp_path, args, option):
    """NaN passes every comparison of a range and inf an open upper end: `kbs synth outdoor --noise
    inf` wrote a scene of 149,132 points with exit code 0, `--sensor-height inf` one of 0 points,
    `kbs tune --time-limit nan` ran with no limit. Each is now a usage error naming the option."""
    r = kbs(*args, "--out", str(tmp_path / "out.ply" if args[0] == "synth" else tmp_path / ("t.yaml" if args[0] == "tune" else "o")))
    assert r.returncode == 2, (r.returncode, r.stderr)
    assert f"Invalid value for '{option}'" in r.stderr and "is not a finite number" in r.stderr, r.stderr
    assert not list(tmp_path.iterdir())


def test_a_sensor_beyond_the_coordinates_the_engine_takes_is_refused(tmp_path):
    """A sensor at 1e300 (beyond the +-1e50 the points may have) overflowed the distances to it
    (numpy warnings, "inf m from the sensor") and the run went on: now a usage error (--sensor), a
    positioned rule file problem (scene.sensor) or a ParameterError (Segmenter)."""
    import kbs as kbs_lib
    from kbs.errors import ParameterError

    r = kbs("run", "--rules", "outdoor", "--sensor", "1e300,0,0", str(EXAMPLE), "--out", str(tmp_path / "o"))
    assert r.returncode == 2 and "expected X,Y,Z (three finite numbers, each within +-1e+50)" in r.stderr, r.stderr
    rules = (ROOT / "rules" / "outdoor.yaml").read_text()
    line = next(k for k, text in enumerate(rules.splitlines(), 1) if text.startswith("  sensor:"))
    bad = tmp_path / "far_sensor.yaml"
    bad.write_text(rules.replace("  sensor: [0, 0, 0]", "  sensor: [1.0e+300, 0, 0]", 1))
    r = kbs("run", "--rules", str(bad), str(EXAMPLE), "--out", str(tmp_path / "o"))
    assert r.returncode == 4, r.stderr
    assert f"far_sensor.yaml:{line}:12: scene.sensor[0]: 1e+300 is greater than the maximum of 1e+50" in r.stderr
    assert not (tmp_path / "o").exists()
    with pytest.raises(ParameterError, match=r"within \+-1e\+50"):
        kbs_lib.Segmenter("outdoor", sensor=[0.0, -1e300, 0.0])


def test_a_tune_mark_of_a_billion_steps_is_a_rule_file_problem_not_a_grid_built(tmp_path):
    """`tune: {min, max, steps: 1000000000}`: the schema reported steps > 101, but the loader built
    the grid of values first (24 GB, killed; 50 million steps still running at 60 s). Now the
    rule file is refused at once, positioned."""
    text = (ROOT / "examples" / "rules" / "outdoor-tune.yaml").read_text()
    bad = tmp_path / "steps.yaml"
    bad.write_text(text.replace("tune: [0.04, 0.05, 0.07]", "tune: {min: 0.01, max: 0.1, steps: 1000000000}", 1))
    r = kbs("rules", "check", str(bad))
    assert r.returncode == 4, r.stderr
    line = next(k for k, t in enumerate(bad.read_text().splitlines(), 1) if "steps: 1000000000" in t)
    assert f"steps.yaml:{line}:40: checks.planar.tune.steps: 1000000000 is greater than the maximum of 101" in r.stderr, \
        r.stderr


def test_tune_marks_whose_settings_multiply_past_the_cap_are_refused_before_any_scan_is_read(tmp_path):
    """Four marks of 101 steps each make 10^8 settings: kbs tune built the list of every setting (and
    a score matrix) before its first segmentation and ran out of memory, --max-evals 2 or not.
    Now the rule file is refused, positioned at the mark that passes the cap, and `kbs run` of the
    same file too (the marks are part of the file)."""
    import re

    from kbs.knowledge.rulebase import TUNE_MAX_SETTINGS

    text = (ROOT / "examples" / "rules" / "outdoor-tune.yaml").read_text()
    marks = re.findall(r"tune: \[[^\]]*\]", text)
    assert len(marks) == 4
    ranges = iter(["{min: 0.03, max: 0.08, steps: 101}", "{min: 0.1, max: 0.4, steps: 101}",
                   "{min: 0.05, max: 0.2, steps: 101}", "{min: 0.02, max: 0.09, steps: 101}"])
    big = tmp_path / "big.yaml"
    big.write_text(re.sub(r"tune: \[[^\]]*\]", lambda m: "tune: " + next(ranges), text))
    third = [k for k, t in enumerate(big.read_text().splitlines(), 1) if "steps: 101" in t][2]
    scans = []
    for name in ("a", "b"):  # never read: the file is refused first
        scans += [str(tmp_path / f"{name}.npy"), str(tmp_path / f"{name}.labels.npy")]
    r = kbs("tune", "--rules", str(big), *scans, "--max-evals", "2", "--out", str(tmp_path / "t.yaml"))
    assert r.returncode == 4, r.stderr
    assert re.search(rf"big.yaml:{third}:\d+: the tune marks make 106,131,204 settings together "
                     rf"\(101 x 101 x 102 x 102 values\); kbs tune tries at most {TUNE_MAX_SETTINGS:,}", r.stderr), r.stderr
    assert not (tmp_path / "t.yaml").exists()
    # two of the marks (10^4 settings) are a grid kbs tune takes
    two = big.read_text()
    for mark in ("tune: {min: 0.05, max: 0.2, steps: 101}", "tune: {min: 0.02, max: 0.09, steps: 101}"):
        two = two.replace(mark, "")
    assert two.count("steps: 101") == 2
    (tmp_path / "two.yaml").write_text(two)
    assert kbs("rules", "check", str(tmp_path / "two.yaml")).returncode == 0
