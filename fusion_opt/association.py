"""Grouping estimates from several sources by target, at a processing node.

Each source reports an `Estimates` (m_k estimates of one n-dimensional state). `associate`
splits all of them into `Group`s: the estimates of one target, at most one per source;
every estimate lands in exactly one group (alone if nothing is close). Two estimates are
close when their distance over the state components `dims` (default: all),

    d(a, b) = || a[dims] - b[dims] ||_2,

is below `threshold`.

- "nearest" (the paper's rule): repeatedly join the closest pair of estimates from two
  different groups that share no source, while d < threshold (single-linkage clustering
  with at most one estimate per source). Beyond 64 estimates only pairs closer than the
  threshold are ever looked at (a k-d tree finds them), so the cost grows with the close
  pairs, not with the square of the number of estimates.
- "assignment": source by source, in the order of `reports`, an optimal assignment
  (scipy's linear_sum_assignment) of the source's estimates to the groups so far, by
  distance to each group's centroid, gated by the threshold; an estimate left unassigned
  opens a new group. Each assignment matches as many estimates as the gate allows and,
  among those, minimises the sum of distances (a pair outside the gate costs more than
  any number of pairs inside it, as in a global nearest neighbour whose missed cost is
  infinite): an estimate may join a group farther than its nearest one, within the
  threshold, so that one more estimate is matched.

A `Group` holds its members' sources, their track ids at those sources, and their means
and covariances, so a processing node fuses it as it is and its (source, id) pairs name
the source tracks it came from.
"""

from __future__ import annotations

import functools
from collections.abc import Hashable, Mapping
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

from .estimates import Estimates, track_ids
from .limits import fits, limits
from .linalg import jit, row_norms
from .results import FusionInputError, ReadOnly
from .validation import finite_real, hashable, is_integer, is_sequence, safe_repr

__all__ = ["METHODS", "Group", "associate"]
METHODS = ("nearest", "assignment")
# Thresholds and spans of points whose squares the k-d tree holds in float64 with room
_NORMAL = (1e-100, 1e100)


@dataclass(frozen=True, eq=False)
class Group(ReadOnly):
    """The estimates of one target, k of them, at most one per source (made by `associate`
    from validated reports; its arrays are read-only).

    sources (k,): distinct source names, in the order of the reports;
    ids (k,) int64: each member's track id at its source (ids of different sources may
    coincide, which is why a group is not an `Estimates`);
    means (k, n), covs (k, n, n): the members' estimates.
    Made by hand, it is checked as an `Estimates` is (but for the ids' uniqueness)."""

    sources: tuple[Hashable, ...]
    ids: np.ndarray
    means: np.ndarray
    covs: np.ndarray

    def __post_init__(self):
        sources = self.sources
        if isinstance(sources, str | bytes) or not isinstance(sources, tuple | list) \
                or not all(hashable(s) for s in sources) or len(set(sources)) != len(sources):
            raise FusionInputError(f"Group: sources must be distinct hashable names, got "
                                   f"{safe_repr(sources)}")
        try:
            checked = Estimates(self.means, self.covs)  # means (k, n), covs (k, n, n)
            ids = track_ids(self.ids, len(checked), unique=False)
        except FusionInputError as exc:
            raise FusionInputError(f"Group: {exc}") from None
        if len(checked) != len(sources):
            raise FusionInputError(f"Group: {len(sources)} sources but {len(checked)} "
                                   "estimates")
        self._set(tuple(sources), ids, checked.means, checked.covs)

    @classmethod
    def _of(cls, sources, ids, means, covs) -> Group:
        """A group of `associate`'s checked arrays, taken without copies or checks."""
        group = object.__new__(cls)
        group._set(sources, ids, means, covs)
        return group

    def _set(self, sources, ids, means, covs) -> None:
        ids.setflags(write=False)
        means.setflags(write=False)
        covs.setflags(write=False)
        self.__dict__.update(sources=sources, ids=ids, means=means, covs=covs)  # frozen

    def __len__(self) -> int:
        return len(self.sources)

    @functools.cached_property
    def pairs(self) -> tuple[tuple[Hashable, int], ...]:
        """(source, source track id) of each member: the source tracks the group joins
        (made once: a processing node reads it twice a step for every group)."""
        return tuple(zip(self.sources, self.ids.tolist(), strict=True))


