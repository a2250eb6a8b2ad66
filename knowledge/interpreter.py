"""The interpreter: runs a rule base's strategy over a cloud, with the inference motor as its only
means of splitting, and records every decision in an :class:`~kbs.knowledge.explain.Explanation`.

Strategies (ALGORITHMS.md section 3):

- ``divisive``: the scene's initial partition (K by APD's first local maximum, or fixed), then
  every cluster a rule wants split is split on its own — by UFP-ONC on its points ('split') or
  along its connected components ('split_components') — and its children are judged in turn.
- ``global`` (the seed paper): while some cluster of the scene's K-partition fails, go on to the
  (K+1)-partition of the whole scene, up to k_max.

Either way: rejected clusters become noise, accepted ones take the first label whose condition
holds, and clusters of the merge label whose planes agree are merged. Every limit reached is
recorded, with its kind; the run always terminates (depth and minimum size are bounded).

The limits are per cluster (``max_depth``, ``min_points``): the subtree of a cluster depends only on
its points and the scene (sensor, ground plane), not on how much else the file holds. The optional
``max_clusters`` is the exception: a cap on the clusters of the whole split tree, counted in wave
order, so with it a point's result depends on the rest of the file.
"""
from __future__ import annotations

import copy

import time
from dataclasses import dataclass
from collections.abc import Callable
from typing import Any, Self

import numpy as np

from kbs.errors import FitError, KbsError
from kbs.inference import UFPONCResult, first_local_max, ufp_onc
from kbs.inference.incremental import IncrementalSweep
from kbs.knowledge.connexity import Connexity, assign_to_nearest, project_on_plane
from kbs.knowledge.engine_settings import UFP_ONC_RULE_SETTINGS
from kbs.knowledge.explain import NO_LABEL, APDCurve, Catalogue, CheckRecord, ClusterRecord, Explanation
from kbs.knowledge.groundplane import robust_plane, supported_points
from kbs.knowledge.predicates import Cluster, Ground, Measurement, PredicateError, Scene
from kbs.knowledge.rulebase import Condition, RuleBase


@dataclass(frozen=True)
class Segmentation:
    """The result of a run.

    Attributes
    ----------
    cluster : ndarray (n,) int32
        Output cluster of each point (numbered by decreasing size), -1 = not assigned (noise).
    label : ndarray (n,) int32
        Index into ``label_names``, -1 = none (noise).
    membership : ndarray (n,) float32
        Membership of each point in its cluster (product of the fuzzy memberships along its path
        in the split tree; crisp splits count 1).
    label_names : list of str
    explanation : Explanation
    clusters : list of dict
        One per output cluster: index, ids of the records merged into it, label, size, descriptors.
    seconds : float
    """

    cluster: np.ndarray
    label: np.ndarray
    membership: np.ndarray
    label_names: list[str]
    explanation: Explanation
    clusters: list[dict[str, Any]]
    seconds: float

    @property
    def n_splits(self) -> int:
        return sum(r.action in ("split", "split_components") for r in self.explanation.records.values())

    def limits_by_kind(self) -> dict[str, dict[str, Any]]:
        """The clusters a rule wanted split but that were kept, grouped by what stopped them.

        Keys are the kinds of :data:`STOP_KINDS`, in that order (only those that occurred). Each
        value: ``setting`` (the rule-file key that decides it, e.g. ``'limits.max_depth'``, or None
        when it is not a setting: the split failed, or gave a single cluster), ``value`` (that
        setting's value), ``count``, ``points`` (their points when judged) and ``clusters`` (their
        ids, the largest first).
        """
        out: dict[str, dict[str, Any]] = {}
        stopped = sorted((r for r in self.explanation.records.values() if r.action == "limit"),
                         key=lambda r: (-r.n_points, r.id))
        for r in stopped:
            lim = r.limit or {"kind": "other", "setting": None, "value": None}
            e = out.setdefault(lim["kind"], {"setting": lim["setting"], "value": lim["value"], "count": 0,
                                             "points": 0, "clusters": []})
            e["count"] += 1
            e["points"] += r.n_points
            e["clusters"].append(r.id)
        order = list(STOP_KINDS)
        return dict(sorted(out.items(), key=lambda kv: order.index(kv[0]) if kv[0] in order else len(order)))

    def summary(self) -> dict[str, Any]:
        """Counts; ``points_per_label``: each label's points, then ``noise`` (points in no output
        cluster: rejected; ``noise (rejected)`` when the rule base has a label named noise) and,
        when there are, ``no label matched`` (points of output clusters no label's condition held
        for)."""
        counts = {name: int((self.label == i).sum()) for i, name in enumerate(self.label_names)}
        counts["noise (rejected)" if "noise" in counts else "noise"] = int((self.cluster < 0).sum())
        unlabelled = int(((self.label < 0) & (self.cluster >= 0)).sum())
        if unlabelled:
            counts[NO_LABEL] = unlabelled
        return {"points": int(self.cluster.size), "clusters": len(self.clusters), "splits": self.n_splits,
                "limits": sum(r.action == "limit" for r in self.explanation.records.values()),
                "limits_by_kind": self.limits_by_kind(),
                "points_per_label": counts, "seconds": round(self.seconds, 3)}


#: Why a cluster that a rule wanted split was kept (``ClusterRecord.limit['kind']``), and the
#: rule-file setting that decides it (None: not a setting of the file).
STOP_KINDS: dict[str, str | None] = {
    "max_depth": "limits.max_depth",          # the cluster is max_depth splits below the scene
    "min_points": "limits.min_points",        # it has fewer points
    "max_clusters": "limits.max_clusters",    # the whole split tree has that many clusters (optional cap)
    "k_max": "engine.k_max",                  # strategy global: no partition of the scene beyond K = k_max
    "split_failed": None,                     # the engine could not split its points
    "single_cluster": None,                   # the split put all its points in one cluster
    "unpartitioned": None,                    # the scene could not be partitioned (further, for global)
}


@dataclass
class _Node:
    id: str
    parent: str | None
    depth: int
    idx: np.ndarray  # indices into X
    weight: np.ndarray  # membership in this node (from its own split)
    path: np.ndarray  # membership along the path


