"""Nearest neighbours among a point cloud, by a k-d tree (scipy's): a million Gaussians' 32
neighbours in seconds and in memory proportional to the points, where a distance matrix per
chunk of points (what this replaced) took O(N^2) time and 8 GB a chunk at that size."""

from __future__ import annotations

import os

import numpy as np
import torch
from scipy.spatial import cKDTree


def nearest(points: torch.Tensor, queries: torch.Tensor, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(distances [Q, k], indices [Q, k]) of the k points [P, 3] nearest each query [Q, 3],
    nearest first (a query that is one of the points finds itself first)."""
    tree = cKDTree(points.detach().cpu().double().numpy())
    distances, indices = tree.query(
        queries.detach().cpu().double().numpy(), k=k, workers=os.cpu_count() or 1
    )
    return distances.reshape(len(queries), k), indices.reshape(len(queries), k)
