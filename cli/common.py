"""Pieces shared by the commands: the cloud argument, the progress bar, result files."""
from __future__ import annotations

import contextlib
import re
import sys
from pathlib import Path
from typing import Iterator, Mapping

import click
import numpy as np
from tqdm import tqdm

from kbs.io import PointCloud, write_ply

#: The CLOUD argument: existence and readability are checked by the reader, which says what is
#: wrong in one line with the file's name (click's own check would not give our exit code).
cloud_argument = click.argument("cloud", type=click.Path(path_type=Path))


@contextlib.contextmanager
def progress_bar(total: int, desc: str, quiet: bool) -> Iterator[tqdm]:
    """A tqdm bar on stderr, shown only on a terminal and when not quiet."""
    bar = tqdm(total=total, desc=desc, file=sys.stderr, disable=True if quiet else None, leave=False)
    try:
        yield bar
    finally:
        bar.close()


def write_result_ply(path: Path, cloud: PointCloud, results: Mapping[str, np.ndarray]) -> None:
    """Write the cloud's points with its own fields and the per-point ``results`` to a PLY file
    (an input field named like a result is kept with the suffix '_in'). For an organised input
    (a range image, an organised PCD), ``pixel`` (int32) is each point's position in the
    row-major grid of ``cloud.shape``."""
    fields = {}
    for name, values in cloud.fields.items():  # the input's own fields, under PLY-safe names
        safe = re.sub(r"\W", "_", name)
        if safe in results:  # the input's own 'label' stays, as 'label_in'
            safe += "_in"
        if safe and safe not in results and np.asarray(values).ndim == 1:
            fields[safe] = values
    fields.update(results)
    if cloud.shape is not None and "pixel" not in fields:  # organised input: where each point sits
        fields["pixel"] = cloud.index.astype(np.int32)
    write_ply(path, cloud.xyz, fields)
