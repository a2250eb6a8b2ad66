"""The files of a drive map (one module owns the format; every file is written to a temporary
name, then renamed):

- ``map.tif``: the grid as a GeoTIFF (rasterio, the ``map`` extra), one float32 band per layer of
  :data:`kbs.maps.grid.BANDS` (NaN = no value), north-up, the world frame as a local engineering
  CRS (or the CRS given), tags saying what the frame is;
- ``map.npy``: the same bands, float32 (bands, rows, cols), north-up;
- ``map.png``: a picture of the grid with the trajectory and the objects' ids;
- ``cloud.ply``: the fused labelled cloud (one point per voxel: label, obstacle, object, frames, count);
- ``objects/object-<id>.ply``: each tracked object's mesh;
- ``map.json``: the index of frames, objects and cells (format :data:`MAP_FORMAT`);
- ``map.html`` (when asked): the map view (:mod:`kbs.report.mapview`).

Every file goes through :func:`kbs.io.atomic.replacing` (a temporary file beside it, renamed over
it when whole): an interrupted write leaves the previous file.

One run id marks the files as kbs's (:func:`kbs.io.result.is_kbs_output`): the ``KBS_RUN_ID``
tag of ``map.tif``, a ``kbs_run_id`` text chunk in ``map.png``, a ``comment kbs_run_id`` in the
PLY files, the closing comment of ``map.html``, the ``run_id`` key of ``map.json``; ``map.npy``
(no room for it) by its SHA-256 in ``map.json``'s ``sha256``. ``kbs map`` checks them all before
segmenting (:func:`check_map_outputs`): a file kbs did not write is replaced only with ``--force``.
"""
from __future__ import annotations

import json
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from kbs import __version__
from kbs.errors import CloudFileError, ParameterError
from kbs.io.result import (
    GEOTIFF_RUN_ID_TAG,
    RUN_ID_COMMENT,
    InputFiles,
    check_output,
    file_digest,
    is_kbs_output,
    listed_by_index,
    new_run_id,
    png_metadata,
    result_comments,
)
from kbs.maps.build import DriveMap
from kbs.maps.grid import BANDS, CLASS_NAMES, OBSTACLE

#: Version of ``map.json``'s layout.
MAP_FORMAT = 1
#: The world frame when no CRS is given: the drive's own, in metres.
LOCAL_CRS_WKT = ('ENGCRS["kbs drive frame",EDATUM["world frame of the drive poses"],CS[Cartesian,2],'
                 'AXIS["x",east],AXIS["y",north],LENGTHUNIT["metre",1]]')


@contextmanager
def _atomic(path: Path) -> Iterator[Path]:
    """A temporary path beside ``path`` (:func:`kbs.io.atomic.replacing`), renamed to it when the
    block succeeds; an OSError of the writer inside the block is a :class:`CloudFileError` naming
    ``path``."""
    from kbs.io.atomic import replacing

    with replacing(path) as (tmp,):
        try:
            yield tmp
        except OSError as exc:
            raise CloudFileError(str(path), f"cannot write: {exc.strerror or exc}") from exc


def png_available() -> bool:
    """Whether matplotlib (in the ``map`` and ``render`` extras) is installed."""
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        return False
    return True


def geotiff_available() -> bool:
    """Whether rasterio (the ``map`` extra) is installed."""
    try:
        import rasterio  # noqa: F401
    except ImportError:
        return False
    return True


def _transform(m: DriveMap) -> tuple[float, float, float, float, float, float]:
    """The affine transform (a, b, c, d, e, f) of the north-up raster: x = a col + c, y = e row + f."""
    x0, _, _, y1 = m.grid.bounds
    s = m.grid.cell_size
    return (s, 0.0, x0, 0.0, -s, y1)


def check_crs(crs: str) -> Any:
    """``crs`` as a rasterio CRS.

    Raises
    ------
    ParameterError
        rasterio is not installed, or ``crs`` is not a CRS it knows.
    """
    try:
        from rasterio.crs import CRS
    except ImportError as exc:
        raise ParameterError("a CRS is for the GeoTIFF, which needs rasterio: pip install 'kbs[map]'") from exc
    try:
        return CRS.from_user_input(crs)
    except Exception as exc:  # noqa: BLE001 - CRSError, ValueError (an EPSG code that is not a number) ...
        raise ParameterError(f"not a CRS: {crs!r} ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") \
            from exc


