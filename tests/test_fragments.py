"""Issue 12, session 41: a fragment of the split tree (10 points or fewer) is not noise for its size
alone. The airborne rules rejected such clusters as noise (`noise: if: tiny, then: reject`); on
the ISPRS samples they hold bare earth (945 points of samp11, 276 of samp61): the split tree cuts
rough ground on steep or broken terrain into pieces until the limits. The rules now keep them
whole, an object until the post steps judge them by where they lie (`terrain`, and `specks`: at
the terrain the ground around allows, not stray points); only a point alone in a cluster of its own
is still noise."""
from __future__ import annotations

import re

import numpy as np
import pytest

from kbs.knowledge import Interpreter, load_rule_base
from kbs.knowledge.predicates import PredicateRegistry
from kbs.knowledge.rulebase import parse_rule_base, shipped_text
from test_groundmodel import _isprs_centred


def _with_noise_rule(text: str) -> str:
    """The shipped airborne rules as they were before session 41: fragments rejected as noise."""
    swaps = [
        (r"    if: lone\n", "    if: tiny\n"),
        (r"    if: \[not planar, not tiny\]\n", "    if: [not planar]\n"),
        (r"    if: \[planar, gentle, not tiny\][^\n]*\n", "    if: [planar, gentle]\n"),
        (r"      - name: specks\n(?:        [^\n]*\n)+", ""),
    ]
    for pattern, repl in swaps:
        text, n = re.subn(pattern, repl, text)
        assert n == 1, pattern  # the shipped file as this test knows it
    return text


@pytest.mark.slow  # a whole real scan twice: pytest --runslow (CI) runs it
def test_airborne_fragments_are_judged_by_where_they_lie_not_rejected_as_noise(shared_data):
    """ISPRS sample 61 (the validation part: rural, terrain discontinuities), against the same rules
    with the old noise rule: no point is noise now; the points the old rules rejected are
    labelled, most of their bare earth ground; `specks` took only fragments lying at the terrain;
    the total error falls (measured 6.32 -> 5.85 %)."""
    _, X, truth = _isprs_centred(shared_data, "samp61")
    rb = load_rule_base("airborne")
    old_text = _with_noise_rule(shipped_text("airborne"))
    rb_old = parse_rule_base(old_text, "airborne-before.yaml", PredicateRegistry.default())
    assert [(r.name, str(r.condition)) for r in rb_old.rules] == [("noise", "tiny"), ("rough", "not planar")]
    assert [(r.name, str(r.condition)) for r in rb.rules] == [("noise", "lone"), ("rough", "not planar and not tiny")]
    seg, old = Interpreter(rb, jobs=1).run(X), Interpreter(rb_old, jobs=1).run(X)
    assert (seg.cluster < 0).sum() == 0
    rejected = old.cluster < 0
    assert rejected.sum() > 200  # 10 points or fewer each, bare earth and objects
    earth = rejected & truth
    assert earth.sum() > 100 and (seg.label[earth] == 0).mean() > 0.5
    specks = [r for r in seg.explanation.records.values()
              if isinstance(r.relabel, dict) and r.relabel.get("rule") == "specks"]
    assert specks
    for r in specks:
        assert r.n_points <= 10
        at = next(c for c in r.checks if c.check == "at_terrain")
        assert -1.0 <= at.value <= 0.5, at

    def total_error(label):
        return np.mean((label == 0) != truth)

    assert total_error(seg.label) < total_error(old.label) - 0.003  # measured 5.85 % against 6.32 %
