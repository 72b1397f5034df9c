"""Kinematic-prior segmentation (Watson et al.): background model, silhouette, energy,
shape, the refinement solver, metrics and the batch driver (``batch``).

Import the concept modules directly (``from jaxcr.segmentation.refine import
refine_frame``); the flat public names are re-exported by ``jaxcr``."""
