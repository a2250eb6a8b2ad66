"""The ground plane of a scene (``scene.ground``): fixed by the rule file, or found from the data as
the seed paper says: the closest large plane to the sensor among the clusters of the initial
partition (or, with ``choose: supporting``, the plane most points stand on), with the fallback
normal only when no candidate gives a plane. The explanation's ``ground`` section records which
cluster, how it was found, and every candidate's verdict."""
from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from kbs.arrays import rows
from kbs.geometry.groundplane import robust_plane, supported_points
from kbs.inference.voxel import bounds
from kbs.knowledge.groundfacts import GroundCandidate, GroundFacts
from kbs.knowledge.predicates import Cluster, Ground, Scene
from kbs.knowledge.state import Draft


def find(run: Any, X: np.ndarray, candidates: list[tuple[Cluster, Draft]]) -> tuple[Ground | None, GroundFacts]:
    """The ground plane (scene.ground): fixed, or the closest large plane to the sensor among the
    candidates (the clusters of the initial partition with at least min_points points): a
    candidate passing the candidate check gives the plane of all its points; one that fails it
    but whose robust plane (scene.ground.plane) holds enough of its points within the inlier
    distance, and lies within its max_tilt of the fallback normal, gives that plane; with
    sensor_above, a plane with the sensor on the side opposite the fallback normal is refused. The
    fallback only when no candidate gives a plane. Returns the plane (None: the rule base uses
    none) and the explanation's ``ground`` facts: which cluster, how it was found, and every
    candidate's verdict."""
    spec = run.rule_base.ground
    if not _uses_ground(run.rule_base):
        return None, GroundFacts()
    if run.given_ground is not None:  # found once on the whole cloud this one is a tile of
        return run.given_ground
    if spec.normal is not None:
        return plane_from_normal(X, np.asarray(spec.normal, float), "fixed", GroundFacts())
    fallback = np.asarray(spec.fallback, float)
    fallback = fallback / np.linalg.norm(fallback)
    best, no_plane, verdicts, planes = None, [], [], []
    tilted: list[str] = []  # the candidates a plane of which was refused for its tilt
    under: list[str] = []  # ... for the sensor under it (sensor_above)
    if spec.candidate is not None or spec.plane is not None:
        provisional = Scene(run.sensor, None, run.rule_base.units)
        for cl, rec in candidates:
            if cl.n_points < spec.min_points:
                continue
            if cl.geometry.degenerate:  # its points on a line: no plane to give
                no_plane.append(cl.id)
                verdicts.append({"cluster": cl.id, "points": cl.n_points,
                                 "why": f"degenerate: {cl.geometry.degeneracy}"})
                continue
            n_planes = spec.plane.planes if spec.plane is not None else 1
            rest = None  # positions in the cluster of the points no earlier plane holds (None: all)
            for rank in range(1, n_planes + 1):
                found = _candidate_plane(run, cl, rec, provisional, rest)
                verdict = {"cluster": cl.id, "points": cl.n_points if rest is None else int(rest.size),
                           **({"plane": rank} if rank > 1 else {}),
                           **{k: v for k, v in found.items() if k not in ("plane", "held")}}
                verdicts.append(verdict)
                if found["plane"] is None:
                    break
                refused = _refused(run, found, verdict, fallback)
                if refused is None:
                    n, point, on = found["plane"]
                    dist = float(np.sqrt(((on - run.sensor) ** 2).sum(axis=1).min()))
                    verdict["distance"] = dist  # to the sensor, of its plane's nearest point
                    planes.append((dist, cl, n, point, verdict["angle_to_fallback"], found, on, verdict))
                    break
                seen = under if refused == "under" else tilted
                if cl.id not in seen:  # a cluster once, whichever of its planes was refused
                    seen.append(cl.id)
                if found["method"] != "robust plane":  # the plane of all its points: no other
                    break
                held = found["held"]  # the next plane among the points this one does not hold
                rest = np.flatnonzero(~held) if rest is None else rest[~held]
    if planes:
        best = _choose(run, X, planes)
    if best is None:
        tests = [f"passes '{spec.candidate}'"] if spec.candidate is not None else []
        if spec.plane is not None:
            tests.append(f"has a robust plane holding >= {spec.plane.min_inlier_share:.0%} of its points within "
                         f"{spec.plane.inlier_distance:g}{run.rule_base.length_unit and ' ' + run.rule_base.length_unit}")
        why = (f"no cluster of the initial partition with >= {spec.min_points} points {' or '.join(tests)}"
               if tests else "scene.ground declares neither a candidate check nor a robust plane")
        if no_plane:
            why += (f" and has a plane ({len(no_plane)} degenerate)" if spec.plane is None else
                    f" ({len(no_plane)} degenerate: no plane)")
        if tilted:
            why += (f" within max_tilt {spec.plane.max_tilt:g} deg of the fallback (the robust plane of "
                    f"{', '.join(tilted[:5])}{' ...' if len(tilted) > 5 else ''} is tilted more)")
        if under:
            why += (f", with the sensor above it ({', '.join(under[:5])}{' ...' if len(under) > 5 else ''} "
                    f"gave a plane with the sensor {list(np.round(run.sensor, 6).tolist())} below it: is the scan in "
                    "the sensor's frame? kbs run --sensor X,Y,Z gives its position)")
        shares = [f"{v['cluster']} {v['inlier_share']:.0%}" for v in verdicts
                  if v.get("inlier_share") is not None and v["cluster"] not in tilted and v["cluster"] not in under]
        if shares:
            why += f" (the share of their points on their robust planes: {', '.join(shares[:5])})"
        facts = GroundFacts(note=f"{why}: the fallback normal {list(spec.fallback)} is used")
        if verdicts and spec.plane is not None:
            facts = replace(facts, candidates=_candidates(verdicts), unit=run.rule_base.length_unit,
                            share_of=_share_of(spec))
        return plane_from_normal(X, np.asarray(spec.fallback, float), "fallback", facts)
    dist, cl, n, point, tilt, found, _, verdict = best
    below = bool(n @ fallback < 0)  # the sensor lies below the ground: its frame is not the scan's (_sensor_note)
    if below:
        n = -n
    robust = spec.plane is not None and "inliers" in found  # a robust plane, or a checked one's (refit)
    facts = GroundFacts(
        source=f"cluster {cl.id}", cluster=cl.id, normal=tuple(n.tolist()), point=tuple(point.tolist()),
        distance_to_sensor=dist, thickness=found.get("plane_thickness", found.get("thickness")), distance=dist,
        unit=run.rule_base.length_unit, method=found["method"],
        supported=verdict["supported"] if spec.support is not None else None,
        candidates=_candidates(verdicts) if spec.support is not None or spec.plane is not None else None,
        support_band=(spec.support.min_height, spec.support.max_height) if spec.support is not None else None,
        angle_to_fallback=round(tilt, 3) if spec.plane is not None else None,
        inliers=found["inliers"] if robust else None, inlier_share=found["inlier_share"] if robust else None,
        plane=verdict.get("plane"), share_of=_share_of(spec),
        note=_sensor_note(run, X, fallback, n, point, below) or None)
    return Ground(normal=n, point=np.asarray(point, float).copy(), source=f"cluster {cl.id}"), facts


