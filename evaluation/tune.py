"""``kbs tune``'s search: the thresholds marked ``tune:`` in a rule base, fitted to labelled scans
by a grid search with k-fold cross-validation over the scans.

Every setting of the grid (one value per marked threshold) is scored on every scan; the scans are
dealt into k folds (scan i into fold i mod k); for each fold the setting with the best mean score
(or median: ``select``) on the other folds' scans is chosen, and scored on the fold's own
(held-back) scans, beside the rule file's own values on the same scans. The values written out
are those chosen on all the scans. Ties go to the setting nearest to the file's values (fewest
thresholds moved, then the smallest moves relative to each range), so a threshold moves only when
a better score asks for it.

Speed: a setting is segmented once per distinct value of its split-relevant thresholds
(:func:`kbs.knowledge.tuning.split_relevant`) and scan; the settings that differ only in
label-only thresholds label that split tree again (:class:`kbs.knowledge.tuning.SplitTree`).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any
from collections.abc import Callable, Sequence

import numpy as np

from kbs.errors import ParameterError
from kbs.evaluation.metrics import GroundMetrics, ground_metrics
from kbs.knowledge.rulebase import RuleBase, Tunable
from kbs.knowledge.tuning import SplitTree, distance, grid, recorder, split_relevant, with_values

#: metric name -> (GroundMetrics attribute, +1 when higher is better / -1 when lower is)
METRICS: dict[str, tuple[str, int]] = {"f1": ("f1", 1), "iou": ("iou", 1), "total_error": ("total_error", -1)}


@dataclass(frozen=True)
class LabelledScan:
    """A scan and its ground truth, for :func:`tune`.

    Attributes
    ----------
    name : str
    X : ndarray (n, 3) float64
        The points, in the rule base's unit.
    truth : ndarray (n,) bool
        True where the ground truth says the rule base's ground label.
    valid : ndarray (n,) bool
        True where the point is labelled (the others are left out of the scores).
    sensor : ndarray (3,), optional
        The sensor position (default: the rule base's).
    """

    name: str
    X: np.ndarray
    truth: np.ndarray
    valid: np.ndarray
    sensor: np.ndarray | None = None


@dataclass(frozen=True)
class Fold:
    """One fold: its held-back scans, the setting chosen on the others, and both scores."""

    held_back: tuple[str, ...]
    chosen: int
    score: float  #: of the chosen setting, mean over the held-back scans
    original_score: float  #: of the rule file's own values, on the same scans


@dataclass
class TuneResult:
    """What :func:`tune` found. ``scores[s, j]``: setting ``s`` on scan ``j`` (metric ``metric``);
    NaN where it was not evaluated (time or evaluation bound)."""

    tunables: tuple[Tunable, ...]
    relevant: tuple[bool, ...]  #: per tunable: split-relevant
    settings: list[dict[str, float]]
    scans: tuple[str, ...]
    metric: str
    scores: np.ndarray
    metrics: dict[tuple[int, int], GroundMetrics]
    original: int
    chosen: int
    folds: list[Fold]
    evaluated: list[int]  #: settings scored on every scan, in evaluation order
    segmentations: int
    seconds: float
    stopped: str | None = None  #: why the search stopped before the whole grid, if it did
    notes: list[str] = field(default_factory=list)
    select: str = "mean"  #: how a setting's scores on the tuning scans were combined to choose it

    @property
    def cv_score(self) -> float:
        """Mean over the folds of the held-back score of the setting chosen without them."""
        return float(np.mean([f.score for f in self.folds]))

    @property
    def cv_original(self) -> float:
        """The same mean for the rule file's own values."""
        return float(np.mean([f.original_score for f in self.folds]))

    def moved(self) -> list[tuple[Tunable, float, float]]:
        """(tunable, old value, new value) of each threshold the chosen setting changes."""
        s = self.settings[self.chosen]
        return [(t, t.value, s[t.name]) for t in self.tunables
                if not math.isclose(s[t.name], t.value, rel_tol=1e-12, abs_tol=1e-15)]

    def to_dict(self) -> dict[str, Any]:
        ch = self.settings[self.chosen]
        return {
            "metric": self.metric, "select": self.select, "scans": list(self.scans),
            "thresholds": [{"name": t.name, "line": t.pos.line, "original": t.value, "values": list(t.values),
                            "split_relevant": r, "chosen": ch[t.name]} for t, r in zip(self.tunables, self.relevant)],
            "moved": [{"name": t.name, "from": a, "to": b} for t, a, b in self.moved()],
            "folds": [{"held_back": list(f.held_back), "chosen": self.settings[f.chosen], "score": f.score,
                       "original_score": f.original_score} for f in self.folds],
            "cv_score": self.cv_score, "cv_original_score": self.cv_original,
            "chosen_on_all_scans": {"setting": ch, "mean_score": self.mean(self.chosen),
                                    "original_mean_score": self.mean(self.original)},
            "per_scan": [{"scan": name, "original": _nan_none(self.scores[self.original, j]),
                          "chosen": _nan_none(self.scores[self.chosen, j])} for j, name in enumerate(self.scans)],
            "grid": {"settings": len(self.settings), "evaluated": len(self.evaluated),
                     "segmentations": self.segmentations, "seconds": self.seconds, "stopped": self.stopped},
            "notes": list(self.notes),
        }

    def mean(self, s: int, scans: Sequence[int] | None = None) -> float:
        cols = list(range(len(self.scans))) if scans is None else list(scans)
        return float(np.mean(self.scores[s, cols]))


def _nan_none(x: float) -> float | None:
    return None if math.isnan(x) else float(x)


def scan_metrics(pred_ground: np.ndarray, scan: LabelledScan) -> GroundMetrics:
    """Ground metrics of a prediction on the labelled points of ``scan``."""
    return ground_metrics(pred_ground[scan.valid], scan.truth[scan.valid].astype(np.int64), ground_values=(1,))


def _order(rule_base: RuleBase, settings: list[dict[str, float]], relevant: tuple[bool, ...],
           original: int) -> list[list[int]]:
    """The settings in groups sharing their split-relevant values (one split tree each): the
    original's group first (the original first in it), the other groups in a shuffled order
    (fixed seed: under a time or evaluation bound the settings tried spread over the grid, as
    a random search), each in grid order."""
    names = [t.name for t, r in zip(rule_base.tunables, relevant) if r]
    groups: dict[tuple, list[int]] = {}
    for i, s in enumerate(settings):
        groups.setdefault(tuple(s[n] for n in names), []).append(i)
    key0 = tuple(settings[original][n] for n in names)
    first = [original] + [i for i in groups.pop(key0) if i != original]
    rest = list(groups.values())
    order = np.random.default_rng(0).permutation(len(rest))
    return [first] + [rest[i] for i in order]


def tune(rule_base: RuleBase, scans: Sequence[LabelledScan], *, ground_label: str, folds: int | None = None,
         metric: str = "f1", jobs: int = 1, max_evals: int | None = None, time_limit: float | None = None,
         progress: Callable[[str], None] | None = None, select: str = "mean") -> TuneResult:
    """Fit the thresholds marked ``tune:`` in ``rule_base`` to ``scans`` (see the module).

    Parameters
    ----------
    rule_base : RuleBase
        With at least one ``tune:`` mark.
    scans : sequence of LabelledScan
        At least 2.
    ground_label : str
        The rule base's label that the scans' truth marks.
    folds : int, optional
        k, 2 <= k <= len(scans); default min(5, len(scans)).
    metric : {'f1', 'iou', 'total_error'}
        Of the ground label; total_error is minimised, the others maximised.
    jobs : int
        Split processes, as :class:`~kbs.knowledge.interpreter.Interpreter`.
    max_evals : int, optional
        At most this many settings are evaluated (the file's own values first).
    time_limit : float, optional
        Seconds: no new setting is started after it (the file's own values are always evaluated).
    progress : callable, optional
        Called with a line of text after each setting scored on a scan.
    select : {'mean', 'median'}
        How a setting's scores on the tuning scans are combined to choose it: their mean (as
        scikit-learn's ``GridSearchCV``), or their median, which one scan much harder than the
        others (an airborne file at 59 % total error beside samples at 5-20 %) does not decide. The
        held-back scores are means in both cases.

    Raises
    ------
    ParameterError
        No ``tune:`` mark, fewer than 2 scans, a bad ``folds``, ``metric`` or ``ground_label``, a
        scan without a labelled point.
    """
    t0 = time.perf_counter()
    tunables = rule_base.tunables
    if not tunables:
        raise ParameterError(f"{rule_base.path}: no threshold is marked 'tune:' (e.g. under a check: "
                             "tune: {min: 0.02, max: 0.10, steps: 5})")
    if metric not in METRICS:
        raise ParameterError(f"metric must be one of {', '.join(METRICS)}, got {metric!r}")
    if select not in SELECT:
        raise ParameterError(f"select must be one of {', '.join(SELECT)}, got {select!r}")
    if ground_label not in rule_base.label_names:
        raise ParameterError(f"rule base '{rule_base.name}' has no label {ground_label!r} "
                             f"(labels: {', '.join(rule_base.label_names)})")
    if len(scans) < 2:
        raise ParameterError(f"cross-validation over scans needs at least 2 labelled scans, got {len(scans)}")
    k = min(5, len(scans)) if folds is None else folds
    if not 2 <= k <= len(scans):
        raise ParameterError(f"folds must be between 2 and the number of scans ({len(scans)}), got {k}")
    for sc in scans:
        if not sc.valid.any():
            raise ParameterError(f"{sc.name}: no labelled point to score")
    attr, sign = METRICS[metric]
    gi = rule_base.label_names.index(ground_label)
    relevant = tuple(split_relevant(rule_base, t) for t in tunables)
    settings = grid(tunables)
    original = settings.index({t.name: t.value for t in tunables})
    groups = _order(rule_base, settings, relevant, original)
    n_scans = len(scans)
    scores = np.full((len(settings), n_scans), np.nan)
    mets: dict[tuple[int, int], GroundMetrics] = {}
    parsed: dict[int, RuleBase] = {}
    budget = len(settings) if max_evals is None else max(1, int(max_evals))
    stopped = None
    n_seg = 0
    done = 0
    total = min(budget, len(settings)) * n_scans

    def rb_of(i: int) -> RuleBase:
        if i not in parsed:
            parsed[i] = with_values(rule_base, settings[i])[1]
        return parsed[i]

    interp = recorder(rule_base, jobs=jobs)
    started: list[int] = []
    try:
        for group in groups:
            todo = group[:budget - len(started)]
            if not todo:
                stopped = f"--max-evals {budget}"
                break
            started.extend(todo)
            over = False
            for j, sc in enumerate(scans):
                tree = SplitTree.grow(rb_of(todo[0]), sc.X, sensor=sc.sensor if sc.sensor is not None else None,
                                      interpreter=interp)
                n_seg += 1
                for i in todo:
                    if i != original and time_limit is not None and time.perf_counter() - t0 > time_limit:
                        over = True
                        continue
                    seg = tree.label(rb_of(i))
                    m = scan_metrics(seg.label == gi, sc)
                    mets[(i, j)] = m
                    scores[i, j] = getattr(m, attr)
                    done += 1
                    if progress:
                        progress(f"{done} of {total} scores ({len(started)} settings, {n_seg} segmentations)")
            if over:
                stopped = f"--time-limit {time_limit:g} s"
                break
    finally:
        interp.close()
    evaluated = [i for i in started if not np.isnan(scores[i]).any()]
    if len(started) < len(settings) and stopped is None:
        stopped = f"--max-evals {budget}"

    distances = [distance(s, tunables) for s in settings]

    def best(cols: list[int]) -> int:
        return best_setting(scores, evaluated, cols, sign, distances, select)

    fold_list = []
    for f in range(k):
        held = [j for j in range(n_scans) if j % k == f]
        train = [j for j in range(n_scans) if j % k != f]
        c = best(train)
        fold_list.append(Fold(tuple(scans[j].name for j in held), c, float(np.mean(scores[c, held])),
                              float(np.mean(scores[original, held]))))
    chosen = best(list(range(n_scans)))
    notes = []
    if stopped:
        notes.append(f"the search stopped at {stopped}: {len(evaluated)} of {len(settings)} settings evaluated")
    cv = float(np.mean([f.score for f in fold_list]))
    cv0 = float(np.mean([f.original_score for f in fold_list]))
    if sign * cv < sign * cv0 - 1e-12:
        notes.append(f"on the held-back scans, the values chosen on the other scans score worse than the file's own "
                     f"({cv:.4f} against {cv0:.4f}): these scans do not show that moving the thresholds helps on "
                     "scans not tuned on; more (or more varied) scans would, or keep the file's values")
    return TuneResult(tunables=tunables, relevant=relevant, settings=settings, scans=tuple(s.name for s in scans),
                      metric=metric, scores=scores, metrics=mets, original=original, chosen=chosen, folds=fold_list,
                      evaluated=evaluated, segmentations=n_seg, seconds=time.perf_counter() - t0, stopped=stopped,
                      notes=notes, select=select)


#: How a setting's scores on the tuning scans are combined to choose it (``tune(select=)``).
SELECT: dict[str, Callable[[np.ndarray], Any]] = {"mean": np.mean, "median": np.median}


def best_setting(scores: np.ndarray, evaluated: Sequence[int], cols: Sequence[int], sign: float,
                 distances: Sequence[Sequence[float]], select: str = "mean") -> int:
    """The setting (a row of ``scores``, among ``evaluated``) whose scores on the scans ``cols``
    combined by ``select`` (:data:`SELECT`) are best (``sign`` 1: highest, -1: lowest); ties to the
    one nearest to the file's values (``distances``, compared in order)."""
    combine = SELECT[select]
    return max(evaluated, key=lambda i: (round(sign * float(combine(scores[i, list(cols)])), 12),
                                         tuple(-x for x in distances[i])))


def tuned_text(rule_base: RuleBase, result: TuneResult, text: str | None = None) -> str:
    """The rule file's text (``text``, its own, else ``rule_base.text``) with the chosen values
    in place of the moved ones, each with a comment 'kbs tune: old -> new, CV score', and a
    first line saying what was done."""
    label = {"f1": "F1", "iou": "IoU", "total_error": "total error"}[result.metric]
    cv = f"cross-validated ground {label} {result.cv_score:.4f} (file's values: {result.cv_original:.4f})"
    moved = result.moved()
    values = {t.name: new for t, _, new in moved}
    comments = {t.name: f"kbs tune: {_g(old, t)} -> {_g(new, t)}, {cv}" for t, old, new in moved}
    text, _ = with_values(rule_base, values, comments=comments, text=text)
    head = (f"# kbs tune: {len(moved)} of {len(result.tunables)} marked thresholds moved on {len(result.scans)} scans "
            f"({len(result.folds)} folds), {cv}\n")
    if METRICS[result.metric][1] * result.cv_score < METRICS[result.metric][1] * result.cv_original - 1e-12:
        head += "# kbs tune: held back, the tuned values scored worse than the file's: see the report\n"
    return head + text


def _g(v: float, t: Tunable) -> str:
    return str(int(v)) if t.integer else f"{v:g}"


def format_report(result: TuneResult, rules_path: str, out: str | None = None) -> str:
    """The report as markdown: the thresholds, the score per fold on the held-back scans beside
    the file's own values, the per-scan scores, which thresholds moved."""
    label = {"f1": "ground F1", "iou": "ground IoU", "total_error": "ground total error"}[result.metric]
    r = result
    lines = [f"# kbs tune: {rules_path}", "",
             f"{len(r.scans)} scans, {len(r.folds)}-fold cross-validation over scans, metric: {label} "
             f"({'lower' if METRICS[r.metric][1] < 0 else 'higher'} is better); {len(r.evaluated)} of "
             f"{len(r.settings)} settings evaluated, {r.segmentations} segmentations, {r.seconds:.0f} s"
             + (f" (stopped at {r.stopped})" if r.stopped else "")
             + ("; each setting chosen by its median score over the tuning scans" if r.select == "median" else ""),
             "",
             "| threshold | line | file's value | values tried | changes the split tree |",
             "|---|---:|---:|---|---|"]
    for t, rel in zip(r.tunables, r.relevant):
        lines.append(f"| {t.name} | {t.pos.line} | {_g(t.value, t)} | {', '.join(_g(v, t) for v in t.values)} | "
                     f"{'yes' if rel else 'no (labels only)'} |")
    lines += ["", "Held-back scores (each fold's setting chosen on the other folds' scans):", "",
              "| fold | held-back scans | chosen on the others | chosen | file's values |", "|---:|---|---|---:|---:|"]
    for n, f in enumerate(r.folds, start=1):
        s = r.settings[f.chosen]
        what = ", ".join(f"{t.name.split('.', 1)[1]} {_g(s[t.name], t)}" for t in r.tunables)
        lines.append(f"| {n} | {', '.join(f.held_back)} | {what} | {f.score:.4f} | {f.original_score:.4f} |")
    lines.append(f"| mean | | | {r.cv_score:.4f} | {r.cv_original:.4f} |")
    lines += ["", "Per scan (chosen on all the scans):", "", "| scan | chosen | file's values |", "|---|---:|---:|"]
    for j, name in enumerate(r.scans):
        lines.append(f"| {name} | {r.scores[r.chosen, j]:.4f} | {r.scores[r.original, j]:.4f} |")
    moved = r.moved()
    lines += [""]
    if moved:
        lines.append("Moved: " + "; ".join(f"{t.name} {_g(a, t)} -> {_g(b, t)}" for t, a, b in moved)
                     + (f" (written to {out})" if out else ""))
    else:
        lines.append("No threshold moved: the file's values score best" + (f" ({out} has them)" if out else ""))
    lines += [f"note: {n}" for n in r.notes]
    return "\n".join(lines)