class Interpreter:
    """Applies a :class:`RuleBase` to clouds.

    Parameters
    ----------
    rule_base : RuleBase
    sensor : array-like (3,), optional
        Overrides the rule base's sensor position.
    progress : callable, optional
        Called with a short message after each decision.
    jobs : int
        Processes computing UFP-ONC splits (1: all in this process; -1: one per available core).
        The splits of one level of the tree are independent, so they run side by side while this
        process judges the clusters; the result is identical whatever ``jobs`` is.
    """

    #: A ground plane found beforehand, with its explanation (:meth:`find_ground`): when set, every
    #: run takes it instead of finding its own (a tile takes the whole cloud's).
    given_ground: tuple[Ground | None, dict[str, Any]] | None = None

    def __init__(self, rule_base: RuleBase, *, sensor: Any = None,
                 progress: Callable[[str], None] | None = None, jobs: int = 1) -> None:
        self.rb = rule_base
        self.sensor = np.asarray(rule_base.sensor if sensor is None else sensor, dtype=np.float64)
        self.progress = progress
        if not isinstance(jobs, (int, np.integer)) or jobs == 0 or jobs < -1:
            raise ValueError(f"jobs must be a positive number of processes or -1 (one per core), got {jobs!r}")
        self.jobs = available_cores() if jobs == -1 else int(jobs)

    # -- worker processes ------------------------------------------------------------------------

    def _worker_pool(self):
        """The pool of split workers (``jobs`` > 1), started when first needed and kept until
        :meth:`close`, so that frame after frame reuses it."""
        pool = getattr(self, "_pool", None)
        if pool is None:
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            from multiprocessing.util import Finalize

            methods = multiprocessing.get_all_start_methods()
            ctx = multiprocessing.get_context("fork" if "fork" in methods else None)
            pool = self._pool = ProcessPoolExecutor(max_workers=self.jobs, mp_context=ctx)
            # stopped when this interpreter is collected or the process exits, before
            # multiprocessing joins its children (in a process that is itself a multiprocessing
            # child, that join comes first and would wait for ever on idle workers)
            self._pool_finalizer = Finalize(self, _shutdown_pool, args=(pool,), exitpriority=10)
        return pool

    def close(self) -> None:
        """Stop the worker processes, if any were started (they start again when needed)."""
        fin = getattr(self, "_pool_finalizer", None)
        self._pool, self._pool_finalizer = None, None
        if fin is not None:
            fin()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- engine --------------------------------------------------------------------------------

    def _ufp_kwargs(self, stop: str, min_k: int = 1) -> dict[str, Any]:
        """ufp_onc's keywords: the rule file's engine settings that are ufp_onc's (the table of
        kbs.inference.settings says which), and the caller's ``stop`` and ``min_k``."""
        e = self.rb.engine
        return {**{s.name: e[s.name] for s in UFP_ONC_RULE_SETTINGS}, "stop": stop, "min_k": min_k}

    def _ufp_onc(self, X: np.ndarray, stop: str, min_k: int = 1) -> UFPONCResult:
        return ufp_onc(X, **self._ufp_kwargs(stop, min_k))

    def _initial_k(self, res: UFPONCResult, notes: list[str]) -> int:
        ik = self.rb.engine["initial_k"]
        if isinstance(ik, int):
            ks = [p.k for p in res.partitions]
            if ik not in ks:
                notes.append(f"initial_k = {ik} could not be reached (the sweep stopped at K = {ks[-1]}: "
                             f"{res.stop_reason}); K = {ks[-1]} is used")
                return ks[-1]
            return ik
        return res.chosen_k

    # -- facts -----------------------------------------------------------------------------------

    def _facts(self, cluster: Cluster, scene: Scene, rec: ClusterRecord) -> Callable[[str], bool]:
        rb = self.rb
        done: dict[str, bool] = {c.check: c.passed for c in rec.checks}  # measured before: reuse

        def fact(name: str) -> bool:
            if name not in done:
                check = rb.checks[name]
                if check.predicate.needs_ground and scene.ground is None:
                    raise FitError(f"check '{name}' needs the ground plane, which is not known yet")
                try:
                    m = check.predicate.measure(cluster, scene, check.params)
                except KbsError:
                    raise
                except Exception as exc:  # a predicate's bug must name the predicate and cluster
                    raise PredicateError(f"predicate '{check.predicate.name}' failed on cluster {cluster.id} "
                                         f"({cluster.n_points} points): {type(exc).__name__}: {exc}") from exc
                done[name] = m.defined and check.passes(m.value)  # an undefined value fails its check
                cluster.cache[name] = m
                rec.checks.append(CheckRecord(
                    check=name, predicate=check.predicate.name, value=m.value if m.defined else None,
                    unit=check.predicate.unit_label(rb.length_unit), min=check.min, max=check.max,
                    passed=done[name], source=check.pos.short, note=m.undefined or ""))
            return done[name]

        return fact

    @staticmethod
    def _names(cond: Condition | None) -> list[str]:
        return [] if cond is None else list(dict.fromkeys(f.name for f in cond.facts()))

    def _judge(self, cluster: Cluster, scene: Scene, rec: ClusterRecord) -> tuple[str, Any]:
        """Evaluate the rules in order: the first whose condition holds acts."""
        fact = self._facts(cluster, scene, rec)
        for rule in self.rb.rules:
            if rule.condition.evaluate(fact):
                rec.rule, rec.rule_source = rule.name, rule.pos.short
                rec.decisive = self._names(rule.condition)
                return rule.action, rule
        return "accept", None

    def _label(self, cluster: Cluster, scene: Scene, rec: ClusterRecord) -> None:
        fact = self._facts(cluster, scene, rec)
        for lab in self.rb.labels:
            if lab.condition is None or lab.condition.evaluate(fact):
                rec.label = lab.name
                if rec.action == "accept":
                    rec.decisive = self._names(lab.condition)
                return
        rec.notes.append("no label's condition holds")

    # -- ground ----------------------------------------------------------------------------------

    def _ground(self, X: np.ndarray, candidates: list[tuple[Cluster, ClusterRecord]], info: dict) -> Ground | None:
        """The ground plane (scene.ground): fixed, or the closest large plane to the sensor among the
        candidates (the clusters of the initial partition with at least min_points points): a
        candidate passing the candidate check gives the plane of all its points; one that fails it
        but whose robust plane (scene.ground.plane) holds enough of its points within the inlier
        distance, and lies within its max_tilt of the fallback normal, gives that plane. The
        fallback only when no candidate gives a plane. ``info`` (the explanation's ``ground``)
        records which cluster, how it was found, and every candidate's verdict."""
        spec = self.rb.ground
        if not self.rb.needs_ground and spec.normal is None and spec.candidate is None and spec.plane is None \
                and self.rb.ground_model is None:
            return None
        if self.given_ground is not None:  # found once on the whole cloud this one is a tile of
            ground, given = self.given_ground
            info.update(copy.deepcopy(given))
            return ground
        if spec.normal is not None:
            return self._plane_from_normal(X, np.asarray(spec.normal, float), "fixed", info)
        fallback = np.asarray(spec.fallback, float)
        fallback = fallback / np.linalg.norm(fallback)
        best, no_plane, verdicts, tilted, planes = None, [], [], [], []
        if spec.candidate is not None or spec.plane is not None:
            provisional = Scene(self.sensor, None, self.rb.units)
            for cl, rec in candidates:
                if cl.n_points < spec.min_points:
                    continue
                if cl.geometry.degenerate:  # its points on a line: no plane to give
                    no_plane.append(cl.id)
                    verdicts.append({"cluster": cl.id, "points": cl.n_points,
                                     "why": f"degenerate: {cl.geometry.degeneracy}"})
                    continue
                found = self._candidate_plane(cl, rec, provisional)
                verdict = {"cluster": cl.id, "points": cl.n_points, **{k: v for k, v in found.items() if k != "plane"}}
                verdicts.append(verdict)
                if found["plane"] is None:
                    continue
                n, point, on = found["plane"]
                if (self.sensor - point) @ n < 0:  # point up, towards the sensor
                    n = -n
                tilt = float(np.degrees(np.arccos(min(1.0, abs(float(n @ fallback))))))
                verdict["angle_to_fallback"] = round(tilt, 3)
                max_tilt = spec.plane.max_tilt if spec.plane is not None else None
                if found["method"] == "robust plane" and max_tilt is not None and tilt > max_tilt:
                    verdict["why"] = f"its robust plane is {tilt:.1f} deg from the fallback normal > max_tilt {max_tilt:g} deg"
                    tilted.append(cl.id)
                    continue
                dist = float(np.sqrt(((on - self.sensor) ** 2).sum(axis=1).min()))
                verdict["distance"] = dist  # to the sensor, of its plane's nearest point
                planes.append((dist, cl, n, point, tilt, found, on, verdict))
        if planes:
            best = self._choose(X, planes)
        if best is None:
            tests = [f"passes '{spec.candidate}'"] if spec.candidate is not None else []
            if spec.plane is not None:
                tests.append(f"has a robust plane holding >= {spec.plane.min_inlier_share:.0%} of its points within "
                             f"{spec.plane.inlier_distance:g}{self.rb.length_unit and ' ' + self.rb.length_unit}")
            why = (f"no cluster of the initial partition with >= {spec.min_points} points {' or '.join(tests)}"
                   if tests else "scene.ground declares neither a candidate check nor a robust plane")
            if no_plane:
                why += (f" and has a plane ({len(no_plane)} degenerate)" if spec.plane is None else
                        f" ({len(no_plane)} degenerate: no plane)")
            if tilted:
                why += (f" within max_tilt {spec.plane.max_tilt:g} deg of the fallback (the robust plane of "
                        f"{', '.join(tilted[:5])}{' ...' if len(tilted) > 5 else ''} is tilted more)")
            shares = [f"{v['cluster']} {v['inlier_share']:.0%}" for v in verdicts
                      if v.get("inlier_share") is not None and v["cluster"] not in tilted]
            if shares:
                why += f" (the share of their points on their robust planes: {', '.join(shares[:5])})"
            info["note"] = f"{why}: the fallback normal {list(spec.fallback)} is used"
            if verdicts and spec.plane is not None:
                info.update(candidates=verdicts, unit=self.rb.length_unit)
            return self._plane_from_normal(X, np.asarray(spec.fallback, float), "fallback", info)
        dist, cl, n, point, tilt, found, _, verdict = best
        info.update(source=f"cluster {cl.id}", cluster=cl.id, normal=n.tolist(), point=point.tolist(),
                    distance_to_sensor=dist, thickness=found.get("plane_thickness", found["thickness"]),
                    distance=dist, unit=self.rb.length_unit, method=found["method"])
        if spec.support is not None:
            info.update(supported=verdict["supported"], candidates=verdicts,
                        support_band=[spec.support.min_height, spec.support.max_height])
        if spec.plane is not None:
            info.update(method=found["method"], angle_to_fallback=round(tilt, 3), candidates=verdicts,
                        unit=self.rb.length_unit)
            if found["method"] == "robust plane":
                info.update(inliers=found["inliers"], inlier_share=found["inlier_share"])
        return Ground(normal=n, point=np.asarray(point, float).copy(), source=f"cluster {cl.id}")

    def _choose(self, X: np.ndarray, planes: list[tuple]) -> tuple:
        """The ground among the candidates that give a plane (distance, cluster, normal, point,
        tilt, found, plane points, verdict): the closest to the sensor, or with
        scene.ground.choose 'supporting', the one with the most points standing on it (the
        closest of equals); each verdict gets its count ('supported')."""
        support = self.rb.ground.support
        if support is None:
            return min(planes, key=lambda p: p[0])  # the first of equals, as before
        for p in planes:
            p[7]["supported"] = supported_points(X, p[2], p[3], p[6], support.min_height, support.max_height)
        return min(planes, key=lambda p: (-p[7]["supported"], p[0]))

    def find_ground(self, X: np.ndarray) -> tuple[Ground | None, dict[str, Any]]:
        """The ground plane a run on ``X`` (n, 3) finds, and its explanation's ``ground``, without
        the rest of the run: the root's UFP-ONC partition and the ground among its clusters (as
        :meth:`run` does). A tiled run finds it once on the whole cloud and gives it to every tile
        (:attr:`given_ground`)."""
        X = np.ascontiguousarray(X, dtype=np.float64)
        n = X.shape[0]
        root = _Node("c", None, 0, np.arange(n), np.ones(n), np.ones(n))
        info: dict[str, Any] = {}
        try:
            fixed_k = isinstance(self.rb.engine["initial_k"], int)
            res = self._ufp_onc(X, "k_max" if self.rb.strategy == "global" or fixed_k else "first_max")
        except FitError:
            child = _Node("c0", "c", 1, root.idx, root.weight, root.path)
            return self._ground(X, [self._record(child, X)], info), info
        k0 = self._initial_k(res, [])
        children = self._initial_children(X, root, res, k0)
        del res
        return self._ground(X, [self._record(c, X) for c in children], info), info

    def _candidate_plane(self, cl: Cluster, rec: ClusterRecord, provisional: Scene) -> dict[str, Any]:
        """How a ground candidate gives a plane: ``plane`` (normal, point, its points) or None,
        ``method``, and what was measured."""
        spec = self.rb.ground
        geo = cl.geometry
        if spec.candidate is not None and self._facts(cl, provisional, rec)(spec.candidate):
            return {"plane": (geo.normal, geo.center, cl.X), "method": f"check '{spec.candidate}'",
                    "thickness": geo.thickness}
        out: dict[str, Any] = {"plane": None, "thickness": geo.thickness}
        if spec.candidate is not None:
            out["why"] = f"fails '{spec.candidate}'"
        if spec.plane is None:
            return out
        p = spec.plane
        rp = robust_plane(cl.X, p.inlier_distance, p.min_inlier_share)
        if rp is None:
            out["why"] = "no plane through its points"
            return out
        out.update(inliers=rp.n_inliers, inlier_share=round(rp.share, 4), plane_thickness=rp.thickness)
        unit = self.rb.length_unit and " " + self.rb.length_unit
        if rp.share < p.min_inlier_share:
            out["why"] = (f"its robust plane holds {rp.share:.0%} of its points within {p.inlier_distance:g}{unit}"
                          f" < {p.min_inlier_share:.0%}")
        elif rp.n_inliers < spec.min_points:
            out["why"] = f"its robust plane holds {rp.n_inliers} points < min_points {spec.min_points}"
        else:
            out.update(plane=(rp.normal, rp.point, cl.X[rp.inliers]), method="robust plane")
            out.pop("why", None)
        return out

    @staticmethod
    def _plane_from_normal(X: np.ndarray, n: np.ndarray, source: str, info: dict) -> Ground:
        n = n / np.linalg.norm(n)
        q = float(np.quantile(X @ n, 0.05))
        info.update(source=source, normal=n.tolist(), point=(q * n).tolist())
        return Ground(normal=n, point=q * n, source=source)

    # -- records ---------------------------------------------------------------------------------

    def _record(self, node: _Node, X: np.ndarray) -> tuple[Cluster, ClusterRecord]:
        cl = Cluster(node.id, X[node.idx], node.weight)
        rec = ClusterRecord(id=node.id, parent=node.parent, depth=node.depth, n_points=int(node.idx.size))
        if node.idx.size:
            geo = cl.geometry
            rec.descriptors = {
                "center": geo.center.tolist(), "normal": None if geo.degenerate else geo.normal.tolist(),
                "thickness": geo.thickness, "eigenvalues": geo.eigenvalues.tolist(), "mass": geo.mass,
            }
            if geo.degenerate:
                rec.notes.append(f"degenerate: {geo.degeneracy}, no plane: normal/ground angle undefined")
        return cl, rec

    @staticmethod
    def _apd(res: UFPONCResult, chosen: int) -> APDCurve:
        return APDCurve(tuple(p.k for p in res.partitions), tuple(p.apd for p in res.partitions), chosen)

    @staticmethod
    def _children_from_memberships(node: _Node, u: np.ndarray) -> list[_Node]:
        hard = u.argmax(axis=1)
        parts = [np.flatnonzero(hard == j) for j in range(u.shape[1])]
        order = sorted((j for j in range(len(parts)) if parts[j].size), key=lambda j: -parts[j].size)
        return [_Node(f"{node.id}.{i}" if node.parent is not None else f"c{i}", node.id, node.depth + 1,
                      node.idx[parts[j]], u[parts[j], j], node.path[parts[j]] * u[parts[j], j])
                for i, j in enumerate(order)]

    # -- strategies ------------------------------------------------------------------------------

    def run(self, X: np.ndarray) -> Segmentation:
        """Segment points ``X`` (n, 3)."""
        t0 = time.perf_counter()
        X = np.ascontiguousarray(X, dtype=np.float64)
        if X.ndim != 2 or X.shape[1] != 3 or X.shape[0] == 0:
            raise FitError(f"expected a non-empty (n, 3) cloud, got shape {X.shape}")
        n = X.shape[0]
        root = _Node("c", None, 0, np.arange(n), np.ones(n), np.ones(n))
        _, root_rec = self._record(root, X)  # its descriptors; the cluster itself (a copy of X) is not kept
        root_rec.action = "partition"
        records: dict[str, ClusterRecord] = {"c": root_rec}
        global_mode = self.rb.strategy == "global"
        ground_info: dict[str, Any] = {}
        try:
            if global_mode:
                sweep = self._sweep(X)
            else:
                fixed_k = isinstance(self.rb.engine["initial_k"], int)
                res = self._ufp_onc(X, "k_max" if fixed_k else "first_max")
        except FitError as exc:  # too few or degenerate points: the scene is one cluster
            root_rec.notes.append(f"the scene was not partitioned: {exc}")
            child = _Node("c0", "c", 1, root.idx, root.weight, root.path)
            root_rec.children = ["c0"]
            c_cl, c_rec = self._record(child, X)
            records["c0"] = c_rec
            scene = Scene(self.sensor, self._ground(X, [(c_cl, c_rec)], ground_info), self.rb.units)
            self._judge_leaf(child, c_cl, c_rec, scene)
            leaves = [] if c_rec.action == "reject" else [(child, c_cl, c_rec)]
            return self._finish(X, leaves, scene, records, ground_info, [], t0)
        if global_mode:
            notes: list[str] = []
            steps: list[dict[str, Any]] = []
            leaves, scene = self._run_global(X, root, sweep, records, ground_info, notes, steps)
            return self._finish(X, leaves, scene, records, ground_info, notes, t0, sweep=steps)
        notes = list(res.notes)
        k0 = self._initial_k(res, notes)
        root_rec.apd = self._apd(res, k0)
        children = self._initial_children(X, root, res, k0)
        del res, root  # the (n, K) memberships and the root's arrays: the children hold copies of their part
        leaves, scene = self._run_divisive(X, children, records, ground_info, notes)
        seg = self._finish(X, leaves, scene, records, ground_info, notes, t0)
        return seg

    def _initial_children(self, X, root, res, k) -> list[_Node]:
        part = res.partition(k)
        u = res.memberships if k == res.chosen_k else part.predict_proba(X)
        return self._children_from_memberships(root, u)

    def _run_divisive(self, X, children, records, ground_info, notes):
        """Breadth first, one level of the split tree (a wave) at a time: every cluster of the wave
        is judged, the UFP-ONC splits it asks for are started (side by side when jobs > 1), then
        the decisions are applied in order — exactly the order of a first-in first-out queue, so
        the optional max_clusters, when a rule file sets it, stops the same clusters whatever the
        number of jobs. Without it, what happens under a cluster depends on its points alone."""
        rb = self.rb
        records["c"].children = [c.id for c in children]
        wave = [(c, *self._record(c, X)) for c in children]
        children.clear()  # the wave holds them now: a node split below is freed with its wave
        scene = Scene(self.sensor, self._ground(X, [(cl, rec) for _, cl, rec in wave], ground_info), rb.units)
        leaves: list[tuple[_Node, Cluster, ClusterRecord]] = []
        n_clusters = len(wave)
        split_kw = self._ufp_kwargs("first_max", rb.engine["split_min_k"])
        with _Splitter(self, split_kw) as splitter:
            while wave:
                judged = []
                for node, cl, rec in wave:
                    records[node.id] = rec
                    action, rule = self._judge(cl, scene, rec)
                    job = None
                    if action == "split" and self._cannot_split(node, 0) is None:  # max_clusters: known later
                        job = splitter.submit(cl.X)  # the cluster's points, X[node.idx]: no second copy
                    judged.append((node, cl, rec, action, rule, job))
                wave = []
                for node, cl, rec, action, rule, job in judged:
                    if action == "reject":
                        rec.action = "reject"
                        continue
                    if action == "accept":
                        rec.action = "accept"
                        leaves.append((node, cl, rec))
                        continue
                    why_not = self._cannot_split(node, n_clusters)
                    kids: list[_Node] = []
                    if why_not is None:
                        try:
                            kids = self._split(node, X, cl, rec, action, rule, job)
                        except FitError as exc:
                            why_not = "split_failed", f"the split failed: {exc}"
                        if why_not is None and len(kids) < 2:
                            why_not = "single_cluster", "the split gave a single cluster"
                    if why_not is not None:
                        self._stop(rec, *why_not)
                        leaves.append((node, cl, rec))
                        continue
                    rec.action = action
                    rec.children = [k.id for k in kids]
                    n_clusters += len(kids) - 1
                    kid_records = [(k, *self._record(k, X)) for k in kids]
                    if action == "split_components":
                        self._inherit_connexity(rule, kid_records)
                    wave.extend(kid_records)
                    if self.progress:
                        self.progress(f"{node.id} split in {len(kids)}")
        return leaves, scene

    def _inherit_connexity(self, rule, children) -> None:
        """A child of a split along connected components is one component of its parent's
        alpha-complex: its connexity checks hold at the parent's alpha, and are recorded so rather
        than measured again with a smaller alpha of its own (which would cut it again and again
        along the sampling pattern, e.g. LiDAR rings)."""
        names = {f.name for f in rule.condition.facts() if self.rb.checks[f.name].predicate.name == "connexity"}
        for _, cl, rec in children:
            for name in names:
                check = self.rb.checks[name]
                passed = check.passes(1.0)
                cl.cache[name] = Measurement(1.0)
                rec.checks.append(CheckRecord(
                    check=name, predicate="connexity", value=1.0, unit=check.predicate.unit_label(self.rb.length_unit),
                    min=check.min, max=check.max, passed=passed, source=check.pos.short,
                    note=f"one component of {rec.parent}, at its alpha"))

    def _judge_leaf(self, node: _Node, cl: Cluster, rec: ClusterRecord, scene: Scene) -> None:
        """Judge a cluster that cannot be split whatever the rules say (the scene could not be
        partitioned at all)."""
        action, _ = self._judge(cl, scene, rec)
        if action in ("split", "split_components"):
            self._stop(rec, "unpartitioned", "it cannot be split: the engine could not partition these points")
        else:
            rec.action = action

    def _cannot_split(self, node: _Node, n_clusters: int) -> tuple[str, str] | None:
        """(kind, note) of the limit that keeps ``node`` from being split, or None. ``n_clusters``
        counts the clusters of the whole tree so far; only the optional max_clusters uses it."""
        lim = self.rb.limits
        if node.depth >= lim["max_depth"]:
            return "max_depth", f"limit reached: max_depth = {lim['max_depth']}"
        if node.idx.size < lim["min_points"]:
            return "min_points", f"limit reached: {node.idx.size} points < min_points = {lim['min_points']}"
        cap = lim.get("max_clusters")
        if cap is not None and n_clusters >= cap:
            return "max_clusters", f"limit reached: max_clusters = {cap}"
        return None

    def _stop(self, rec: ClusterRecord, kind: str, note: str) -> None:
        """Keep a cluster a rule wanted split, saying what stopped it."""
        setting = STOP_KINDS[kind]
        value = None
        if setting is not None:
            section, key = setting.split(".")
            value = (self.rb.limits if section == "limits" else self.rb.engine).get(key)
        rec.action = "limit"
        rec.limit = {"kind": kind, "setting": setting, "value": value}
        rec.notes.append(note)

    def _split(self, node: _Node, X: np.ndarray, cl: Cluster, rec: ClusterRecord, action: str, rule,
               job: _Job | None = None) -> list[_Node]:
        if action == "split":
            res = job.result() if job is not None else \
                self._ufp_onc(X[node.idx], "first_max", min_k=self.rb.engine["split_min_k"])
            k = res.chosen_k
            if k < 2:
                if len(res.partitions) < 2:
                    raise FitError("UFP-ONC found no second cluster")
                k = 2
            rec.apd = self._apd(res, k)
            u = res.memberships if k == res.chosen_k else res.partition(k).predict_proba(X[node.idx])
            sub = _Node(node.id, node.parent, node.depth, node.idx, node.weight, node.path)
            kids = self._children_from_memberships(sub, u)
            for kid in kids:  # children ids are path-like under this node
                kid.parent = node.id
            return kids
        # split_components: reuse the components of the failed connexity check
        conn: Connexity | None = None
        for f in rule.condition.facts():
            m = cl.cache.get(f.name)
            if m is not None and isinstance(m.details, Connexity):
                conn = m.details
                break
        if conn is None or conn.n_significant < 2:
            raise FitError("no two significant connected components to split along")
        geo = cl.geometry
        labels = assign_to_nearest(project_on_plane(cl.X, geo.center, geo.normal), conn.labels, conn.significant)
        kids = []
        for i in range(conn.n_significant):
            sel = np.flatnonzero(labels == i)
            if sel.size:
                kids.append(_Node(f"{node.id}.{len(kids)}", node.id, node.depth + 1, node.idx[sel],
                                  np.ones(sel.size), node.path[sel]))
        return kids

    # -- the global strategy (the seed paper's) ----------------------------------------------------

    def _sweep(self, X: np.ndarray) -> IncrementalSweep:
        """The whole scene's incremental sweep, at K = 1. A cluster dies under the engine's own
        minimum size (0.1 % of the points) or limits.min_points, whichever is smaller: a K + 1 sought
        for a small thick cluster must not kill the small planar clusters beside it (on the
        generated polyhedral scenes, the engine's 0.1 % stopped the sweep before every face was found)."""
        e = self.rb.engine
        return IncrementalSweep(X, m=e["m"], tol=e["tol"], fcm_tol=e["fcm_tol"], max_iter=e["max_iter"],
                                min_variance=e["min_variance"],
                                max_condition=e["max_condition"], max_fit_points=e["max_fit_points"],
                                min_cluster_size=min(float(self.rb.limits["min_points"]), max(4.0, 1e-3 * len(X))))

    def _global_first_k(self, sweep: IncrementalSweep, notes: list[str]) -> tuple[int, list[tuple[int, float]]]:
        """Grow the sweep with UFP-ONC's own incremental init (way V) up to APD's first local
        maximum (or the rule file's fixed initial_k), then go back to that K."""
        e = self.rb.engine
        ik = e["initial_k"]
        while sweep.k < e["k_max"]:
            parts = sweep.partitions
            if isinstance(ik, int) and sweep.k >= ik:
                break
            if not isinstance(ik, int) and len(parts) >= 3 and parts[-1].apd <= parts[-2].apd:
                break  # the first local maximum (among K >= 2) is confirmed
            if sweep.grow() is None:
                break
        eligible = [p for p in sweep.partitions if p.k >= 2] or sweep.partitions
        if isinstance(ik, int):
            k0 = min(ik, sweep.k)
            if k0 < ik:
                notes.append(f"initial_k = {ik} could not be reached (the sweep stopped at K = {k0}); K = {k0} is used")
        else:
            k0 = eligible[first_local_max([p.apd for p in eligible])].k
        first = [(p.k, p.apd) for p in sweep.partitions]
        sweep.back_to(k0)
        return k0, first

    @staticmethod
    def _partition_children(X, root: _Node, sweep: IncrementalSweep) -> list[tuple[_Node, int]]:
        """The clusters of the sweep's last partition (ids c0, c1, ... by decreasing size), each with
        its column in the partition."""
        u = sweep.memberships(X)
        hard = u.argmax(axis=1)
        parts = [np.flatnonzero(hard == j) for j in range(u.shape[1])]
        order = sorted((j for j in range(len(parts)) if parts[j].size), key=lambda j: -parts[j].size)
        return [(_Node(f"c{i}", root.id, 1, root.idx[parts[j]], u[parts[j], j], u[parts[j], j]), j)
                for i, j in enumerate(order)]

    def _run_global(self, X, root, sweep: IncrementalSweep, records, ground_info, notes, steps):
        """The seed paper's strategy: the whole scene's K-partition, K from APD's first local
        maximum; while a rule wants some cluster split (a heuristic fails on it), the (K+1)-partition
        of the whole scene, seeded from the K-partition with the new prototype in the largest failing
        cluster (its prototype split in two along its largest axis; when that cluster's new
        prototype dies, the next failing cluster, then UFP-ONC's own way V), until no rule wants a
        split or K = k_max. Every K visited is recorded in ``steps`` (the explanation's ``sweep``):
        its clusters with centre, axes and outcome, the cluster its new prototype was seeded in."""
        rb = self.rb
        k_max = rb.engine["k_max"]
        min_points = rb.limits["min_points"]
        k0, first = self._global_first_k(sweep, notes)
        scene = None
        seeded: str | None = None
        while True:
            kids = self._partition_children(X, root, sweep)
            judged = [(node, j, *self._record(node, X)) for node, j in kids]
            if scene is None:  # the ground plane from the first partition judged, as the divisive strategy does
                scene = Scene(self.sensor, self._ground(X, [(cl, rec) for _, _, cl, rec in judged], ground_info),
                              rb.units)
            failing = []
            for node, j, cl, rec in judged:
                action, rule = self._judge(cl, scene, rec)
                rec.action = action
                if action in ("split", "split_components"):
                    if node.idx.size < min_points:
                        self._stop(rec, "min_points", f"limit reached: {node.idx.size} points < min_points = {min_points}")
                    else:
                        failing.append((node, j))
            steps.append(self._step_record(sweep, judged, seeded))
            if not failing or sweep.k >= k_max:
                break
            grown = None
            for node, j in failing:  # the largest first (ids are by decreasing size)
                if sweep.grow(target=j, name=f"{node.id} of K={sweep.k}") is not None:
                    grown = node.id
                    break
            if grown is None and sweep.grow() is None:
                break
            seeded = grown or "anywhere (way V)"
            steps[-1]["next"] = seeded
        k = sweep.k
        for st in steps:
            st["kept"] = st["k"] == k
        records["c"].children = [node.id for node, _, _, _ in judged]
        curve = sorted(dict(first + [(p.k, p.apd) for p in sweep.partitions]).items())  # every K computed
        records["c"].apd = APDCurve(tuple(kk for kk, _ in curve), tuple(a for _, a in curve), chosen=k)
        records["c"].notes.append(f"global strategy: K = {k0} (APD's first local maximum) to K = {k} "
                                  f"({len(steps)} partitions judged); K = {k} kept")
        notes.extend(sweep.notes)
        leaves = []
        for node, _, cl, rec in judged:
            records[node.id] = rec
            if rec.action in ("split", "split_components"):
                if k >= k_max:
                    self._stop(rec, "k_max", f"limit reached: no partition of the scene beyond K = {k} "
                                             f"(k_max = {k_max})")
                else:
                    self._stop(rec, "unpartitioned", f"it cannot be split: no partition of the scene beyond K = {k} "
                                                     "(every new prototype died)")
            if rec.action != "reject":
                leaves.append((node, cl, rec))
        return leaves, scene

    def _step_record(self, sweep: IncrementalSweep, judged, seeded: str | None) -> dict[str, Any]:
        """One K of the global strategy, as data: its clusters (id, points, centre, covariance axes,
        what the rules decided and the checks that failed)."""
        part = sweep.partitions[-1]
        clusters = []
        for node, j, cl, rec in judged:
            geo = cl.geometry
            decisive = [{"check": c.check, "predicate": c.predicate, "value": c.value, "unit": c.unit, "min": c.min,
                         "max": c.max, "passed": c.passed, "source": c.source} for c in rec.decisive_checks()]
            clusters.append({"id": node.id, "column": int(j), "points": int(node.idx.size),
                             "center": geo.center.tolist(), "eigenvalues": geo.eigenvalues.tolist(),
                             "eigenvectors": geo.eigenvectors.tolist(), "action": rec.action,
                             "rule": rec.rule, "rule_source": rec.rule_source, "decisive": decisive,
                             "limit": rec.limit})
        return {"k": part.k, "apd": part.apd, "seeded_in": seeded, "clusters": clusters}

    # -- labels, merge, output -------------------------------------------------------------------

    def _finish(self, X, leaves, scene, records, ground_info, notes, t0, sweep=None) -> Segmentation:
        rb = self.rb
        for _node, cl, rec in leaves:
            self._label(cl, scene, rec)
        if rb.ground_model is not None and leaves:
            leaves = self._post_ground(X, leaves, scene, ground_info)
        groups = self._merge(leaves)
        n = X.shape[0]
        cluster = np.full(n, -1, dtype=np.int32)
        label = np.full(n, -1, dtype=np.int32)
        membership = np.zeros(n, dtype=np.float32)
        groups.sort(key=lambda g: -sum(leaves[i][0].idx.size for i in g))
        out_clusters = []
        for gi, members in enumerate(groups):
            ids = [leaves[i][2].id for i in members]
            lab = leaves[members[0]][2].label
            li = rb.label_names.index(lab) if lab in rb.label_names else -1
            size = 0
            for i in members:
                node, cl, rec = leaves[i]
                cluster[node.idx] = gi
                label[node.idx] = li
                membership[node.idx] = node.path
                rec.output_index = gi
                size += node.idx.size
                if len(members) > 1:
                    rec.notes.append(f"merged with {len(members) - 1} other coplanar {lab} cluster"
                                     f"{'s' if len(members) > 2 else ''} into output cluster {gi}")
            out_clusters.append({"index": gi, "ids": ids, "label": lab, "n_points": int(size),
                                 "descriptors": leaves[members[0]][2].descriptors if len(members) == 1 else
                                 self._group_descriptors(X, [leaves[i][0] for i in members])})
        expl = Explanation(rule_base=rb.name, rule_file=rb.path, strategy=rb.strategy, label_names=rb.label_names,
                           records=records, root="c", ground=ground_info, notes=notes, catalogue=Catalogue.of(rb),
                           sweep=sweep or [])
        return Segmentation(cluster=cluster, label=label, membership=membership, label_names=rb.label_names,
                            explanation=expl, clusters=out_clusters, seconds=time.perf_counter() - t0)

    # -- the local ground surface: relabel and ground contact ----------------------------------------

    def _local_ground(self, X, leaves, scene: Scene):
        from kbs.knowledge.groundmodel import LocalGround

        spec = self.rb.ground_model
        mine = [i for i, (_, _, rec) in enumerate(leaves) if rec.label == spec.label]
        index = np.concatenate([leaves[i][0].idx for i in mine]) if mine else np.zeros(0, dtype=np.int64)
        owner = np.concatenate([np.full(leaves[i][0].idx.size, i) for i in mine]) if mine else np.zeros(0, dtype=np.int64)
        model = LocalGround.build(X, index, scene.ground.normal, scene.ground.point, neighbours=spec.neighbours,
                                  radius=spec.radius, owners=np.searchsorted(mine, owner) if mine else owner,
                                  owner_ids=tuple(leaves[i][2].id for i in mine), workers=self.jobs)
        return model, owner

    def _post_ground(self, X, leaves, scene: Scene, ground_info: dict):
        """post.ground_model: build the local ground surface from the clusters of its label, apply
        post.relabel (whose conditions may measure against it), then post.ground_release and
        post.ground_contact, both against the same surface."""
        rb = self.rb
        spec = rb.ground_model
        if scene.ground is None:  # the rule base has no way to orient the ground: say so, do nothing
            ground_info["local_model"] = {"note": "no ground plane: post.ground_model skipped"}
            return leaves
        model, owner = self._local_ground(X, leaves, scene)
        ground_info["local_model"] = {"label": spec.label, "points": model.n_points, "neighbours": spec.neighbours,
                                      "radius": spec.radius, "source": spec.pos.short}
        if rb.relabel:
            post_scene = Scene(scene.sensor, scene.ground, scene.unit, ground_model=model)
            changed = 0
            for _node, cl, rec in leaves:
                for r in rb.relabel:
                    if rec.label != r.source or not r.condition.evaluate(self._facts(cl, post_scene, rec)):
                        continue
                    names = self._names(r.condition)
                    rec.relabel = {"rule": r.name, "source": r.pos.short, "from": r.source, "to": r.target,
                                   "checks": names}
                    rec.label = r.target
                    changed += 1
                    break
            ground_info["local_model"]["relabelled"] = changed
            if changed:
                model, owner = self._local_ground(X, leaves, scene)
                ground_info["local_model"]["points_after_relabel"] = model.n_points
        if model.n_points:
            if rb.release is not None:
                self._ground_release(X, leaves, model, ground_info)
            if rb.contact is not None:
                self._ground_contact(X, leaves, model, owner,
                                     Scene(scene.sensor, scene.ground, scene.unit, ground_model=model))
        kept = []
        for lf in leaves:
            if lf[0].idx.size:
                kept.append(lf)
            else:
                lf[2].notes.append("every point of it left for other clusters: no output cluster")
        return kept

    @staticmethod
    def _receive(leaves, moved_in: dict, note: str) -> None:
        """Append moved points (idx, weight, path) to their destination leaves, with a note."""
        for t, parts in moved_in.items():
            node, _, rec = leaves[t]
            n_in = sum(p[0].size for p in parts)
            node.idx = np.concatenate([node.idx] + [p[0] for p in parts])
            node.weight = np.concatenate([node.weight] + [p[1] for p in parts])
            node.path = np.concatenate([node.path] + [p[2] for p in parts])
            rec.notes.append(note.format(n=f"{n_in:,}"))

    @staticmethod
    def _give(node: _Node, move: np.ndarray, targets: np.ndarray, moved_in: dict) -> list[int]:
        """Take the points ``move`` (mask) out of ``node``, bound for leaves ``targets``; returns
        the destination leaves."""
        dest = np.unique(targets)
        pos = np.flatnonzero(move)
        for t in dest:
            sel = pos[targets == t]
            moved_in.setdefault(int(t), []).append((node.idx[sel], node.weight[sel], node.path[sel]))
        keep = ~move
        node.idx, node.weight, node.path = node.idx[keep], node.weight[keep], node.path[keep]
        return [int(t) for t in dest]

    #: points per batch of surface queries in the post steps
    SURFACE_BATCH = 1 << 18

    @classmethod
    def _surface_batches(cls, X, todo, model, may_matter=None):
        """For each leaf of ``todo`` in order: (heights above the local surface, positions of the
        nearest surface points) of its points, asked for batches of leaves of about
        ``SURFACE_BATCH`` points together (few small queries, bounded temporaries).

        ``may_matter(hp, lo, hi)``: which points the caller needs, from their heights above the
        ground plane and the bounds of the surface under them (:meth:`LocalGround.height_bounds`);
        the others are not asked for and come back as NaN (height) and -1 (nearest). The caller
        promises that their outcome is the same either way (the bounds decide it)."""
        batch: list = []
        size = 0
        for i, lf in enumerate(todo):
            batch.append(lf)
            size += lf[0].idx.size
            if size < cls.SURFACE_BATCH and i + 1 < len(todo):
                continue
            P = X[np.concatenate([b[0].idx for b in batch])]
            hp = (P - model.point) @ model.normal
            bounds = model.height_bounds(P) if may_matter is not None else None
            if bounds is None:
                ground, nearest = model.query(P)
                h = hp - ground
            else:
                ask = np.flatnonzero(may_matter(hp, *bounds))
                h = np.full(P.shape[0], np.nan)
                nearest = np.full(P.shape[0], -1, dtype=np.int64)
                ground, nearest[ask] = model.query(P[ask])
                h[ask] = hp[ask] - ground
            stop = 0
            for b in batch:
                start, stop = stop, stop + b[0].idx.size
                yield h[start:stop], nearest[start:stop]
            batch, size = [], 0

    def _ground_contact(self, X, leaves, model, owner, scene: Scene) -> None:
        """post.ground_contact: points of other clusters lying on the surface join the ground
        cluster under them."""
        spec = self.rb.contact
        gl = self.rb.ground_model.label
        unit = self.rb.length_unit
        moved_in: dict[int, list] = {}
        todo = [lf for lf in leaves if lf[2].label in spec.sources and lf[2].label != gl and lf[0].idx.size
                and (spec.condition is None or spec.condition.evaluate(self._facts(lf[1], scene, lf[2])))]
        # queries for batches of clusters (the surface does not change while points move: they
        # are received after the loop)
        tol = spec.tolerance
        # a point whose surface bounds put it farther than the tolerance from any height the
        # surface can have under it does not move: it is not asked for
        near = lambda hp, lo, hi: (hp - hi <= tol) & (hp - lo >= -tol)  # noqa: E731
        for (node, _cl, rec), (h, nearest) in zip(todo, self._surface_batches(X, todo, model, near)):
            move = np.abs(np.nan_to_num(h, nan=np.inf)) <= spec.tolerance
            n_move, size = int(move.sum()), node.idx.size
            if not n_move:
                continue
            dest = self._give(node, move, owner[nearest[move]], moved_in)
            rec.contact = n_move
            ids = [leaves[t][2].id for t in dest]
            rec.notes.append(f"{n_move:,} of its {size:,} points lie within {spec.tolerance:g} {unit} of the local "
                             f"ground surface and joined {gl} cluster{'s' if len(ids) > 1 else ''} "
                             f"{', '.join(ids[:5])}{' ...' if len(ids) > 5 else ''} [{spec.pos.short} ground_contact]")
        self._receive(leaves, moved_in, "{n} points of other clusters in contact with it joined it "
                      f"[{spec.pos.short} ground_contact]")

    def _ground_release(self, X, leaves, model, ground_info: dict) -> None:
        """post.ground_release: points of the ground clusters standing above the surface (a tuft,
        the bottom of a bush inside a ground cluster) join the nearest cluster of the target label."""
        from scipy.spatial import cKDTree

        spec = self.rb.release
        gl = self.rb.ground_model.label
        unit = self.rb.length_unit
        targets = [li for li, (node, _, rec) in enumerate(leaves) if rec.label == spec.target and node.idx.size]
        if not targets:
            ground_info["local_model"]["release_note"] = f"no {spec.target} cluster to take released points"
            return
        t_idx = np.concatenate([leaves[li][0].idx for li in targets])
        t_owner = np.concatenate([np.full(leaves[li][0].idx.size, li) for li in targets])
        tree = cKDTree(X[t_idx])
        moved_in: dict[int, list] = {}
        total = 0
        todo = [lf for lf in leaves if lf[2].label == gl and lf[0].idx.size]
        # queries for batches of clusters (points move only after the loop)
        tol = spec.tolerance
        above = lambda hp, lo, hi: hp - lo > tol  # noqa: E731 (no surface height under it is low enough: stays)
        for (node, _cl, rec), (h, _) in zip(todo, self._surface_batches(X, todo, model, above)):
            move = np.nan_to_num(h, nan=-np.inf) > spec.tolerance
            n_move, size = int(move.sum()), node.idx.size
            if not n_move:
                continue
            _, j = tree.query(X[node.idx[move]], workers=self.jobs if n_move >= 4096 else 1)
            dest = self._give(node, move, t_owner[j], moved_in)
            rec.released = n_move
            total += n_move
            ids = [leaves[t][2].id for t in dest]
            rec.notes.append(f"{n_move:,} of its {size:,} points stand more than {spec.tolerance:g} {unit} above the "
                             f"local ground surface and joined {spec.target} cluster{'s' if len(ids) > 1 else ''} "
                             f"{', '.join(ids[:5])}{' ...' if len(ids) > 5 else ''} [{spec.pos.short} ground_release]")
        ground_info["local_model"]["released"] = total
        self._receive(leaves, moved_in, "{n} points released by ground clusters joined it (the nearest "
                      f"{spec.target} cluster) [{spec.pos.short} ground_release]")

    @staticmethod
    def _group_descriptors(X, nodes: list[_Node]) -> dict[str, Any]:
        from kbs.inference import cluster_geometry

        idx = np.concatenate([nd.idx for nd in nodes])
        geo = cluster_geometry(X[idx], np.concatenate([nd.weight for nd in nodes]))
        return {"center": geo.center.tolist(), "normal": geo.normal.tolist(), "thickness": geo.thickness,
                "eigenvalues": geo.eigenvalues.tolist(), "mass": geo.mass}

    def _merge(self, leaves) -> list[list[int]]:
        """Groups of leaf indices: clusters of the merge label whose planes agree (normals within
        max_angle, each centre within max_offset of the other's plane) are merged, transitively."""
        groups = np.arange(len(leaves))
        spec = self.rb.merge
        if spec is not None:
            cand = np.array([i for i, (_, cl, rec) in enumerate(leaves)
                             if rec.label == spec.label and not cl.geometry.degenerate], dtype=int)  # no plane
            if cand.size > 1:
                geos = [leaves[i][1].geometry for i in cand]
                N = np.array([g.normal for g in geos])
                C = np.array([g.center for g in geos])
                cos = np.clip(np.abs(N @ N.T), 0.0, 1.0)
                off = np.abs(np.einsum("id,ijd->ij", N, C[None, :, :] - C[:, None, :]))  # j's centre to i's plane
                ok = (np.degrees(np.arccos(cos)) <= spec.max_angle) & (np.maximum(off, off.T) <= spec.max_offset)
                from scipy.sparse.csgraph import connected_components

                _, comp = connected_components(ok, directed=False)
                for c in np.unique(comp):  # each merged group takes its first member's number
                    members = cand[comp == c]
                    groups[members] = members[0]
        out: dict[int, list[int]] = {}
        for i, g in enumerate(groups):
            out.setdefault(int(g), []).append(i)
        return list(out.values())