def associate(reports: Mapping[Hashable, Estimates], threshold: float,
              method: str = "nearest", dims=None) -> list[Group]:
    """Groups of the estimates in `reports` (source -> Estimates), by `method` (module
    docstring); groups are ordered by their first member in the order of the reports."""
    threshold = check_threshold(threshold)
    check_method(method)
    dims = check_dims(dims)  # a list: an iterator is read once
    names, reports = _check_reports(reports)
    n = reports[0].n if reports else None
    return groups_of(names, reports, threshold, method, check_dims(dims, n))


def groups_of(names: list, reports: list[Estimates], threshold: float, method: str,
              dims: list[int] | None) -> list[Group]:
    """`associate` of checked arguments: the reports (all of one n) and their source names,
    threshold, method and dims as the checks above return them (a processing node checks
    its own once, not again at every step)."""
    if not reports:
        return []
    owner = np.concatenate([np.full(len(r), k) for k, r in enumerate(reports)])
    means = np.concatenate([r.means for r in reports])
    points = means if dims is None else means[:, dims]
    members = (_nearest if method == "nearest" else _assignment)(points, owner, threshold)
    covs = np.concatenate([r.covs for r in reports])
    ids = np.concatenate([r.ids for r in reports])
    source = [names[k] for k in owner.tolist()]  # each point's source name
    return [Group._of(tuple([source[j] for j in idx.tolist()]), ids[idx], means[idx], covs[idx])
            for idx in members]


def check_threshold(threshold) -> float:
    value = finite_real(threshold)
    if value is None or value <= 0:
        raise FusionInputError(f"threshold must be a positive finite distance, got "
                               f"{safe_repr(threshold)}")
    return value


def check_method(method) -> str:
    if method not in METHODS:
        raise FusionInputError(f"association method must be one of {METHODS}, got "
                               f"{safe_repr(method)}")
    return method


def check_dims(dims, n: int | None = None) -> list[int] | None:
    """dims: None (all components) or distinct integer components, each in [0, n)."""
    if dims is None:
        return None
    if not is_sequence(dims):
        raise FusionInputError(f"dims must be a sequence of state components, got "
                               f"{safe_repr(dims)}")
    dims = list(dims)
    if not dims or not all(map(is_integer, dims)) or len(set(dims)) != len(dims):
        raise FusionInputError(f"dims must be distinct integer state components, got "
                               f"{safe_repr(dims)}")
    if any(d < 0 for d in dims):
        raise FusionInputError(f"dims must be state components >= 0, got {safe_repr(dims)}")
    if n is not None and any(d >= n for d in dims):
        raise FusionInputError(f"dims {safe_repr(dims)} out of range for a state of dimension "
                               f"n = {n}")
    return [int(d) for d in dims]


def _check_reports(reports) -> tuple[list, list[Estimates]]:
    """(names, Estimates) of the reports; every report an Estimates, all of one n."""
    if not isinstance(reports, Mapping):
        raise FusionInputError(f"reports must be a mapping source -> Estimates, got "
                               f"{type(reports).__name__}")
    for name, r in reports.items():
        if not isinstance(r, Estimates):
            raise FusionInputError(f"report of source {safe_repr(name)} must be an Estimates, got "
                                   f"{type(r).__name__}")
    ns = {name: r.n for name, r in reports.items()}
    if len(set(ns.values())) > 1:
        raise FusionInputError(f"reports have different state dimensions n: {safe_repr(ns)}")
    return list(reports), list(reports.values())


