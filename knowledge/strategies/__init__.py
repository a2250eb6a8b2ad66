"""The strategies (``strategy:`` in a rule file): how the scene is divided until the rules are
satisfied. One module per strategy, one line per strategy in :data:`STRATEGIES`."""
from __future__ import annotations

from kbs.knowledge.parts import Strategy
from kbs.knowledge.strategies.divisive import Divisive
from kbs.knowledge.strategies.global_sweep import GlobalSweep

#: The strategies, by rule-file name.
STRATEGIES: dict[str, type[Strategy]] = {
    Divisive.key: Divisive,
    GlobalSweep.key: GlobalSweep,
}

__all__ = ["STRATEGIES", "Divisive", "GlobalSweep"]
