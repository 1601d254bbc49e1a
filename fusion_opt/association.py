"""Grouping estimates from several nodes by target, at a processing node.

Node k sends m_k estimates (means (m_k, n)). A group holds at most one estimate per node;
every estimate lands in exactly one group (a singleton if nothing is close). Distances are
Euclidean over the state components `dims` (default: all).

- "nearest" (the paper's rule): repeatedly join the closest pair of estimates from two
  different groups that share no node, while that distance is below the threshold
  (single-linkage clustering with one estimate per node).
- "assignment": node by node, an optimal assignment (scipy's linear_sum_assignment) of the
  node's estimates to the groups so far, by distance to each group's centroid, gated by
  the threshold; unassigned estimates open new groups.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial.distance import cdist

from .results import FusionInputError

Group = list[tuple[int, int]]  # (node, estimate index) pairs


def associate(means: Sequence, threshold: float, method: str = "nearest",
              dims=None) -> list[Group]:
    """Groups of (node, index) over the estimates means[k] (m_k, n) of each node k."""
    points = _check(means, threshold, dims)
    if method == "nearest":
        return _nearest(points, threshold)
    if method == "assignment":
        return _assignment(points, threshold)
    raise FusionInputError(f"method must be 'nearest' or 'assignment', got {method!r}")


def _check(means, threshold, dims) -> list[np.ndarray]:
    if not np.isfinite(threshold) or threshold <= 0:
        raise FusionInputError(f"threshold must be a positive finite distance, got {threshold}")
    points = []
    for k, m in enumerate(means):
        m = np.asarray(m, dtype=float)
        if m.size == 0:
            m = m.reshape(0, m.shape[-1] if m.ndim == 2 else 0)
        if m.ndim != 2:
            raise FusionInputError(f"means of node {k} must have shape (m, n), got {m.shape}")
        if not np.all(np.isfinite(m)):
            raise FusionInputError(f"means of node {k} has a non-finite value")
        points.append(m if dims is None or m.shape[0] == 0 else m[:, dims])
    return points


def _nearest(points, threshold) -> list[Group]:
    labels = [(k, i) for k, p in enumerate(points) for i in range(len(p))]
    if not labels:
        return []
    X = np.concatenate([p for p in points if len(p)])
    node = np.array([k for k, _ in labels])
    D = cdist(X, X)
    D[node[:, None] == node[None, :]] = np.inf
    group = np.arange(len(labels))
    members = {g: {int(node[g])} for g in group}
    for flat in np.argsort(D, axis=None):
        a, b = np.unravel_index(flat, D.shape)
        if D[a, b] >= threshold:
            break
        ga, gb = group[a], group[b]
        if ga == gb or members[ga] & members[gb]:
            continue
        group[group == gb] = ga
        members[ga] |= members.pop(gb)
    return [[labels[j] for j in np.flatnonzero(group == g)] for g in np.unique(group)]


def _assignment(points, threshold) -> list[Group]:
    groups: list[Group] = []
    centroids: list[np.ndarray] = []
    for k, p in enumerate(points):
        rows = cols = np.array([], dtype=int)
        if len(p) and groups:
            cost = cdist(p, np.array(centroids))
            gated = np.where(cost < threshold, cost, 1e6 * threshold)
            rows, cols = linear_sum_assignment(gated)
            ok = cost[rows, cols] < threshold
            rows, cols = rows[ok], cols[ok]
        for i, g in zip(rows, cols, strict=True):
            groups[g].append((k, int(i)))
            n_g = len(groups[g])
            centroids[g] = centroids[g] + (p[i] - centroids[g]) / n_g
        for i in sorted(set(range(len(p))) - set(rows.tolist())):
            groups.append([(k, i)])
            centroids.append(p[i].copy())
    return groups