def segment(X: np.ndarray, rule_base: RuleBase, *, sensor: Any = None, jobs: int = 1) -> Segmentation:
    """Segment points ``X`` (n, 3) with a rule base (see :class:`Interpreter`)."""
    return Interpreter(rule_base, sensor=sensor, jobs=jobs).run(X)


# -- running the splits of a wave side by side -------------------------------------------------------


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity, where the system tells)."""
    import os

    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def _shutdown_pool(pool) -> None:
    pool.shutdown(wait=True, cancel_futures=True)


def _split_job(X: np.ndarray, kwargs: dict[str, Any]) -> tuple[str, Any]:
    """In a worker: UFP-ONC on one cluster's points; a FitError travels back as its message."""
    try:
        return "ok", ufp_onc(X, **kwargs)
    except FitError as exc:
        return "error", str(exc)


class _Job:
    """A split under way: in a worker process (``future``) or not started yet (computed here, on
    demand, when ``jobs`` is 1)."""

    def __init__(self, X: np.ndarray, kwargs: dict[str, Any], future=None) -> None:
        self.X, self.kwargs, self.future = X, kwargs, future

    def result(self) -> UFPONCResult:
        from concurrent.futures.process import BrokenProcessPool

        try:
            status, value = self.future.result() if self.future is not None else _split_job(self.X, self.kwargs)
        except BrokenProcessPool:  # a worker died (killed, out of memory): do this split here
            status, value = _split_job(self.X, self.kwargs)
        self.X = self.future = None  # the points and the result are the caller's now: nothing kept here
        if status == "error":
            raise FitError(value)
        return value


