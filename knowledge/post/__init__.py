"""The post steps: what is done after the clusters are labelled, in the order the rule file's
``post`` lists them. One module per step, one line per step in :data:`STEPS`; a plugin adds more
(:class:`kbs.knowledge.parts.PostStep`)."""
from __future__ import annotations

from kbs.knowledge.parts import PostStep
from kbs.knowledge.post.ground_contact import GroundContact
from kbs.knowledge.post.ground_model import GroundModel
from kbs.knowledge.post.ground_release import GroundRelease
from kbs.knowledge.post.merge_coplanar import MergeCoplanar
from kbs.knowledge.post.relabel import Relabel

#: The built-in post steps, by rule-file key.
STEPS: dict[str, type[PostStep]] = {
    GroundModel.key: GroundModel,
    Relabel.key: Relabel,
    GroundRelease.key: GroundRelease,
    GroundContact.key: GroundContact,
    MergeCoplanar.key: MergeCoplanar,
}
#: The order the steps of a ``post`` written as a mapping (rule files before the sequence) run in.
LEGACY_ORDER = ("ground_model", "relabel", "ground_release", "ground_contact", "merge_coplanar")

__all__ = ["STEPS", "LEGACY_ORDER", "GroundModel", "Relabel", "GroundRelease", "GroundContact", "MergeCoplanar"]
