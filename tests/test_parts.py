"""The knowledge layer's parts (post steps, actions, strategies): their tables, the rule file's
``post`` sequence, and parts added from a plugin file and used from a rule file, through the real
command."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from plyfile import PlyData

from kbs.io import write_ply
from kbs.knowledge import Interpreter, PredicateRegistry, load_rule_base
from kbs.knowledge.actions import ACTIONS
from kbs.knowledge.parts import post_schema
from kbs.knowledge.post import LEGACY_ORDER, STEPS
from kbs.knowledge.rulebase import RuleFileError, parse_rule_base, schema
from kbs.knowledge.strategies import STRATEGIES
from scenes import ground_and_rocks, outdoor_one_release
from test_cli import ROOT, kbs

PLUGIN = '''
"""A plugin with a post step and an action, as a user would write them."""
from dataclasses import dataclass, replace
from typing import ClassVar

import numpy as np

from kbs.knowledge import Action, PostStep


@dataclass(frozen=True)
class SmallToNoise(PostStep):
    """Clusters of a label with fewer than min_points points take another label."""

    key: ClassVar[str] = "small_to"
    schema: ClassVar[dict] = {"type": "object", "additionalProperties": False, "required": ["label", "to"],
                              "properties": {"label": {"$ref": "#/$defs/name"}, "to": {"$ref": "#/$defs/name"},
                                             "min_points": {"type": "integer", "minimum": 1},
                                             "tune": {"$ref": "#/$defs/tune"}}}
    tunable: ClassVar[tuple] = ("min_points",)

    label: str
    to: str
    min_points: int
    pos: object

    @classmethod
    def parse(cls, raw, ctx):
        ctx.label_ref(ctx.path + ("label",), raw.get("label"))
        ctx.label_ref(ctx.path + ("to",), raw.get("to"))
        return cls(raw.get("label"), raw.get("to"), ctx.number(raw.get("min_points"), 100, int),
                   ctx.pos(ctx.path, key=True))

    def apply(self, state, ctx):
        note = f"fewer than {self.min_points} points: {self.to} [{self.pos.short} small_to]"
        return replace(state, leaves=tuple(
            lf.with_record(label=self.to, notes=(note,)) if lf.label == self.label and lf.size < self.min_points
            else lf for lf in state.leaves))


class Halve(Action):
    """Divide the cluster in two at the median of its coordinate along its main axis."""

    key: ClassVar[str] = "halve"
    divides: ClassVar[bool] = True

    def divide(self, engine, node, cluster, record, rule, prepared):
        geo = cluster.geometry
        t = (cluster.X - geo.center) @ geo.eigenvectors[:, 2]
        low = t <= np.median(t)
        return [replace(node, id=f"{node.id}.{i}", parent=node.id, depth=node.depth + 1, idx=node.idx[m],
                        weight=np.ones(int(m.sum())), path=node.path[m])
                for i, m in enumerate((low, ~low))]
'''

RULES = '''
kbs_rules: 1
name: halves
units: m
strategy: divisive
limits: {max_depth: 3, min_points: 200}
scene: {ground: {normal: [0, 0, 1]}}
checks:
  planar: {predicate: thickness, max: 0.05}
  level: {predicate: ground_angle, max: 20}
  big: {predicate: point_count, min: 3000}
rules:
  - {name: halve_big, if: [big, not planar], then: halve}
labels:
  - {name: ground, if: [planar, level]}
  - {name: clutter, if: [planar, not level]}
  - {name: obstacle}
post:
  - small_to: {label: obstacle, to: clutter, min_points: 3000}
'''


@pytest.fixture(scope="module")
def rocks(tmp_path_factory) -> Path:
    X, labels = ground_and_rocks()
    path = tmp_path_factory.mktemp("scan") / "rocks.ply"
    write_ply(path, X, {"truth": labels.astype(np.int32)})
    return path


def test_the_committed_schema_declares_the_tables():
    """rules/rule-base.schema.json (what an editor validates against) says what the tables hold:
    the post steps' own schemas, the strategies, the actions."""
    doc = schema()
    assert doc["properties"]["post"] == post_schema(STEPS)
    assert set(doc["properties"]["strategy"]["enum"]) == set(STRATEGIES)
    assert doc["properties"]["rules"]["items"]["properties"]["then"]["enum"] == list(ACTIONS)
    assert list(LEGACY_ORDER) == list(STEPS)


@pytest.mark.slow
def test_a_post_step_and_an_action_from_a_plugin_file_run_from_a_rule_file(rocks, tmp_path):
    plugin = tmp_path / "parts.py"
    plugin.write_text(PLUGIN)
    rules = tmp_path / "halves.yaml"
    rules.write_text(RULES)
    r = kbs("run", "--plugin", str(plugin), "--rules", str(rules), str(rocks), "--out", str(tmp_path / "o"))
    assert r.returncode == 0, r.stderr
    doc = json.loads((tmp_path / "o" / "rocks.json").read_text())
    recs = doc["explanation"]["clusters"]
    halved = [c for c in recs if c["action"] == "halve"]
    assert halved and all(len(c["children"]) == 2 for c in halved)
    assert doc["summary"]["splits"] == len(halved)
    small = [c for c in recs if any("small_to]" in n for n in c["notes"])]
    assert small and all(c["label"] == "clutter" and c["n_points"] < 3000 for c in small)
    v = PlyData.read(str(tmp_path / "o" / "rocks.ply"))["vertex"]
    assert (np.asarray(v["scalar_label"]) == doc["label_names"].index("clutter")).sum() == sum(c["n_points"] for c in small if c["output_index"] is not None)
    # the explanation reads them back
    e = kbs("explain", str(tmp_path / "o" / "rocks.json"), "--cluster", halved[0]["id"])
    assert e.returncode == 0 and halved[0]["id"] in e.stdout, e.stderr
    # and the plugin step's threshold can be marked for kbs tune
    rb = load_rule_base(str(rules), _registry(plugin))
    assert [s.key for s in rb.post] == ["small_to"] and rb.rules[0].part.key == "halve"