def _candidates(verdicts: list[dict[str, Any]]) -> tuple[GroundCandidate, ...]:
    """The candidates' verdicts, as the search wrote them, as records."""
    return tuple(GroundCandidate(**v) for v in verdicts)


#: A sensor farther than this many times the scan's bounding-box diagonal from the box is taken
#: for a scan not in the sensor's frame (map or survey coordinates with the rule base's sensor).
FAR_SENSOR = 10.0


def _sensor_note(run: Any, X: np.ndarray, fallback: np.ndarray, n: np.ndarray, point: np.ndarray,
                 below: bool) -> str | None:
    """What to tell a user whose sensor position does not fit the scan (None when it fits).

    The ground normal points towards the sensor, the ground being below it. A sensor below the
    plane chosen (on the side opposite the rule base's fallback normal), or far from the scan (a
    scan in map or survey coordinates read with the rule base's default sensor, the origin), says
    the scan is not in the sensor's frame: the normal then follows the fallback normal's side
    (the rule base's up), and the note says so and how to give the sensor's position."""
    unit = run.rule_base.length_unit
    u = f" {unit}" if unit else ""
    vec = lambda v: "[" + ", ".join(f"{x:.6g}" for x in v) + "]"  # noqa: E731
    said = []
    lo, hi = bounds(X)
    diag = max(float(np.linalg.norm(hi - lo)), float(np.finfo(float).tiny))
    away = float(np.linalg.norm(run.sensor - np.clip(run.sensor, lo, hi)))
    if away > FAR_SENSOR * diag:
        said.append(f"the sensor {vec(run.sensor)} is {away:.6g}{u} from the scan's bounding box, {away / diag:.3g} "
                    "times its diagonal (the ground is the candidate plane closest to it)")
    if below:
        depth = float((point - run.sensor) @ n)
        said.append(f"{'it' if said else f'the sensor {vec(run.sensor)}'} lies {depth:.6g}{u} below the ground plane "
                    f"found: the plane's normal was turned to the side of the fallback normal {vec(fallback)}")
    if not said:
        return None
    return "; ".join(said) + ("; is the scan in the sensor's frame? kbs run --sensor X,Y,Z (Segmenter(sensor=...)) "
                              "gives its position")

