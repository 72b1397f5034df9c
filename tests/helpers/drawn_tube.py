"""A tube drawn round a 2-D axis for the end-fit tests: the union of discs of radius ``r``
round a densely sampled axis, each pixel's coverage counted on a supersampled grid
(scipy cKDTree distances, only in the axis' bounding box), then blurred (scipy.ndimage)."""

import numpy as np
from scipy import ndimage as ndi
from scipy.spatial import cKDTree


def drawn_tube(shape, axis, r, *, blur=1.2, supersample=4) -> np.ndarray:
    """Coverage (H, W) in 0..1 of the discs of radius ``r`` round ``axis`` (n, 2) (u, v)."""
    h, w = shape
    axis = np.asarray(axis, np.float64)
    m = r + 4.0 * blur + 2.0
    u0, v0 = (max(int(np.floor(axis[:, i].min() - m)), 0) for i in (0, 1))
    u1 = min(int(np.ceil(axis[:, 0].max() + m)) + 1, w)
    v1 = min(int(np.ceil(axis[:, 1].max() + m)) + 1, h)
    o = (np.arange(supersample) + 0.5) / supersample - 0.5
    vv, uu = np.meshgrid(np.arange(v0, v1), np.arange(u0, u1), indexing="ij")
    tree = cKDTree(axis)
    cover = np.zeros((h, w))
    box = np.zeros(vv.shape)
    for du in o:
        for dv in o:
            X = np.stack([(uu + du).ravel(), (vv + dv).ravel()], 1)
            box += (tree.query(X)[0] <= r).reshape(vv.shape)
    cover[v0:v1, u0:u1] = box / supersample**2
    return ndi.gaussian_filter(cover, blur, mode="nearest")