def _registry(plugin: Path) -> PredicateRegistry:
    reg = PredicateRegistry.default(entry_points_too=False)
    reg.add_plugin_file(plugin)
    return reg


def test_a_plugin_part_that_breaks_the_contract_is_refused_when_loaded(tmp_path):
    cases = {
        "no schema": PLUGIN.replace('    schema: ClassVar[dict] = {"type": "object"', '    schemo: ClassVar[dict] = {"type": "object"'),
        "clash": PLUGIN.replace('key: ClassVar[str] = "small_to"', 'key: ClassVar[str] = "relabel"'),
        "no divide": PLUGIN.replace("    def divide(self, engine", "    def divided(self, engine"),
    }
    said = {
        "no schema": "post step 'small_to' needs a 'schema'",
        "clash": "post step 'relabel' from",
        "no divide": "action 'halve' divides: it must define divide()",
    }
    for name, text in cases.items():
        plugin = tmp_path / f"{name.replace(' ', '_')}.py"
        plugin.write_text(text)
        r = kbs("rules", "check", "outdoor", "--plugin", str(plugin))
        assert r.returncode == 7 and said[name] in r.stderr and "Traceback" not in r.stderr, (name, r.stderr)


def _parse(post: str, extra_checks: str = "") -> object:
    text = RULES.replace("post:\n  - small_to: {label: obstacle, to: clutter, min_points: 3000}\n", post)
    text = text.replace("then: halve", "then: split")
    text = text.replace("checks:\n", "checks:\n" + extra_checks)
    return parse_rule_base(text, "t.yaml", PredicateRegistry.default(entry_points_too=False))


@pytest.mark.parametrize("post, message", [
    ("post:\n  - ground_modl: {label: ground}\n", "t.yaml:19:5: unknown key 'ground_modl' in post[0] (did you mean "
                                                  "'ground_model'?)"),
    ("post:\n  - {ground_model: {label: ground}, merge_coplanar: {label: ground}}\n",
     "t.yaml:19:5: post[0] must be one step"),
    ("post: ground_model\n", "t.yaml:18:7: post must be a sequence of steps"),
    ("post:\n  - ground_contact: {tolerance: 0.05}\n  - ground_model: {label: ground}\n",
     "t.yaml:19:5: ground_contact needs post.ground_model"),
    ("post:\n  - ground_model: {label: ground, radius: -1}\n",
     "t.yaml:19:43: post[0].ground_model.radius: -1 is less than or equal to the minimum of 0"),
])
def test_post_sequence_problems_are_positioned(post, message):
    with pytest.raises(RuleFileError) as info:
        _parse(post)
    assert message in str(info.value), str(info.value)


def test_steps_run_in_the_order_the_sequence_gives():
    """Two relabel steps: the second sees the first one's labels; in the other order it does not."""
    first = "  - relabel: [{name: a, from: obstacle, to: clutter, if: not planar}]\n"
    second = "  - relabel: [{name: b, from: clutter, to: ground, if: not planar}]\n"
    X, _ = ground_and_rocks()
    one = Interpreter(_parse("post:\n" + first + second)).run(X)
    other = Interpreter(_parse("post:\n" + second + first)).run(X)
    recs = one.explanation.records.values()
    moved = [r for r in recs if r.relabel]
    assert moved and all(r.relabel["rule"] == "b" and r.label == "ground" for r in moved)
    assert all(r.label == "clutter" for r in other.explanation.records.values() if r.relabel)
    with pytest.raises(RuleFileError, match="relabel rule 'a' is defined twice"):
        _parse("post:\n" + first + first)


def test_a_post_mapping_as_older_files_write_it_runs_in_the_fixed_order(rocks):
    """outdoor.yaml with its post written as one mapping, merge_coplanar first as the files before
    the sequence had it: the same labels, clusters and memberships as the shipped sequence (without
    its second ground_release, which a mapping, one step of each kind, cannot hold)."""
    rb = outdoor_one_release()
    text = rb.text
    start = text.index("\npost:")
    end = text.index("\n\n", start + 1)
    lines = text[start + 1:end].split("\n")
    mapping = ["post:"]
    for line in lines[1:]:
        mapping.append("  " + line[4:] if line.startswith("  - ") else line[2:] if line.startswith("      ") else line)
    merge_at = next(i for i, ln in enumerate(mapping) if ln.startswith("  merge_coplanar:"))
    mapping = mapping[:1] + mapping[merge_at:merge_at + 4] + mapping[1:merge_at] + mapping[merge_at + 4:]
    old = parse_rule_base(text[:start + 1] + "\n".join(mapping) + text[end:], "outdoor.yaml",
                          PredicateRegistry.default(entry_points_too=False))
    assert [s.key for s in old.post] == [s.key for s in rb.post] == list(LEGACY_ORDER)
    X, _ = ground_and_rocks()
    a, b = Interpreter(rb).run(X), Interpreter(old).run(X)
    assert np.array_equal(a.cluster, b.cluster) and np.array_equal(a.label, b.label)
    assert np.array_equal(a.membership, b.membership)
    assert [c["ids"] for c in a.clusters] == [c["ids"] for c in b.clusters]


def test_every_built_in_part_documents_itself():
    for table in (STEPS, ACTIONS, STRATEGIES):
        for key, cls in table.items():
            assert cls.key == key and len(cls.doc()) > 30, key
    assert (ROOT / "knowledge" / "post" / "ground_model.py").is_file()