def _choose(run: Any, X: np.ndarray, planes: list[tuple]) -> tuple:
    """The ground among the candidates that give a plane (distance, cluster, normal, point,
    tilt, found, plane points, verdict): the closest to the sensor, or with
    scene.ground.choose 'supporting', the one with the most points standing on it (the
    closest of equals); each verdict gets its count ('supported')."""
    support = run.rule_base.ground.support
    if support is None:
        return min(planes, key=lambda p: p[0])  # the first of equals, as before
    for p in planes:
        p[7]["supported"] = supported_points(X, p[2], p[3], p[6], support.min_height, support.max_height)
    return min(planes, key=lambda p: (-p[7]["supported"], p[0]))

def _share_of(spec: Any) -> str | None:
    """What the robust planes' shares are counted among, for the facts: None when all of a
    candidate's points (the default)."""
    return spec.plane.share_of if spec.plane is not None and spec.plane.share_of != "all" else None


def _refused(run: Any, found: dict[str, Any], verdict: dict[str, Any], fallback: np.ndarray) -> str | None:
    """Whether a candidate's plane is refused for its direction: 'under' (sensor_above: the sensor
    under it), 'tilted' (a robust plane past max_tilt), None (a ground plane). Turns its normal
    towards the sensor, and writes its angle to the fallback (and the reason) in ``verdict``."""
    spec = run.rule_base.ground
    n, point, on = found["plane"]
    if (run.sensor - point) @ n < 0:  # point up, towards the sensor
        n = -n
        found["plane"] = (n, point, on)
    tilt = float(np.degrees(np.arccos(min(1.0, abs(float(n @ fallback))))))
    verdict["angle_to_fallback"] = round(tilt, 3)
    if spec.sensor_above and float(n @ fallback) < 0.0:  # the sensor under its plane
        depth = float((run.sensor - point) @ n)  # n points towards it: its distance to the plane
        unit = run.rule_base.length_unit and " " + run.rule_base.length_unit
        verdict["why"] = (f"the sensor lies {depth:.3g}{unit} below its plane (on the side opposite the "
                          "fallback normal): seen from underneath, not the ground (sensor_above)")
        return "under"
    max_tilt = spec.plane.max_tilt if spec.plane is not None else None
    if found["method"] == "robust plane" and max_tilt is not None and tilt > max_tilt:
        verdict["why"] = f"its robust plane is {tilt:.1f} deg from the fallback normal > max_tilt {max_tilt:g} deg"
        return "tilted"
    return None


def _candidate_plane(run: Any, cl: Cluster, rec: Draft, provisional: Scene,
                     rest: np.ndarray | None = None) -> dict[str, Any]:
    """How a ground candidate gives a plane: ``plane`` (normal, point, its points) or None,
    ``method``, what was measured, and (a robust plane) ``held``, which of the points it was
    sought among it holds. ``rest``: the positions in the cluster of the points an earlier plane
    of it did not hold (scene.ground.plane.planes): the next robust plane is sought among them
    alone, with no candidate check."""
    spec = run.rule_base.ground
    geo = cl.geometry
    if rest is None and spec.candidate is not None and run.fact(cl, provisional, rec)(spec.candidate):
        checked = {"plane": (geo.normal, geo.center, cl.X), "method": f"check '{spec.candidate}'",
                   "thickness": geo.thickness}
        if spec.plane is not None and spec.plane.refit:  # the plane most of its points lie on
            rp = robust_plane(cl.X, spec.plane.inlier_distance, spec.plane.min_inlier_share)
            share, among = (0.0, 0) if rp is None else _share(run, spec.plane, cl.X, rp)
            if rp is not None and _refusal(run, rp, share, among, None) is None:
                checked.update(plane=(rp.normal, rp.point, cl.X), inliers=rp.n_inliers,
                               inlier_share=round(share, 4), plane_thickness=rp.thickness)
        return checked
    out: dict[str, Any] = {"plane": None} if rest is not None else {"plane": None, "thickness": geo.thickness}
    if spec.candidate is not None and rest is None:
        out["why"] = f"fails '{spec.candidate}'"
    if spec.plane is None:
        return out
    p = spec.plane
    P = cl.X if rest is None else rows(cl.X, rest)
    rp = robust_plane(P, p.inlier_distance, p.min_inlier_share)
    if rp is None:
        out["why"] = ("no plane through its points" if rest is None else
                      "no plane through the points its earlier planes do not hold")
        return out
    share, among = _share(run, p, P, rp)
    out.update(inliers=rp.n_inliers, inlier_share=round(share, 4), plane_thickness=rp.thickness)
    why = _refusal(run, rp, share, among, rest)
    if why is not None:
        out["why"] = why
    else:
        out.update(plane=(rp.normal, rp.point, rows(P, rp.inliers)), method="robust plane", held=rp.inliers)
        out.pop("why", None)
    return out


