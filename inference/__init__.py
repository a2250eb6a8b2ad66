"""The inference motor: fuzzy c-means, Gath-Geva, the UFP-ONC driver, validity criteria and
cluster geometry. Arrays in, arrays and result objects out; knows nothing of rules or files."""
from __future__ import annotations

from kbs.inference._validation import Interval, NoneValue, Options, validate_params
from kbs.inference.engine import DroppedCluster
from kbs.inference.geometry import ClusterGeometry, angle_between_planes, cluster_geometry
from kbs.inference.ufp_onc import KPartition, UFPONCResult, first_local_max, ufp_onc
from kbs.inference.voxel import VoxelReduction, auto_voxel_size, voxel_reduce

__all__ = [
    "FuzzyCMeans", "GathGeva", "ufp_onc", "UFPONCResult", "KPartition", "first_local_max",
    "DroppedCluster", "ClusterGeometry", "cluster_geometry", "angle_between_planes",
    "VoxelReduction", "voxel_reduce", "auto_voxel_size",
    # the declarative parameter checks the engine uses, public for the scene generators (kbs.synth)
    # and the engine-settings table's readers (the rule files, the command line)
    "Interval", "Options", "NoneValue", "validate_params",
]


def __getattr__(name: str):
    # The estimators pull in scikit-learn (about 1 s to import); load them only when asked for,
    # so that the command line and ufp_onc start fast.
    if name in ("FuzzyCMeans", "GathGeva"):
        from kbs.inference import estimators

        return getattr(estimators, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
