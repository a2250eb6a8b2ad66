"""Labelled synthetic scenes: polyhedral scenes seen by a simulated range sensor, outdoor scenes
seen by a stereo-like sensor.

>>> from kbs.synth import polyhedral_scene, outdoor_scene
>>> scene = polyhedral_scene(seed=0)           # doctest: +SKIP
>>> scene.xyz.shape, scene.n_labels            # doctest: +SKIP
>>> scene.save("polyhedral.ply")               # doctest: +SKIP

Every scene is in the sensor frame (metres): the sensor at the origin, z up, x the horizontal
direction it looks towards, y to its left, the ground about ``sensor_height`` below. Same seed
and options, same arrays (one ``numpy.random.Generator`` per call, no global state).
"""
from __future__ import annotations

from kbs.synth.outdoor import outdoor_scene
from kbs.synth.polyhedral import polyhedral_scene
from kbs.synth.raycast import HeightField
from kbs.synth.scene import Face, Scene

__all__ = ["Scene", "Face", "HeightField", "polyhedral_scene", "outdoor_scene"]
