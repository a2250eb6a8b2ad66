"""Reading the ``<stem>.json`` that ``kbs run`` writes beside its result cloud."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Iterable

from kbs.errors import CloudFileError


def read_result_json(path: str | Path, *, require: Iterable[str] = ()) -> dict[str, Any]:
    """The parsed result document; every way it can be unreadable is a one-line CloudFileError.

    Parameters
    ----------
    path : path of the JSON file.
    require : keys the document must have (e.g. ``("explanation",)``).
    """
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        for key in require:
            doc[key]  # noqa: B018 -- a KeyError says which key is missing
    except FileNotFoundError as exc:
        raise CloudFileError(str(path), "no such file") from exc
    except IsADirectoryError as exc:
        raise CloudFileError(str(path), "is a directory, not a result file") from exc
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError) as exc:
        raise CloudFileError(str(path), f"not a kbs result file ({type(exc).__name__}: {exc})") from exc
    return doc
