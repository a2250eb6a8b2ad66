"""An example predicate plugin for kbs: use it with ``kbs run --plugin examples/plugins/elongation.py``.

A predicate MEASURES one number from a cluster; the rule file decides what the number means.
Declare it with ``@predicate``: kbs checks the contract (name, unit, docstring, keyword-only
parameters with defaults) when the file is loaded, not when a rule first calls it.
"""
from __future__ import annotations

import numpy as np

from kbs.knowledge import predicate


@predicate(unit="ratio", value_range=(1.0, None), bounds={"min_eigenvalue": (0.0, None)})
def elongation(cluster, scene, *, min_eigenvalue: float = 1e-12) -> float:
    """sqrt(mu3 / mu2): how much longer the cluster is along its main axis than along the
    second one (1 for a disc or a ball; large for a pole, a trunk or a cable)."""
    mu = cluster.geometry.eigenvalues
    return float(np.sqrt(max(mu[2], min_eigenvalue) / max(mu[1], min_eigenvalue)))


@predicate(unit="deg", value_range=(0.0, 90.0), needs_ground=True)
def axis_tilt(cluster, scene) -> float:
    """Angle in degrees between the cluster's main axis (e3) and the ground normal: 0 for an
    upright pole, 90 for a log lying on the ground."""
    e3 = cluster.geometry.eigenvectors[:, 2]
    return float(np.degrees(np.arccos(min(1.0, abs(float(e3 @ scene.ground.normal))))))