def write_geotiff(m: DriveMap, path: Path, crs: str | None = None, *, run_id: str | None = None) -> str:
    """Write the grid's bands as a GeoTIFF; returns what the CRS is (one line).

    Parameters
    ----------
    crs : str, optional
        A CRS rasterio understands (``"EPSG:32632"``, WKT ...) when the poses are in it; default:
        the drive's local frame as an engineering CRS.

    Raises
    ------
    ParameterError
        rasterio is not installed, or ``crs`` is not a CRS.
    """
    try:
        import rasterio
        from rasterio.crs import CRS
        from rasterio.transform import Affine
    except ImportError as exc:
        raise ParameterError("writing a GeoTIFF needs rasterio: pip install 'kbs[map]'") from exc
    if crs is None:
        crs_obj = CRS.from_wkt(LOCAL_CRS_WKT)
        crs_note = ("local engineering CRS: the world frame of the drive's poses (metres, x east, y north by "
                    "convention); not georeferenced")
    else:
        crs_obj = check_crs(crs)
        crs_note = f"{crs} (as given: the poses are taken to be in this CRS)"
    bands = m.grid.bands()
    a, b, c, d, e, f = _transform(m)
    profile = dict(driver="GTiff", width=bands.shape[2], height=bands.shape[1], count=len(BANDS), dtype="float32",
                   crs=crs_obj, transform=Affine(a, b, c, d, e, f), nodata=np.nan, compress="deflate")
    with _atomic(path) as tmp:
        with rasterio.open(tmp, "w", **profile) as dst:
            dst.write(bands)
            for i, name in enumerate(BANDS, start=1):
                dst.set_band_description(i, name)
            dst.update_tags(KBS_VERSION=__version__, KBS_MAP_FORMAT=str(MAP_FORMAT), KBS_CRS=crs_note,
                            KBS_CLASSES="class band: " + ", ".join(f"{i} {n}" for i, n in enumerate(CLASS_NAMES)),
                            KBS_RULE_BASE=m.rule_base, KBS_FRAMES=str(len(m.frames)),
                            KBS_POSES=m.poses.note or m.poses.source,
                            **({GEOTIFF_RUN_ID_TAG: run_id} if run_id else {}))
    return crs_note


