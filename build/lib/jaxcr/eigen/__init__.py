"""Eigen-feature pose estimation of a single-segment continuum robot (Reiter et al.):
colour segmentation, contour, angular-histogram stereo descriptor, PCA, thin-plate spline
manifold and k-NN inverse-distance query.

Model files (``save_model`` / ``load_model``, format ``jaxcr.manifold/2``) are I/O and live in
:mod:`jaxcr.io.eigen_model`."""

from jaxcr.eigen.colour import ColourModel, fit_colour_model, label_batch, label_image, rgb_to_lab
from jaxcr.eigen.descriptor import angular_histogram, mask_descriptors, stereo_descriptor
from jaxcr.eigen.knn_index import KnnIndex, build_index, knn_batch, query_batch_indexed
from jaxcr.eigen.manifold import Manifold, build_manifold, idw_weights, knn, query, query_batch
from jaxcr.eigen.model import EigenModel, TrainConfig, estimate, train
from jaxcr.eigen.pca import PCA, components_for_variance, fit_pca, project
from jaxcr.eigen.pipeline import stereo_histograms, view_centres
from jaxcr.eigen.tps import ThinPlateSpline, evaluate_tps, fit_tps

__all__ = [
    "ColourModel",
    "EigenModel",
    "KnnIndex",
    "Manifold",
    "PCA",
    "ThinPlateSpline",
    "TrainConfig",
    "angular_histogram",
    "build_index",
    "build_manifold",
    "components_for_variance",
    "estimate",
    "evaluate_tps",
    "fit_colour_model",
    "fit_pca",
    "fit_tps",
    "idw_weights",
    "knn",
    "knn_batch",
    "label_batch",
    "label_image",
    "mask_descriptors",
    "project",
    "query",
    "query_batch",
    "query_batch_indexed",
    "rgb_to_lab",
    "stereo_descriptor",
    "stereo_histograms",
    "train",
    "view_centres",
]
