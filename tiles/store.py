"""The finished tiles of a run, kept on disk until the run is done: what ``kbs run --tile
--resume`` does not segment again.

One file per tile, ``<folder>/<tile>.npz``: its ``cluster``, ``label``, ``membership`` arrays and
a JSON document (label names, clusters, explanation, seconds) with the tile's key. The key is a
digest of everything the tile's result depends on: the rule file's text, the plugins' texts, the
sensor, the kbs version, and the tile's points (their indices and coordinates). A file whose key
differs (another rule base, another cloud, another grid) is not used. Each file is written whole
or not at all (written beside it, then renamed; not synced: a torn file is one :meth:`TileStore.load` cannot read).
"""
from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from kbs.arrays import rows
from kbs.errors import CloudFileError
from kbs.knowledge.explain import Explanation
from kbs.knowledge.interpreter import Segmentation
from kbs.knowledge.segmenter import Segmenter
from kbs.tiles.grid import Tile

#: Version of the tile files (``format`` in their JSON).
TILE_FORMAT = 1


class TileStore:
    """The tile files of one run in ``folder`` (created when the first tile is saved).

    Parameters
    ----------
    folder : path
    segmenter : Segmenter
        What the tiles are segmented with: its rule file, plugins and sensor enter every key.
    """

    def __init__(self, folder: str | os.PathLike[str], segmenter: Segmenter) -> None:
        from kbs import __version__

        self.folder = Path(os.fspath(folder))
        h = hashlib.sha256()
        for part in (f"kbs {__version__}", segmenter.rule_base.text, repr(segmenter.sensor)):
            h.update(part.encode("utf-8"))
            h.update(b"\0")
        for plugin in segmenter.plugins:
            try:
                h.update(Path(plugin).read_bytes())
            except OSError:
                h.update(plugin.encode("utf-8"))
            h.update(b"\0")
        self._base = h.digest()

    def key(self, tile: Tile, X: np.ndarray, given: Any = None) -> str:
        """The digest of what ``tile``'s result depends on (``given``: the whole cloud's ground plane
        and its explanation, as :func:`kbs.tiles.run.scene_ground` returns them)."""
        index = tile.index
        return self.key_of(index, rows(X, index), given)

    def key_of(self, index: np.ndarray, points: np.ndarray, given: Any = None) -> str:
        """:meth:`key` of a tile of the points ``points`` (n_tile, 3) at ``index`` in the cloud."""
        h = hashlib.sha256(self._base)
        if given is not None:
            ground, info = given
            if ground is not None:
                h.update(np.concatenate([ground.normal, ground.point]).astype(np.float64).tobytes())
            h.update(json.dumps(info.to_dict(), sort_keys=True, default=str).encode("utf-8"))
        h.update(np.ascontiguousarray(index, dtype=np.int64).tobytes())
        h.update(np.ascontiguousarray(points, dtype=np.float64).tobytes())
        return h.hexdigest()

    @classmethod
    def at(cls, folder: str | os.PathLike[str], base: bytes) -> TileStore:
        """The store of ``folder`` with the digest of an existing store's segmenter (``store._base``):
        what a Dask worker saves its tiles with."""
        store = cls.__new__(cls)
        store.folder, store._base = Path(os.fspath(folder)), base
        return store

    def path(self, tile: Tile) -> Path:
        return self.folder / f"{tile.name}.npz"

    def load(self, tile: Tile, key: str) -> Segmentation | None:
        """The saved result of ``tile``, or None (no file, another key, unreadable)."""
        path = self.path(tile)
        try:
            with np.load(path, allow_pickle=False) as f:
                doc = json.loads(bytes(f["doc"]).decode("utf-8"))
                if doc.get("format") != TILE_FORMAT or doc.get("key") != key:
                    return None
                return Segmentation(cluster=f["cluster"].copy(), label=f["label"].copy(),
                                    membership=f["membership"].copy(), label_names=list(doc["label_names"]),
                                    explanation=Explanation.from_dict(doc["explanation"]), clusters=doc["clusters"],
                                    seconds=float(doc["seconds"]))
        except (OSError, ValueError, KeyError, TypeError):
            return None

    def save(self, tile: Tile, key: str, seg: Segmentation) -> None:
        """Write ``tile``'s result (whole or not at all)."""
        from kbs.io.result import strict_json

        doc = {"format": TILE_FORMAT, "key": key, "tile": tile.name, "label_names": seg.label_names,
               "clusters": seg.clusters, "explanation": seg.explanation.to_dict(), "seconds": seg.seconds}
        data = np.frombuffer(strict_json(doc).encode("utf-8"), dtype=np.uint8)
        path = self.path(tile)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
            # renamed whole into place, not synced to the disk: a file a crash left torn is one
            # load() cannot read, and that tile is segmented again (a sync per tile cost 5 % of a run)
            with open(tmp, "wb") as stream:
                np.savez(stream, cluster=seg.cluster, label=seg.label, membership=seg.membership, doc=data)
            os.replace(tmp, path)
        except OSError as exc:
            tmp.unlink(missing_ok=True)
            raise CloudFileError(str(self.path(tile)), f"cannot write: {exc.strerror or exc}") from exc

    def remove(self) -> None:
        """Delete the tile files (the run is done) and the folder if nothing else is in it."""
        if not self.folder.is_dir():
            return
        for path in self.folder.glob("t*_*.npz"):
            path.unlink(missing_ok=True)
        try:
            self.folder.rmdir()
        except OSError:
            pass  # something else is in it: left as it is