def _nearest(points: np.ndarray, owner: np.ndarray, threshold: float) -> list[np.ndarray]:
    """Single-linkage with one member per source: points (M, d), owner (M,) source index.

    Joins never cross a connected component of the graph of close pairs, and a component
    holding at most one estimate per source ends as one group whatever the order of its
    joins; so only components with two estimates of one source are joined pair by pair."""
    M = len(points)
    if M == 0:
        return []
    pairs = _candidates(points, threshold)
    i, j = np.ascontiguousarray(pairs.T)
    with np.errstate(over="ignore"):  # a difference past float64 is inf: never near
        diff = points.take(i, axis=0) - points.take(j, axis=0)
    d, near = _distance(diff, threshold)
    keep = near & (owner.take(i) != owner.take(j))  # take: 3x indexing by a column's speed
    pairs, d = pairs[keep], d[keep]
    label = _components(pairs, M)
    conflicted = _repeats_a_source(label, owner)
    inside = conflicted[pairs[:, 0]]
    pairs, d, points = pairs[inside], d[inside], np.flatnonzero(conflicted)
    if points.size:
        n_sources = int(owner.max()) + 1
        if points.size * n_sources > limits.array_memory:
            raise FusionInputError(
                f"reports: {points.size} estimates from {n_sources} sources to join pair by "
                f"pair need {points.size * n_sources / 2**30:.3g} GiB, over "
                "fusion_opt.limits.array_memory")
        # by distance, then (i, j): np.lexsort's order, by two stable sorts in half its time
        by_pair = np.argsort(pairs[:, 0] * M + pairs[:, 1], kind="stable")
        order = by_pair[np.argsort(d[by_pair], kind="stable")]
        group = _joined(pairs[order], owner, points, n_sources)
        label[points] = M + group[points]  # fresh labels: components are numbered below M
    order = np.argsort(label, kind="stable")  # stable: members stay in report order
    ends = np.flatnonzero(np.diff(label[order])).tolist()  # np.split: 4x the time
    groups = [order[a + 1:b + 1] for a, b in zip([-1, *ends], [*ends, M - 1], strict=True)]
    return sorted(groups, key=lambda g: g[0])


def _candidates(points: np.ndarray, threshold: float) -> np.ndarray:
    """(P, 2), i < j: a superset of the pairs of points (M, d) closer than threshold:
    every pair up to _ALL_PAIRS points, else `_tree_candidates`. `_nearest` orders the
    pairs it keeps by (distance, i, j), so its groups do not depend on which superset."""
    if len(points) <= _ALL_PAIRS:
        return _all_pairs(len(points))
    return _tree_candidates(points, threshold)


# Up to this many points all M (M - 1) / 2 pairs are measured: building and querying the
# k-d tree cost more (about 40 us of a processing node's 0.5 ms step at 12 points).
_ALL_PAIRS = 64


@functools.lru_cache(maxsize=_ALL_PAIRS + 1)
def _all_pairs(M: int) -> np.ndarray:
    """Every pair (i, j) of M points, i < j, (M (M - 1) / 2, 2) intp, read-only (shared)."""
    pairs = np.ascontiguousarray(np.column_stack(np.triu_indices(M, 1)), dtype=np.intp)
    pairs.setflags(write=False)
    return pairs


def _tree_candidates(points: np.ndarray, threshold: float) -> np.ndarray:
    """`_candidates` by a k-d tree. In the normal range by its Euclidean distance, widened
    by far more than its rounding; else in the maximum norm, without squaring (coordinates
    of 1e200 overflow there), on halved points (pairs within threshold / 2 + rounding) if a
    span overflows the tree. The Euclidean query is the faster (1.0 against 1.8 ms at
    32 x 100 points)."""
    with np.errstate(over="ignore"):
        span = np.ptp(points, axis=0).max()
    if _NORMAL[0] < threshold < _NORMAL[1] and span < _NORMAL[1]:
        tree, r, p = cKDTree(points), threshold * (1.0 + 1e-9), 2.0
    else:
        tree, r, p = cKDTree(0.5 * points if not np.isfinite(span) else points), threshold, np.inf
    _pairs_fit(tree, r, p)
    return tree.query_pairs(r, p=p, output_type="ndarray")


def _pairs_fit(tree, r: float, p: float) -> None:
    """Refuses (before they are made) candidate pairs whose arrays would pass
    fusion_opt.limits.array_memory: every estimate within one threshold of every other
    makes M^2 / 2 of them (4 sources of 3,000 took 5.7 GB). A pair is counted at 8 + 2 d
    doubles, at most 1.25 times the peak of `_nearest` (its indices, the two points it
    takes, their difference, distance, masks and sort orders; tracemalloc, M = 1,200, 2 to
    1,200 sources: 55-78 bytes a pair at d = 1, 64-86 at d = 2, 96-102 at 4, 160 at 8,
    where 5 + d doubles were counted, too few: fuzz K5). Counted by the tree only when all
    M^2 / 2 pairs would not fit, so a usual step pays nothing for it."""
    M, d = tree.data.shape
    per_pair = pair_bytes(d)
    if per_pair * M * (M - 1) / 2 <= limits.array_memory:
        return
    pairs = (int(tree.count_neighbors(tree, r, p=p)) - M) / 2  # i != j, each once
    fits(f"reports: {M} estimates with {pairs:.0f} pairs within the threshold",
         per_pair * pairs)


