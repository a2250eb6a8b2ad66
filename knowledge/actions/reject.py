"""``reject``: the cluster's points are noise."""
from __future__ import annotations

from typing import ClassVar

from kbs.knowledge.parts import Action


class Reject(Action):
    """The cluster's points are noise: they belong to no output cluster (cluster -1, label -1)."""

    key: ClassVar[str] = "reject"
    divides: ClassVar[bool] = False
    keeps: ClassVar[bool] = False
