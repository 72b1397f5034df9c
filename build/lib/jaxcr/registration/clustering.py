"""Euclidean clustering of obstacle points and merging with earlier clusters (paper
Sec. III.A): points closer than ``tolerance`` (m) are in the same cluster (connected
components of the radius graph, built with a k-d tree)."""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree


def euclidean_clusters(points: np.ndarray, tolerance: float, min_size: int = 1) -> list[np.ndarray]:
    """Index arrays of the clusters of ``points`` (n, 3), largest first; clusters smaller than
    ``min_size`` are dropped."""
    n = len(points)
    if n == 0:
        return []
    pairs = cKDTree(points).query_pairs(tolerance, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    k, labels = connected_components(graph, directed=False)
    clusters = [np.flatnonzero(labels == c) for c in range(k)]
    clusters = [c for c in clusters if len(c) >= min_size]
    return sorted(clusters, key=len, reverse=True)


class ClusterMap:
    """The sensed obstacles: a list of point clusters (world frame). New points are clustered;
    a new cluster within ``tolerance`` of an existing one is merged into it, otherwise it is
    added as a new obstacle."""

    def __init__(self, tolerance: float = 0.02, voxel: float = 0.005):
        self.tolerance = tolerance
        self.voxel = voxel
        self.clusters: list[np.ndarray] = []

    def add(self, points: np.ndarray) -> int:
        """Add sensed points; returns the number of new clusters created."""
        created = 0
        for idx in euclidean_clusters(points, self.tolerance):
            new = points[idx]
            hit = [
                j
                for j, c in enumerate(self.clusters)
                if np.isfinite(cKDTree(c).query(new, distance_upper_bound=self.tolerance)[0]).any()
            ]
            if hit:
                merged = np.concatenate([self.clusters[j] for j in hit] + [new])
                self.clusters = [c for j, c in enumerate(self.clusters) if j not in hit]
                self.clusters.append(_thin(merged, self.voxel))
            else:
                self.clusters.append(_thin(new, self.voxel))
                created += 1
        return created

    def points(self) -> np.ndarray:
        return np.concatenate(self.clusters) if self.clusters else np.zeros((0, 3))


def _thin(points: np.ndarray, voxel: float) -> np.ndarray:
    key = np.floor(points / voxel).astype(np.int64)
    _, first = np.unique(key, axis=0, return_index=True)
    return points[np.sort(first)]
