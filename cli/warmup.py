"""``kbs warmup``: compile and cache the compiled kernels now, in the foreground."""
from __future__ import annotations

import time

import click


@click.command()
def warmup() -> None:
    """Compile and cache the engine's compiled kernels (numba) now, rather than in the background
    after the first run: for images, robots and CI that want every run at full speed from the
    start. Takes 20-30 s once per install; later runs load the cached code. Then build them ahead
    of time into one extension module (about 15 s more, needs a C compiler), which later runs
    import instead of loading numba: about 0.5 s less per process. KBS_AOT=0 skips that step."""
    import os

    from kbs.inference import _aot, _flags, _warmup

    try:
        _flags._state_dir()
    except OSError as exc:  # an unusable KBS_CACHE_DIR (or no writable cache folder at all)
        where = f"KBS_CACHE_DIR={os.environ['KBS_CACHE_DIR']!r}" if os.environ.get("KBS_CACHE_DIR") else "the cache folder"
        raise click.UsageError(f"{where} cannot hold the compiled kernels' marker: {exc}") from None
    warmed = False
    if _flags.ready():
        click.echo(f"kbs: the compiled kernels are already cached ({_flags.marker()})")
    else:
        t0 = time.perf_counter()
        _warmup.warm()
        warmed = True
        click.echo(f"kbs: compiled and cached the kernels in {time.perf_counter() - t0:.1f} s ({_flags.marker()})")
    if not _aot.wanted():
        return
    if _aot.ready():
        click.echo(f"kbs: the kernels' ahead-of-time module is already built ({_aot.paths()[0]})")
        return
    t0 = time.perf_counter()
    if not warmed:
        _warmup.warm()  # the signatures to export: loaded from numba's cache
    try:
        so = _aot.build()
    except Exception as exc:  # noqa: BLE001 - no C compiler, pycc gone: numba's kernels stay in use
        click.echo(f"kbs: note: the kernels' ahead-of-time module was not built ({type(exc).__name__}: {exc}); "
                   "runs load numba's cached kernels instead")
        return
    click.echo(f"kbs: built the kernels ahead of time in {time.perf_counter() - t0:.1f} s ({so})")