def pair_bytes(d: int) -> float:
    """The bytes a candidate pair of points in d dimensions is counted at (`_pairs_fit`)."""
    return 8.0 * (8 + 2 * d)


def _distance(diff: np.ndarray, threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """Distances |diff| over the last axis in units of threshold's power of two s (the
    squares stay in float64 for any threshold; `_tiny` those whose squares underflow), and
    whether each is below threshold; a difference that overflowed (inf) is never below
    it."""
    s = _unit(threshold)
    with np.errstate(over="ignore", invalid="ignore"):
        scaled = diff / s
        d = np.sqrt(np.einsum("...k,...k->...", scaled, scaled))  # 5x np.linalg.norm's speed
    _tiny(d, lambda tiny: diff[tiny], s)
    return d, d < threshold / s


_TINY = 2.0**-480  # distances (units of s) below it may have squares under float64's range


def _tiny(d: np.ndarray, differences, s: float) -> None:
    """d (in units of s) again by `linalg.row_norms` where it is below _TINY: the squares
    of a distance under about 1e-154 of the threshold underflow, and such pairs all tied at
    0 in the join order, by index then, not by distance. differences(mask) gives their
    differences (..., k) in the input's units. The other distances keep their bits (the
    studies' groups with them)."""
    tiny = d < _TINY
    if tiny.any():
        d[tiny] = row_norms(differences(tiny)) / s


def _pair_differences(p: np.ndarray, c: np.ndarray, rows, cols) -> np.ndarray:
    """p[rows] - c[cols] (K, d): the differences of the pairs (rows[k], cols[k])."""
    return p[rows] - c[cols]


def _unit(threshold: float) -> float:
    """The power of two s in [threshold, 2 threshold), at most 2^1023 (2^1024 overflows:
    a threshold of 1e308 then grouped nothing), in which `_distance` measures."""
    return float(np.ldexp(1.0, min(int(np.frexp(threshold)[1]), 1023)))


def _centroid_distance(p: np.ndarray, c: np.ndarray, threshold: float):
    """`_distance` of points p (m, d) to centroids c (K, d), (m, K); by scipy's cdist
    (faster than the differences) unless a coordinate in units of s overflows."""
    s = _unit(threshold)
    with np.errstate(over="ignore"):
        ps, cs = p / s, c / s
    if np.isfinite(ps).all() and np.isfinite(cs).all():
        with np.errstate(over="ignore"):
            d = cdist(ps, cs)
        _tiny(d, lambda tiny: _pair_differences(p, c, *tiny.nonzero()), s)
        return d, d < threshold / s
    d, near = np.empty((len(p), len(c))), np.empty((len(p), len(c)), dtype=bool)
    for i in range(len(p)):  # a row at a time: the (m, K, d) differences at once made every
        with np.errstate(over="ignore"):  # step count d doubles a cell more (fuzz K10)
            diff = p[i] - c  # a difference past float64 is inf: never near
        d[i], near[i] = _distance(diff, threshold)
    return d, near


@jit
def _components(pairs, M):
    """(M,) a label per point, equal exactly within the connected components of the graph
    of pairs (P, 2): the smallest point index of the component. Union-find that keeps the
    smaller root, so a root is its set's smallest index and every parent[i] <= i; read in
    increasing i, parent[parent[i]] is then i's root. Compiled: scipy's sparse
    connected_components costs 150 us of setup and numpy's min-label propagation 11 us for
    a handful of points, more than a whole fusion of them."""
    parent = np.arange(M)
    for p in range(pairs.shape[0]):
        a, b = _root(parent, pairs[p, 0]), _root(parent, pairs[p, 1])
        if a < b:
            parent[b] = a
        elif b < a:
            parent[a] = b
    for i in range(M):
        parent[i] = parent[parent[i]]
    return parent


@jit
def _root(parent, i):
    """The root of i, halving the path to it."""
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


@jit
def _repeats_a_source(label, owner):
    """(M,) True for the points of components (labels in [0, M)) holding two estimates of
    one source (owner (M,) >= 0): the points ordered by component (a counting sort), each
    component's sources stamped in turn (O(M) plus one stamp per source)."""
    M = label.size
    start = np.zeros(M + 1, dtype=np.int64)
    for i in range(M):
        start[label[i] + 1] += 1
    for c in range(M):
        start[c + 1] += start[c]
    order, fill = np.empty(M, dtype=np.int64), start[:M].copy()
    for i in range(M):
        order[fill[label[i]]] = i
        fill[label[i]] += 1
    stamp = np.full(owner.max() + 1, -1)
    repeats = np.zeros(M, dtype=np.bool_)
    for c in range(M):
        for t in range(start[c], start[c + 1]):
            s = owner[order[t]]
            repeats[c] |= stamp[s] == c
            stamp[s] = c
    out = np.empty(M, dtype=np.bool_)
    for i in range(M):
        out[i] = repeats[label[i]]
    return out


@jit
def _joined(pairs, owner, points, n_sources):
    """Starting from the points (C,) alone, join the groups of each pair of pairs (P, 2),
    in that order (by distance), unless they share a source (owner (M,) in
    [0, n_sources)); returns each point's group (M,), a point of it (-1 off points).
    Compiled: 1,000 estimates from each of 3 sources, all within the threshold, make 3
    million pairs, whose Python loop took 2.1 s of `associate`'s 4.8 (now 0.02 s). Members
    are a linked list (nxt), the smaller group joins the larger; has[slot, s]: the group
    of that slot has source s."""
    M = owner.size
    group, slot = np.full(M, -1), np.full(M, -1)
    nxt, tail, size = np.full(M, -1), np.full(M, -1), np.zeros(M, dtype=np.int64)
    has = np.zeros((points.size, n_sources), dtype=np.bool_)
    for c in range(points.size):
        i = points[c]
        group[i], slot[i], tail[i], size[i] = i, c, i, 1
        has[c, owner[i]] = True
    for p in range(pairs.shape[0]):
        ga, gb = group[pairs[p, 0]], group[pairs[p, 1]]
        if ga == gb:
            continue
        if size[ga] < size[gb]:
            ga, gb = gb, ga
        m = gb
        while m >= 0 and not has[slot[ga], owner[m]]:
            m = nxt[m]
        if m >= 0:  # a member of gb has a source of ga
            continue
        m = gb
        while m >= 0:
            group[m] = ga
            has[slot[ga], owner[m]] = True
            m = nxt[m]
        nxt[tail[ga]] = gb
        tail[ga], size[ga] = tail[gb], size[ga] + size[gb]
    return group


def _assignment(points: np.ndarray, owner: np.ndarray, threshold: float) -> list[np.ndarray]:
    """Source by source, gated optimal assignment to the groups' centroids; refused before
    it starts when a source's cost matrix against up to all M estimates' groups, with its
    distances, gate and the solver's copy (about 4 doubles a cell), would pass
    fusion_opt.limits.array_memory (16 sources of 4,000 took 4.2 GB)."""
    M, d = points.shape
    most = int(np.bincount(owner).max(initial=0))
    fits(f"reports: {M} estimates, up to {most} from one source, assigned to up to {M} groups",
         8.0 * most * M * 4)
    groups: list[list[int]] = []
    centroids: list[np.ndarray] = []
    s = _unit(threshold)
    for k in np.unique(owner):
        flat = np.flatnonzero(owner == k)
        p = points[flat]
        rows = cols = np.array([], dtype=int)
        if groups:
            cost, near = _centroid_distance(p, np.array(centroids), threshold)
            rows, cols = linear_sum_assignment(np.where(near, cost, 1e6 * (threshold / s)))
            ok = near[rows, cols]
            rows, cols = rows[ok], cols[ok]
        for i, g in zip(rows.tolist(), cols.tolist(), strict=True):
            groups[g].append(int(flat[i]))
            centroids[g] = centroids[g] + (p[i] - centroids[g]) / len(groups[g])
        for i in sorted(set(range(len(p))) - set(rows.tolist())):
            groups.append([int(flat[i])])
            centroids.append(p[i].copy())
    return [np.array(g) for g in sorted(groups, key=min)]
