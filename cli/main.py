"""Entry point of the ``kbs`` command.

Data goes to stdout, progress and diagnostics to stderr. Errors a user can cause print one line
``kbs: error: ...`` and exit with the code of :class:`kbs.errors.ExitCode`; click's own usage
errors exit with 2. Anything else is a bug: one line says so and names the file its traceback
was written to (``KBS_TRACEBACK=1`` prints it), exit code 1. Ctrl-C is exit code 130 and SIGTERM
143, wherever they arrive (inside a compiled kernel too).
"""
from __future__ import annotations

import atexit
import contextlib
import errno
import importlib
import logging
import os
import signal
import sys
import threading

import click

from kbs.errors import ExitCode, KbsError, Terminated, exception_chain, interrupted

#: command name -> "module:attribute". Commands are imported when used (click's lazy-group
#: pattern), so `kbs run` does not pay for the imports of `kbs eval` or `kbs synth`.
COMMANDS = {
    "run": "kbs.cli.run:run",
    "map": "kbs.cli.map:map_",
    "explain": "kbs.cli.run:explain",
    "rules": "kbs.cli.run:rules",
    "predicates": "kbs.cli.run:predicates",
    "eval": "kbs.cli.eval:eval_",
    "tune": "kbs.cli.tune:tune_",
    "cluster": "kbs.cli.cluster:cluster",
    "synth": "kbs.cli.synth:synth",
    "segcomp": "kbs.cli.segcomp:segcomp",
    "render": "kbs.cli.render:render",
    "warmup": "kbs.cli.warmup:warmup",
}


#: each command's first help paragraph, for `kbs --help` without importing every command (a test
#: keeps it equal to the commands' own docstrings)
SHORT_HELP = {
    "run": (
        'Segment each CLOUD with a rule base; write DIR/<stem>.ply (per-vertex scalar_cluster, '
        'scalar_label, scalar_membership) or, with --out-format las|laz (the default for LAS/LAZ input), '
        'DIR/<stem>.las|.laz (ASPRS classification, cluster, label, membership), and DIR/<stem>.json '
        '(label names, clusters, the explanation tree).'
    ),
    "map": (
        'Segment every frame of a drive (SCANS: scan files and folders of scans in name order, without '
        'the files that are not scans: poses.txt and other poses files, calib.txt, labels; one KITTI '
        'sequence folder holding velodyne/*.bin and poses.txt, or one ROS 1/2 bag) with one rule base, '
        'bring each into the world frame with its pose and fuse them into DIR/: an obstacle grid in log-'
        'odds (map.tif, map.npy, map.png), the obstacles tracked across frames with a mesh each '
        '(objects/), a fused labelled cloud (cloud.ply) and an index of frames, objects and cells '
        '(map.json); with --report, the map view (map.html).'
    ),
    "explain": (
        'Print what a `kbs run` RESULT.json did, grouped (rules, labels by outcome, checks with their '
        'docs), then its explanation tree; or why one cluster ended as it did (--cluster). Deeper parts '
        'of a large tree are folded into counts: --depth and --cluster unfold them.'
    ),
    "rules": (
        'Check, show and list rule bases.'
    ),
    "predicates": (
        'List every predicate a rule file may use, with unit, parameters and doc.'
    ),
    "eval": (
        'Compare a `kbs run` RESULT (.ply) with GROUND_TRUTH: a label file (.npy, a SemanticKITTI .label,'
        ' or text with one integer per line) or field:NAME, a field of RESULT (e.g. field:label_in, the '
        "input's own 'label')."
    ),
    "tune": (
        "Fit the thresholds marked 'tune:' in a rule file to labelled scans, SCAN GT pairs (GT as in kbs "
        'eval: a label file .npy / .label / text, or field:NAME of the scan), and write NEW.yaml.'
    ),
    "cluster": (
        "Run UFP-ONC on CLOUD and print the per-K table; the K chosen (APD's first local maximum) is "
        "marked '*'."
    ),
    "synth": (
        'Generate a labelled synthetic scene (sensor frame: origin at the sensor, z up).'
    ),
    "segcomp": (
        'Write the SegComp machine segmentation of a `kbs run` RESULT.ply on a range image.'
    ),
    "render": (
        'Draw figures of a `kbs run` RESULT.json (its points are read from the sibling RESULT.ply; the '
        "two must be the same run's)."
    ),
    "warmup": (
        "Compile and cache the engine's compiled kernels (numba) now, rather than in the background after"
        ' the first run: for images, robots and CI that want every run at full speed from the start. '
        'Takes 20-30 s once per install; later runs load the cached code.'
    ),
}


