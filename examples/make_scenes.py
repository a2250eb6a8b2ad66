"""Generate the bundled example scenes with kbs's own labelled scene generator (kbs.synth):

- ``examples/data/outdoor.ply``: uneven ground, three rocks and a bin seen by a stereo-like
  sensor at the origin (density falling with distance); per-vertex ``label`` (0 ground, 1-3
  rocks, 4 bin), ``object``, ``ground``, ``pixel``.
- ``examples/data/polyhedral.ply``: boxes and wedges on a ground plane seen by a range sensor;
  per-vertex ``label`` (one per planar face, 0 = ground), ``object``, ``ground``, ``pixel``.

Deterministic (seed 0). The same as ``kbs synth outdoor --seed 0 --resolution 150x270`` and
``kbs synth polyhedral --seed 0 --resolution 120x160``.

Usage: python examples/make_scenes.py [OUT_DIR]
"""
from __future__ import annotations

import sys
from pathlib import Path

from kbs.synth import outdoor_scene, polyhedral_scene


def main(argv: list[str]) -> None:
    out = Path(argv[0]) if argv else Path(__file__).resolve().parent / "data"
    out.mkdir(parents=True, exist_ok=True)
    for name, scene in (("outdoor", outdoor_scene(0, resolution=(150, 270))),
                        ("polyhedral", polyhedral_scene(0, resolution=(120, 160)))):
        scene.save(out / f"{name}.ply")
        print(f"wrote {out / f'{name}.ply'}: {scene.summary()}")


if __name__ == "__main__":
    main(sys.argv[1:])
