"""``kbs warmup``: compile and cache the compiled kernels now, in the foreground."""
from __future__ import annotations

import time

import click


@click.command()
def warmup() -> None:
    """Compile and cache the engine's compiled kernels (numba) now, rather than in the background
    after the first run: for images, robots and CI that want every run at full speed from the
    start. Takes 20-30 s once per install; later runs load the cached code."""
    from kbs.inference import _flags, _warmup

    if _flags.ready():
        click.echo(f"kbs: the compiled kernels are already cached ({_flags.marker()})")
        return
    t0 = time.perf_counter()
    _warmup.warm()
    click.echo(f"kbs: compiled and cached the kernels in {time.perf_counter() - t0:.1f} s ({_flags.marker()})")
