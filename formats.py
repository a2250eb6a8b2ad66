"""Names and versions of the documents kbs writes (the result JSON, its explanation tree).

A document says what it is and which version of that format it follows::

    {"format": "kbs-result", "version": "1.1", ...}

``version`` is ``"MAJOR.MINOR"``. A minor version adds keys a reader of the same major version
may ignore: an older kbs still reads the file. A major version changes what existing keys mean:
a reader refuses a major version newer than its own, saying so (``kbs`` exits with code 3).
A document without ``version`` was written before versions existed and is read as ``1.0``.
"""
from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

__all__ = ["FormatVersionError", "NewerVersionError", "Version", "document_version"]


class FormatVersionError(ValueError):
    """A document of another format, with a malformed version, or of a newer major version."""


class NewerVersionError(FormatVersionError):
    """A document of a newer major version than this kbs reads."""


_VERSION = re.compile(r"(0|[1-9][0-9]{0,5})\.(0|[1-9][0-9]{0,5})")


@dataclass(frozen=True, order=True)
class Version:
    """A format version: ``major.minor``."""

    major: int
    minor: int = 0

    def __str__(self) -> str:
        return f"{self.major}.{self.minor}"

    @classmethod
    def parse(cls, value: Any) -> Version:
        """``"1.1"`` (an int ``N``, as some writers may put it, is ``N.0``).

        Raises
        ------
        FormatVersionError
            Anything else (a float is refused: ``1.10`` and ``1.1`` would be the same number).
        """
        if isinstance(value, int) and not isinstance(value, bool) and 0 <= value < 1_000_000:
            return cls(value, 0)
        if isinstance(value, str):
            m = _VERSION.fullmatch(value)
            if m:
                return cls(int(m.group(1)), int(m.group(2)))
        raise FormatVersionError(f"'version' is {value!r}: expected \"MAJOR.MINOR\", e.g. \"1.1\"")


def document_version(doc: Mapping[str, Any], *, format: str, reads: Version,
                     legacy_key: str | None = None) -> Version:
    """The version of ``doc``, checked against what this kbs reads.

    Parameters
    ----------
    doc : mapping
        The parsed document.
    format : str
        Its expected ``format`` value (a document without ``format`` is taken to be one).
    reads : Version
        The version this kbs writes; it reads every version of the same major.
    legacy_key : str, optional
        An older integer key that held the major version (``result_format``), read when there is
        no ``version``.

    Raises
    ------
    FormatVersionError
        ``format`` names another format or ``version`` is malformed; :class:`NewerVersionError`
        when its major version is newer than ``reads``'s (the message says to upgrade kbs).
    """
    name = doc.get("format", format)
    if name != format:
        raise FormatVersionError(f"'format' is {name!r}, not {format!r}")
    if "version" in doc:
        version = Version.parse(doc["version"])
    elif legacy_key is not None and legacy_key in doc:
        legacy = doc[legacy_key]
        if not isinstance(legacy, int) or isinstance(legacy, bool):
            raise FormatVersionError(f"{legacy_key!r} is {legacy!r}")
        version = Version(legacy, 0)
    else:
        version = Version(1, 0)
    if version.major > reads.major:
        raise NewerVersionError(f"written by a newer kbs ({format} version {version}; this kbs reads "
                                 f"{reads.major}.x): upgrade kbs to read it")
    return version
