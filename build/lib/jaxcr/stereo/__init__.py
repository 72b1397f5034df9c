"""Stereo shape sensing of tubular continuum robots with an ArUco base frame (issue 4;
"Shape Sensing of Tubular Continuum Robots using Stereo Vision").

One concept per module: :mod:`~jaxcr.stereo.aruco` (base frame), :mod:`~jaxcr.stereo.chroma`
(chroma key, background plate), :mod:`~jaxcr.stereo.base_locate` (flood fill, Canny,
Hough), :mod:`~jaxcr.stereo.thinning` (Zhang-Suen in JAX), :mod:`~jaxcr.stereo.ordering`
(base-to-tip walk), :mod:`~jaxcr.stereo.correspondence` and
:mod:`~jaxcr.stereo.triangulation`, :mod:`~jaxcr.stereo.diameter`,
:mod:`~jaxcr.stereo.segments`, :mod:`~jaxcr.stereo.shadow` (slope-angle segmentation),
:mod:`~jaxcr.stereo.fits` (plane, circular arc), :mod:`~jaxcr.stereo.pipeline` (one stereo
pair end to end), :mod:`~jaxcr.stereo.overlay` (drawings), :mod:`~jaxcr.stereo.base_frame`
(base frame without markers: a given pose or the entry pixels),
:mod:`~jaxcr.stereo.view2d` (each view's tip pixel and 2-D backbone),
:mod:`~jaxcr.stereo.single_view` (one camera: the 2-D results alone).
"""

from jaxcr.stereo.api import StereoReconstruction, reconstruct
from jaxcr.stereo.aruco import MarkerLayout, detect_markers, stereo_base_pose
from jaxcr.stereo.base_frame import BaseSpec, triangulate_entry
from jaxcr.stereo.fits import fit_arc, fit_plane, plane_angles
from jaxcr.stereo.ordering import order_skeleton
from jaxcr.stereo.pipeline import StereoConfig, StereoFailure, reconstruct_pair
from jaxcr.stereo.single_view import reconstruct_view
from jaxcr.stereo.thinning import zhang_suen_thin
from jaxcr.stereo.triangulation import triangulate_points
from jaxcr.stereo.view2d import tip_pixel

__all__ = [
    "BaseSpec",
    "MarkerLayout",
    "StereoConfig",
    "StereoFailure",
    "StereoReconstruction",
    "detect_markers",
    "fit_arc",
    "fit_plane",
    "order_skeleton",
    "plane_angles",
    "reconstruct",
    "reconstruct_pair",
    "reconstruct_view",
    "stereo_base_pose",
    "tip_pixel",
    "triangulate_entry",
    "triangulate_points",
    "zhang_suen_thin",
]
