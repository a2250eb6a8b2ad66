"""``accept``: the cluster is a leaf of the split tree (what happens when no rule acts)."""
from __future__ import annotations

from typing import ClassVar

from kbs.knowledge.parts import Action


class Accept(Action):
    """The cluster is kept as it is: a leaf, labelled by the first label whose condition holds."""

    key: ClassVar[str] = "accept"
    divides: ClassVar[bool] = False
    keeps: ClassVar[bool] = True
