"""Evaluation of segmentations: Hoover et al. (1996) region metrics, ground-segmentation metrics, ground-truth loading."""