class LazyGroup(click.Group):
    def list_commands(self, ctx: click.Context) -> list[str]:
        return list(COMMANDS)

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        if name not in COMMANDS:
            return None
        module, attr = COMMANDS[name].split(":")
        return getattr(importlib.import_module(module), attr)

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        """The commands' table of `kbs --help` from :data:`SHORT_HELP`, as click would write it
        from the commands themselves, without importing them (about 0.5 s of imports)."""
        limit = formatter.width - 6 - max(len(name) for name in COMMANDS)
        rows = [(name, click.Command(name, help=SHORT_HELP[name]).get_short_help_str(limit)) for name in COMMANDS]
        with formatter.section("Commands"):
            formatter.write_dl(rows)


def _print_version(ctx: click.Context, param: click.Parameter, value: bool) -> None:
    """--version, as click.version_option writes it, with the version read only when asked
    (kbs.__version__: package metadata)."""
    if not value or ctx.resilient_parsing:
        return
    from kbs import __version__

    click.echo(f"kbs, version {__version__}")
    ctx.exit()


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--version", is_flag=True, expose_value=False, is_eager=True, callback=_print_version,
              help="Show the version and exit.")
@click.option("-q", "--quiet", is_flag=True,
              help="Only errors on stderr (no progress, no notes); `kbs run` prints no summary either.")
@click.pass_context
def cli(ctx: click.Context, quiet: bool) -> None:
    """kbs: knowledge-based partitioning of unorganised 3D point clouds.

    Main command: kbs run --rules outdoor SCAN; a drive: kbs map --rules outdoor SCANS... --poses FILE.

    Exit codes: 0 ok, 1 internal error (a bug), 2 bad usage or option, 3 unreadable or empty
    input file, 4 invalid rule file, 5 the engine could not fit the data, 6 invalid parameter,
    7 a predicate plugin broke the contract or failed, 8 out of memory, 130 Ctrl-C, 143 SIGTERM.
    """
    ctx.ensure_object(dict)
    ctx.obj["quiet"] = quiet
    logging.basicConfig(level=logging.WARNING if quiet else logging.INFO, format="kbs: %(message)s",
                        stream=sys.stderr)