def _refusal(run: Any, rp: Any, share: float, among: int, rest: np.ndarray | None) -> str | None:
    """Why a robust plane (holding ``share`` of the ``among`` points it is counted among) gives no
    ground plane: too small a share, too few points (min_points), too thick (max_thickness); None
    when it gives one. ``rest``: not None for a cluster's later plane (the message says so)."""
    spec = run.rule_base.ground
    p = spec.plane
    unit = run.rule_base.length_unit and " " + run.rule_base.length_unit
    its = "its robust plane" if rest is None else "its next robust plane"
    if share < p.min_inlier_share:
        of = "its points" if rest is None else "the points its earlier planes do not hold"
        if p.share_of == "not_above":
            of += f" not above it ({among:,})"
        return f"{its} holds {share:.0%} of {of} within {p.inlier_distance:g}{unit} < {p.min_inlier_share:.0%}"
    if rp.n_inliers < spec.min_points:
        return f"{its} holds {rp.n_inliers} points < min_points {spec.min_points}"
    if p.max_thickness is not None and rp.thickness > p.max_thickness:
        return (f"{its}'s points spread {rp.thickness:.3g}{unit} across it > max_thickness "
                f"{p.max_thickness:g}{unit}: a slab through a volume, not a surface")
    return None


def _share(run: Any, p: Any, P: np.ndarray, rp: Any) -> tuple[float, int]:
    """The share of the points ``P`` the robust plane ``rp`` holds, and how many points it is
    counted among: all of them, or (share_of: not_above) those not above it, on the sensor's side
    farther than the inlier distance (what stands on the ground does not count against it)."""
    if p.share_of != "not_above":
        return rp.share, P.shape[0]
    side = (P - rp.point) @ rp.normal
    if float((run.sensor - rp.point) @ rp.normal) < 0:
        side = -side  # positive towards the sensor
    among = int(np.count_nonzero(side <= p.inlier_distance))  # the inliers among them: never 0
    return (rp.n_inliers / among if among else 0.0), among


def _uses_ground(rule_base: Any) -> bool:
    """Whether the rule base uses a ground plane at all."""
    spec = rule_base.ground
    return bool(rule_base.needs_ground or spec.normal is not None or spec.candidate is not None
                or spec.plane is not None or rule_base.ground_model is not None)


def needs_candidates(run: Any) -> bool:
    """Whether :func:`find` looks at the candidates it is given: not when the rule base uses no
    ground, when the ground is given (a tile's) or when its normal is fixed by the rule file. The
    initial partition that makes the candidates need not be computed then
    (:meth:`kbs.knowledge.interpreter.Interpreter.find_ground`)."""
    return _uses_ground(run.rule_base) and run.given_ground is None and run.rule_base.ground.normal is None


def plane_from_normal(X: np.ndarray, n: np.ndarray, source: str,
                      facts: GroundFacts) -> tuple[Ground, GroundFacts]:
    """The plane of normal ``n`` under the cloud (through the 5 % quantile of the heights along
    it), and ``facts`` with its source, normal and point."""
    n = n / np.linalg.norm(n)
    q = float(np.quantile(X @ n, 0.05))
    facts = replace(facts, source=source, normal=tuple(n.tolist()), point=tuple((q * n).tolist()))
    return Ground(normal=n, point=q * n, source=source), facts

