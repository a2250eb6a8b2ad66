"""``divisive``: the scene's first partition, then every cluster a rule wants divided is divided
on its own, and its children judged in turn."""
from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, ClassVar

import numpy as np

from kbs.errors import FitError
from kbs.inference import UFPONCResult
from kbs.knowledge.explain import APDCurve
from kbs.knowledge.parts import Strategy
from kbs.knowledge.state import Division, Draft, Judged, Node


class Divisive(Strategy):
    """The scene's initial partition (K by APD's first local maximum, or fixed), then every cluster
    a rule wants divided is divided on its own (by its action: UFP-ONC on its points, its
    connected components) and its children are judged in turn, one level of the tree at a time.

    The limits are per cluster (max_depth, min_points): the subtree of a cluster depends only on
    its points and the scene (sensor, ground plane), not on how much else the file holds. The
    optional max_clusters is the exception: a cap on the clusters of the whole split tree, counted
    in wave order, so with it a point's result depends on the rest of the file.
    """

    key: ClassVar[str] = "divisive"

    def partition(self, run: Any, X: np.ndarray) -> UFPONCResult:
        fixed_k = isinstance(run.rule_base.engine["initial_k"], int)
        return run.ufp_onc(X, "k_max" if fixed_k else "first_max")

    @staticmethod
    def first_children(run: Any, X: np.ndarray, root: Node, res: UFPONCResult, notes: list[str]) -> tuple[int, list[Node]]:
        """K of the first partition and its clusters."""
        k = run.initial_k(res, notes)
        u = res.memberships if k == res.chosen_k else res.partition(k).predict_proba(X)
        return k, root.children(u)

    def run(self, run: Any, X: np.ndarray, root: Node, records: dict[str, Draft],
            res: UFPONCResult) -> Judged:
        notes = list(res.notes)
        k0, children = self.first_children(run, X, root, res, notes)
        records["c"].set(apd=APDCurve(tuple(p.k for p in res.partitions), tuple(p.apd for p in res.partitions), k0))
        del res, root  # the (n, K) memberships: the children hold copies of their part
        return self.divide(run, X, children, records, notes)

    @staticmethod
    def divide(run: Any, X: np.ndarray, children: list[Node], records: dict[str, Draft],
               notes: list[str]) -> Judged:
        """Breadth first, one level of the split tree (a wave) at a time: every cluster of the wave
        is judged, the divisions it asks for are started (the UFP-ONC splits side by side when
        jobs > 1), then the decisions are applied in order — exactly the order of a first-in
        first-out queue, so the optional max_clusters, when a rule file sets it, stops the same
        clusters whatever the number of jobs.

        With jobs > 1 (and no max_clusters, worker processes that can be forked, and a cloud of
        fewer than EARLY_WORKERS points: a larger one keeps the splits alone in the workers, for
        its memory), once the
        scene's clusters are judged and divided here, the whole subtree of each of their children
        is judged and divided in a worker process (:class:`kbs.knowledge.interpreter.Subtrees`):
        the tree below a cluster depends on its points and the scene alone, so the records and
        leaves it gives are those of one process, put back in the queue's order. A child holding
        more than 1 / (SUBTREE_SHARE x jobs) of the cloud is split here first, a level at a time
        (its split in a worker), so that a large cloud is not left to one worker's subtree; on
        vehicle frames that measured the same as giving every child whole (docs/PERFORMANCE.md,
        session 32)."""
        from kbs.knowledge.interpreter import _Splitter

        rb = run.rule_base
        records["c"].set(children=tuple(c.id for c in children))
        wave = [(c, *run.record(c)) for c in children]
        children.clear()  # the wave holds them now: a node split below is freed with its wave
        ground, ground_facts = run.ground([(cl, rec) for _, cl, rec in wave])
        scene = run.scene(ground)
        leaves: list[tuple[Node, Any, Draft]] = []
        from kbs.knowledge.run import EARLY_WORKERS

        # a large cloud keeps the splits alone in the workers: with whole subtrees, 10^7 airborne points
        # took 4,475 MiB against 3,937 (over the 4 GB target; docs/PERFORMANCE.md, session 32)
        delegate = (run.jobs > 1 and rb.limits.get("max_clusters") is None and run.interpreter.forks
                    and X.shape[0] < EARLY_WORKERS)
        if not delegate:
            with _Splitter(run.interpreter, run.ufp_kwargs("first_max", rb.engine["split_min_k"])) as splitter:
                run.splitter = splitter
                Divisive.waves(run, wave, scene, records, leaves, n_clusters=len(wave))
                run.splitter = None
            return Judged.of(X, leaves, scene, records, ground_facts, tuple(notes))
        from kbs.knowledge.interpreter import Subtrees

        # a cluster of more than this goes on here, one level at a time (its split in a worker), so
        # that no subtree holds most of the work while the other workers wait
        large = X.shape[0] // (SUBTREE_SHARE * run.jobs) if SUBTREE_SHARE else X.shape[0]
        with _Splitter(run.interpreter, run.ufp_kwargs("first_max", rb.engine["split_min_k"])) as splitter, \
                Subtrees(run.interpreter, scene) as trees:
            run.splitter = splitter  # the scene's clusters here, their splits side by side in the workers
            first = True
            while wave:
                small = [] if first else [w for w in wave if w[0].size <= large]
                wave = wave if first else [w for w in wave if w[0].size > large]
                first = False
                wave = Divisive.waves(run, wave, scene, records, leaves, n_clusters=0, max_waves=1,
                                      started=functools.partial(trees.start, small))  # behind this wave's splits
            run.splitter = None
            for node, tree_records, kept in trees.results():
                for rid, record in tree_records:
                    records[rid] = Draft(record)
                leaves.extend((Node(n.id, n.parent, n.depth, node.idx[n.idx], n.weight, n.path), cl, Draft(record))
                              for n, cl, record in kept)
        order = {rid: i for i, rid in enumerate(_queue_order(records))}
        queued = sorted(records.items(), key=lambda item: order[item[0]])
        records.clear()
        records.update(queued)
        leaves.sort(key=lambda leaf: order[leaf[0].id])
        return Judged.of(X, leaves, scene, records, ground_facts, tuple(notes))

    @staticmethod
    def waves(run: Any, wave: list[tuple[Node, Any, Draft]], scene: Any, records: dict[str, Draft],
              leaves: list[tuple[Node, Any, Draft]], n_clusters: int, max_waves: int | None = None,
              started: Callable[[], None] | None = None) -> list[tuple[Node, Any, Draft]]:
        """Judge and divide ``wave`` and the waves below it (``max_waves`` of them at most: then
        the next wave is returned, empty when the tree is done); the records of the judged clusters
        go into ``records``, the kept ones into ``leaves``, in the order of a first-in first-out
        queue. ``started`` is called once the first wave's divisions are started (or at once when
        ``wave`` is empty)."""
        done = 0
        if not wave and started is not None:
            started()
        while wave and (max_waves is None or done < max_waves):
            done += 1
            judged = []
            for node, cl, rec in wave:
                records[node.id] = rec
                action, rule = run.judge(cl, scene, rec)
                prepared = None
                if action.divides and run.cannot_split(node, 0) is None:  # max_clusters: known later
                    prepared = action.prepare(run, cl)
                judged.append((node, cl, rec, action, rule, prepared))
            if started is not None:
                started()
                started = None
            wave = []
            for node, cl, rec, action, rule, prepared in judged:
                if not action.divides:
                    rec.set(action=action.key)
                    if action.keeps:
                        leaves.append((node, cl, rec))
                    continue
                why_not = run.cannot_split(node, n_clusters)
                division = Division(())
                if why_not is None:
                    try:
                        division = Division.of(action.divide(run, node, cl, rec.facts, rule, prepared))
                    except FitError as exc:
                        why_not = "split_failed", f"the split failed: {exc}"
                    if division.apd is not None:
                        rec.set(apd=division.apd)
                    if why_not is None and len(division.children) < 2:
                        why_not = "single_cluster", "the split gave a single cluster"
                if why_not is not None:
                    run.stop(rec, *why_not)
                    leaves.append((node, cl, rec))
                    continue
                kids = division.children
                rec.set(action=action.key, children=tuple(k.id for k in kids))
                n_clusters += len(kids) - 1
                kid_records = [(k, *run.record(k)) for k in kids]
                known = action.inherit(run, rule, node)
                for _, _, kid in kid_records:
                    for check, measured in known:
                        kid.check(check, measured)
                wave.extend(kid_records)
                if run.progress:
                    run.progress(f"{node.id} split in {len(kids)}")
        return wave


#: with jobs > 1, a cluster holding more than 1 / (SUBTREE_SHARE x jobs) of the cloud is not given
#: to a worker whole: it is split here and its children are (0: every child of the first clusters
#: is given whole)
SUBTREE_SHARE = 4


def _queue_order(records: dict[str, Draft]) -> list[str]:
    """The ids of the split tree in the order of its first-in first-out queue (level by level,
    each cluster's children in their order), from the root 'c' and each record's children."""
    order, i = ["c"], 0
    while i < len(order):
        order.extend(records[order[i]].record.children or ())
        i += 1
    return order