def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns (and exits with) the exit code."""
    try:
        # without standalone mode, click returns the code of an Exit (raised by --help, --version,
        # or a command that chooses its exit code) instead of raising it
        code = cli.main(args=argv, prog_name="kbs", standalone_mode=False)
    except click.exceptions.Exit as exc:  # --help, --version
        return int(exc.exit_code)
    except click.ClickException as exc:
        exc.show()
        return int(ExitCode.USAGE if isinstance(exc, click.UsageError) else exc.exit_code)
    except (click.exceptions.Abort, KeyboardInterrupt) as exc:  # Ctrl-C (click turns it into Abort)
        return _aborted(exc)
    except KbsError as exc:
        click.echo(f"kbs: error: {exc}", err=True)
        return int(exc.exit_code)
    except BrokenPipeError:
        return 0
    except MemoryError:
        click.echo("kbs: error: out of memory: segment the cloud in tiles (kbs run --tile SIZE, or the rule "
                   "base's limits.tile), with fewer jobs (-j), or on a machine with more memory", err=True)
        return int(ExitCode.MEMORY)
    except OSError as exc:
        if exc.errno in _PATH_ERRNOS:  # a path the system refuses, wherever a command met it: the input's fault
            name = exc.filename if exc.filename is not None else "a path"
            click.echo(f"kbs: error: {name}: {exc.strerror}", err=True)
            return int(ExitCode.CLOUD)
        if interrupted(exc):
            return _aborted(exc)
        return _internal_error(exc, argv)
    except Exception as exc:  # noqa: BLE001 - a bug in kbs, not the user's input: said as such, not a traceback
        if interrupted(exc):  # Ctrl-C inside a compiled kernel comes out as a SystemError caused by it
            return _aborted(exc)
        return _internal_error(exc, argv)
    return code if isinstance(code, int) else 0


def _aborted(exc: BaseException) -> int:
    """Ctrl-C (exit code 130) or SIGTERM (143): one line, with what the interrupted work left for a
    next run (the notes added to the KeyboardInterrupt on its way up: a tiled run's finished tiles)."""
    chain = list(exception_chain(exc))
    term = any(isinstance(e, Terminated) for e in chain)
    notes = [note for e in chain for note in getattr(e, "__notes__", ())]
    said = "kbs: terminated (SIGTERM)" if term else "kbs: aborted"
    click.echo(said + "".join(f"; {note}" for note in dict.fromkeys(notes)), err=True)
    return 128 + signal.SIGTERM if term else 130


def _on_sigterm(signum: int, frame: object) -> None:
    raise Terminated


#: errno values of a path the system refuses whatever kbs does: a name too long for the file system
_PATH_ERRNOS = frozenset({errno.ENAMETOOLONG})


def _internal_error(exc: BaseException, argv: list[str] | None) -> int:
    """An exception no part of kbs raised on purpose: one line saying it is a bug, the traceback
    written to a report file (or printed with ``KBS_TRACEBACK=1``), exit code 1."""
    import tempfile
    import time
    import traceback

    from kbs import __version__

    text = "".join(traceback.format_exception(exc))
    args = sys.argv[1:] if argv is None else list(argv)
    head = f"kbs {__version__}, Python {sys.version.split()[0]}, {sys.platform}\ncommand: kbs {' '.join(args)}\n\n"
    where = None
    try:
        fd, where = tempfile.mkstemp(prefix=time.strftime("kbs-internal-error-%Y%m%d-%H%M%S-"), suffix=".txt")
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(head + text)
    except OSError:
        where = None
    first = str(exc).splitlines()[0] if str(exc) else ""
    click.echo(f"kbs: internal error (a bug in kbs, not in the input): {type(exc).__name__}"
               + (f": {first}" if first else ""), err=True)
    if os.environ.get("KBS_TRACEBACK", "") not in ("", "0"):
        click.echo(text.rstrip("\n"), err=True)
    elif where is None:
        click.echo("kbs: the report file could not be written; run again with KBS_TRACEBACK=1 to see the "
                   "traceback", err=True)
    if where is not None:
        click.echo(f"kbs: the traceback is in {where}: please report it with the command line "
                   "(KBS_TRACEBACK=1 prints it here)", err=True)
    return int(ExitCode.INTERNAL)


def entry() -> None:
    """The ``kbs`` command (the console script, ``python -m kbs.cli.main``): :func:`main`, then the
    process ends without the interpreter's teardown (:func:`fast_exit`). :func:`main` is for
    callers that go on after it (tests, scripts): it returns. SIGTERM stops the run as Ctrl-C
    does (exit code 143), where it arrives in the main thread."""
    with contextlib.suppress(ValueError, OSError):  # not the main thread: the default action
        signal.signal(signal.SIGTERM, _on_sigterm)
    code = main()
    with contextlib.suppress(ValueError, OSError):  # the run is over: a late SIGTERM just ends the process
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
    fast_exit(code)


def fast_exit(code: int) -> None:
    """End the process with ``code`` as ``sys.exit`` would, without Python's teardown of every
    module's objects one by one: 0.4-0.6 s after a segmentation (numba's and scipy's registries,
    the LLVM modules), about a fifth of a whole ``kbs run`` of a vehicle frame. What ``sys.exit``
    does that matters is kept: the exit handlers run (:mod:`atexit`: logging, multiprocessing,
    temporary folders, coverage), then stdout and stderr are flushed. With a thread other than a
    daemon still running, Python must wait for it: then it is ``sys.exit``."""
    if any(t is not threading.main_thread() and not t.daemon for t in threading.enumerate()):
        sys.exit(code)
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe (kbs run ... | head): nothing more to say
            pass
    os._exit(code)


if __name__ == "__main__":
    entry()
