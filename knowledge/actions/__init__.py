"""The actions a rule may take (``then:``). One module per action, one line per action in
:data:`ACTIONS`; a plugin adds more (:class:`kbs.knowledge.parts.Action`). A cluster no rule acts
on is accepted (:class:`Accept`)."""
from __future__ import annotations

from kbs.knowledge.actions.accept import Accept
from kbs.knowledge.actions.reject import Reject
from kbs.knowledge.actions.split import Split
from kbs.knowledge.actions.split_components import SplitComponents
from kbs.knowledge.parts import Action

#: The built-in actions, by rule-file name (``accept`` is what happens when no rule acts: a rule
#: cannot name it).
ACTIONS: dict[str, type[Action]] = {
    Split.key: Split,
    SplitComponents.key: SplitComponents,
    Reject.key: Reject,
}
#: The action of a cluster no rule acts on.
DEFAULT = Accept

__all__ = ["ACTIONS", "DEFAULT", "Accept", "Reject", "Split", "SplitComponents"]