class _Splitter:
    """Starts the UFP-ONC splits of a wave: in the interpreter's pool of ``jobs`` worker
    processes (forked, so nothing is imported again; started at the first split and kept for
    the next runs, so a loaded segmenter does not fork again frame after frame), or lazily in
    this process when ``jobs`` is 1."""

    def __init__(self, owner: Interpreter, kwargs: dict[str, Any]) -> None:
        self.owner, self.jobs, self.kwargs = owner, owner.jobs, kwargs
        self.jobs_started: list[_Job] = []

    def __enter__(self) -> Self:
        return self

    def __exit__(self, exc_type, *exc) -> None:
        if exc_type is not None:  # interrupted or failed: do not leave splits running for the next run
            for job in self.jobs_started:
                if job.future is not None:
                    job.future.cancel()
            if exc_type is not FitError and not issubclass(exc_type, KbsError):
                self.owner.close()

    def submit(self, X: np.ndarray) -> _Job:
        if self.jobs <= 1:
            return _Job(X, self.kwargs)
        from concurrent.futures.process import BrokenProcessPool

        try:
            future = self.owner._worker_pool().submit(_split_job, X, self.kwargs)
        except BrokenProcessPool:  # a worker died in an earlier wave or run: split here, fresh pool next run
            self.owner.close()
            return _Job(X, self.kwargs)
        job = _Job(X, self.kwargs, future)
        self.jobs_started.append(job)
        return job