def write_png(m: DriveMap, path: Path, *, run_id: str | None = None) -> None:
    """A picture of the grid (ground, obstacles shaded by height, unknown), the trajectory and the
    objects' ids."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap

    from kbs.report.colors import GRID_HEX

    g = m.grid
    x0, y0, x1, y1 = g.bounds
    fig, ax = plt.subplots(figsize=(8, 8 * max(0.3, min(3.0, (y1 - y0) / max(x1 - x0, 1e-9)))), dpi=110)
    ax.imshow(g.raster(g.cls), cmap=ListedColormap(list(GRID_HEX)), vmin=0, vmax=2,
              extent=(x0, x1, y0, y1), interpolation="nearest")
    h = np.where(g.cls == OBSTACLE, g.obstacle_height, np.nan)
    if np.isfinite(h).any():
        im = ax.imshow(g.raster(h), cmap="magma_r", extent=(x0, x1, y0, y1), interpolation="nearest",
                       vmin=0, vmax=max(0.5, float(np.nanpercentile(h, 95))))
        fig.colorbar(im, ax=ax, shrink=0.7, label="obstacle height (m)")
    pos = m.poses.positions
    ax.plot(pos[:, 0], pos[:, 1], "-o", color="#1565c0", ms=2, lw=1, label="trajectory")
    for o in m.objects:
        c = o.centroid
        ax.annotate(str(o.id), (c[0], c[1]), color="black", fontsize=7, ha="center", va="center",
                    bbox=dict(boxstyle="round,pad=0.1", fc="white", alpha=0.7, lw=0))
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"{len(m.frames)} frames, {len(m.objects)} objects; green ground, red obstacle, grey unknown",
                 fontsize=9)
    ax.legend(loc="upper right", fontsize=7)
    with _atomic(path) as tmp:
        fig.savefig(tmp, format="png", bbox_inches="tight", metadata=png_metadata(run_id) if run_id else None)
    plt.close(fig)


def _index(m: DriveMap, files: dict[str, Any], crs_note: str) -> dict[str, Any]:
    g = m.grid
    a, b, c, d, e, f = _transform(m)
    obst = np.argwhere(g.cls == OBSTACLE)
    xs, ys = g.centers()
    rows = g.shape[1] - 1 - obst[:, 1]  # north-up row of each cell
    obj_of_cell: dict[tuple[int, int], set[int]] = {}
    for o in m.objects:
        for ij in {tuple(v) for v in g.cell_of(o.points).tolist()}:
            obj_of_cell.setdefault(ij, set()).add(o.id)
    cells = [{"row": int(r), "col": int(ix), "x": round(float(xs[ix, iy]), 4), "y": round(float(ys[ix, iy]), 4),
              "p_obstacle": round(float(g.p_obstacle[ix, iy]), 4),
              "height": None if not np.isfinite(g.obstacle_height[ix, iy]) else round(float(g.obstacle_height[ix, iy]), 3),
              "frames_seen": int(g.frames_seen[ix, iy]), "frames_obstacle": int(g.frames_obstacle[ix, iy]),
              "objects": sorted(obj_of_cell.get((int(ix), int(iy)), ()))}
             for (ix, iy), r in zip(obst.tolist(), rows.tolist())]
    objects = []
    for o in m.objects:
        lo, hi = o.bbox
        objects.append({"id": o.id, "frames": list(o.frames), "clusters": [list(fc) for fc in o.clusters],
                        "n_points": o.n_points, "n_fused_points": len(o.points),
                        "centroid": [round(float(v), 4) for v in o.centroid],
                        "bbox": [[round(float(v), 4) for v in lo], [round(float(v), 4) for v in hi]],
                        "mesh": files["objects"].get(o.id), "mesh_kind": o.mesh_kind,
                        "mesh_faces": None if o.faces is None else len(o.faces)})
    frames = [{"index": r.index, "name": r.name, "path": r.path, "pose": np.round(r.pose, 9).tolist(),
               "n_points": r.n_points, "n_ground": r.n_ground, "n_obstacle": r.n_obstacle, "n_noise": r.n_noise,
               "clusters": r.clusters, "objects": {str(k): v for k, v in sorted(r.objects.items())},
               "segment_seconds": round(r.segment_seconds, 4), "fuse_seconds": round(r.fuse_seconds, 5)}
              for r in m.frames]
    return {
        "kbs_map": MAP_FORMAT, "kbs_version": __version__, "source": m.source, "rule_base": m.rule_base,
        "rule_file": m.rule_file, "label_names": m.label_names, "params": m.params,
        "poses": {"source": m.poses.source, "path": m.poses.path, "note": m.poses.note,
                  "residuals": [{"frame": i + 1, **{k: round(v, 4) for k, v in r.__dict__.items()}}
                                for i, r in enumerate(m.poses.residuals)]},
        "notes": list(m.notes), "files": {k: v for k, v in files.items() if k != "objects"},
        "grid": {"cell_size": g.cell_size, "origin": list(g.origin), "bounds": list(g.bounds),
                 "shape": {"rows": g.shape[1], "cols": g.shape[0]}, "transform": [a, b, c, d, e, f],
                 "transform_doc": "x = a col + b row + c, y = d col + e row + f (cell corner; row 0 is the largest y)",
                 "bands": list(BANDS), "classes": list(CLASS_NAMES), "crs": crs_note, "counts": g.counts(),
                 "fusion": {"l_obstacle": g.params.l_obstacle, "l_ground": g.params.l_ground,
                            "l_clamp": g.params.l_clamp, "min_obstacle_points": g.params.min_obstacle_points}},
        "frames": frames, "objects": objects, "obstacle_cells": cells,
        "fuse_ms_per_frame": round(m.fuse_ms_per_frame, 3),
    }


def map_files(out_dir: str | os.PathLike[str], *, geotiff: bool | None = None, png: bool | None = None,
              report: bool = False) -> dict[str, Path]:
    """The files :func:`write_map` writes in ``out_dir`` but the objects' meshes, key -> path
    (``geotiff``, ``png``: None as write_map decides, by what is installed)."""
    out = Path(out_dir)
    geotiff = geotiff_available() if geotiff is None else geotiff
    png = png_available() if png is None else png
    files = {"geotiff": out / "map.tif"} if geotiff else {}
    files["npy"] = out / "map.npy"
    if png:
        files["png"] = out / "map.png"
    files["cloud"] = out / "cloud.ply"
    if report:
        files["report"] = out / "map.html"
    files["index"] = out / "map.json"
    return files


def check_map_outputs(out_dir: str | os.PathLike[str], *, inputs: Any = (), force: bool = False,
                      geotiff: bool | None = None, report: bool = False) -> None:
    """Refuse, before any work, a map :func:`write_map` must not write in ``out_dir``.

    Each file it would write or replace, the earlier map's ``objects/object-*.ply`` it would
    remove included, is checked with :func:`kbs.io.result.check_output`: never one of ``inputs``
    (the scans, the poses); an existing file kbs did not write only with ``force``.

    Raises
    ------
    CloudFileError
    """
    out = Path(out_dir)
    files = map_files(out, geotiff=geotiff, report=report)
    sources = inputs if isinstance(inputs, InputFiles) else InputFiles(inputs)
    stale = sorted((out / "objects").glob("object-*.ply")) if (out / "objects").is_dir() else []
    for path in (*files.values(), *stale):
        own = path == files["npy"] and listed_by_index(path, files["index"])
        check_output(path, inputs=sources, force=force, own=own)


def write_map(m: DriveMap, out_dir: str | os.PathLike[str], *, crs: str | None = None,
              geotiff: bool | None = None, report: bool = False, force: bool = False) -> dict[str, Any]:
    """Write every file of the map in ``out_dir``; returns the index (``map.json``'s content).

    Parameters
    ----------
    crs : str, optional
        The CRS the poses are in (for the GeoTIFF); default the drive's local frame.
    geotiff : bool, optional
        Write ``map.tif`` (True: rasterio is required; None: when rasterio is installed, else a
        note in the index says why there is none).
    report : bool
        Also write ``map.html``, the map view (:func:`kbs.report.mapview.write_map_report`; plotly,
        the ``report`` extra); its explanations are those ``map_drive(..., explain=True)`` kept.
    force : bool
        Remove an earlier ``objects/object-*.ply`` that kbs did not write (no run id) too; without
        it such a file is refused (:func:`check_map_outputs` says so before the work).

    Raises
    ------
    CloudFileError
        A file cannot be written.
    ParameterError
        ``geotiff=True`` without rasterio, or a bad ``crs``.
    MissingExtra
        ``report=True`` without plotly.
    """
    from kbs.io import write_ply
    from kbs.report.meshes import write_mesh_ply

    out = Path(out_dir)
    try:
        (out / "objects").mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CloudFileError(str(out), f"cannot create the output directory: {exc.strerror or exc}") from exc
    run_id = new_run_id()
    for stale in (out / "objects").glob("object-*.ply"):  # an earlier map's objects would mislead
        if not force and not is_kbs_output(stale):
            raise CloudFileError(str(stale), "exists and was not written by kbs (it has no kbs run id); give --force "
                                             "to replace it, or choose another --out")
        try:
            stale.unlink()
        except OSError as exc:
            raise CloudFileError(str(stale), f"cannot remove an earlier map's mesh: {exc.strerror or exc}") from exc
    files: dict[str, Any] = {"objects": {}}
    notes = []
    if geotiff is None:
        geotiff = geotiff_available()
        if not geotiff:
            notes.append("map.tif not written: rasterio is not installed (pip install 'kbs[map]')")
    crs_note = "none"
    if geotiff:
        crs_note = write_geotiff(m, out / "map.tif", crs, run_id=run_id)
        files["geotiff"] = "map.tif"
    with _atomic(out / "map.npy") as tmp:
        with open(tmp, "wb") as fh:
            np.save(fh, m.grid.bands())
        digests = {"map.npy": file_digest(tmp)}
    files["npy"] = "map.npy"
    if png_available():
        write_png(m, out / "map.png", run_id=run_id)
        files["png"] = "map.png"
    else:
        notes.append("map.png not written: matplotlib is not installed (pip install 'kbs[map]')")
    cl = m.cloud
    with _atomic(out / "cloud.ply") as tmp:
        write_ply(tmp, cl.xyz, {"label": cl.label, "obstacle": cl.obstacle.astype(np.uint8), "object": cl.object,
                                "frames": cl.frames, "count": cl.count},
                  comments=[f"kbs map: fused cloud of {len(m.frames)} frames, voxel {m.params['voxel_size']:g} m",
                            "labels: " + ", ".join(f"{i} {n}" for i, n in enumerate(m.label_names)),
                            *result_comments(run_id)])
    files["cloud"] = "cloud.ply"
    for o in m.objects:
        if o.faces is None:
            continue
        name = f"objects/object-{o.id}.ply"
        with _atomic(out / name) as tmp:
            write_mesh_ply(tmp, o.vertices, o.faces, run_id=run_id)
        files["objects"][o.id] = name
    if report:
        from kbs.report.mapview import write_map_report

        with _atomic(out / "map.html") as tmp:
            write_map_report(m, tmp)
            with open(tmp, "a", encoding="utf-8") as stream:  # marks the page as kbs's own (--force)
                stream.write(f"<!-- {RUN_ID_COMMENT} {run_id} -->\n")
        files["report"] = "map.html"
    doc = _index(m, files, crs_note)
    doc = {"kbs_map": doc.pop("kbs_map"), "kbs_version": doc.pop("kbs_version"), "run_id": run_id, **doc,
           "sha256": digests}
    doc["notes"] += notes
    with _atomic(out / "map.json") as tmp:
        tmp.write_text(json.dumps(doc, indent=1, default=_jsonable))
    return doc


def _jsonable(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o).__name__)


def read_map_index(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The parsed ``map.json`` (``path`` is the file or its folder).

    Raises
    ------
    CloudFileError
        Missing, not JSON or not a kbs map index.
    """
    p = Path(path)
    if p.is_dir():
        p = p / "map.json"
    try:
        doc = json.loads(p.read_text())
        if doc.get("kbs_map") != MAP_FORMAT:
            raise KeyError("kbs_map")
    except FileNotFoundError as exc:
        raise CloudFileError(str(p), "no such file") from exc
    except (OSError, ValueError, KeyError, AttributeError, RecursionError) as exc:
        raise CloudFileError(str(p), f"not a kbs map index ({type(exc).__name__}: {exc})") from exc
    return doc
