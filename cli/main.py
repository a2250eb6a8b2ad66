"""Entry point of the ``kbs`` command.

Data goes to stdout, progress and diagnostics to stderr. Errors a user can cause print one line
``kbs: error: ...`` and exit with the code of :class:`kbs.errors.ExitCode`; click's own usage
errors exit with 2. Anything else is a bug: it prints a traceback and exits with 1.
"""
from __future__ import annotations

import importlib
import logging
import sys

import click

from kbs import __version__
from kbs.errors import ExitCode, KbsError

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


class LazyGroup(click.Group):
    def list_commands(self, ctx: click.Context) -> list[str]:
        return list(COMMANDS)

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        if name not in COMMANDS:
            return None
        module, attr = COMMANDS[name].split(":")
        return getattr(importlib.import_module(module), attr)


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="kbs")
@click.option("-q", "--quiet", is_flag=True,
              help="Only errors on stderr (no progress, no notes); `kbs run` prints no summary either.")
@click.pass_context
def cli(ctx: click.Context, quiet: bool) -> None:
    """kbs: knowledge-based partitioning of unorganised 3D point clouds.

    Main command: kbs run --rules outdoor SCAN; a drive: kbs map --rules outdoor SCANS... --poses FILE.

    Exit codes: 0 ok, 1 internal error (a bug), 2 bad usage or option, 3 unreadable or empty
    input file, 4 invalid rule file, 5 the engine could not fit the data, 6 invalid parameter,
    7 a predicate plugin broke the contract or failed.
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
    except click.exceptions.Abort:
        click.echo("kbs: aborted", err=True)
        return 130
    except KbsError as exc:
        click.echo(f"kbs: error: {exc}", err=True)
        return int(exc.exit_code)
    except BrokenPipeError:
        return 0
    return code if isinstance(code, int) else 0


if __name__ == "__main__":
    sys.exit(main())
