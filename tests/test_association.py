"""Association of estimates across sources: hand-made cases for both rules, the groups'
contents against the reports, a brute-force reference for "nearest", and bad input."""

import itertools
import warnings

import numpy as np
import pytest

import fusion_opt as fo


def _reports(*means, ids=None):
    """Source k -> Estimates with means[k] (m_k, n), covariances k + 1 times I."""
    out = {}
    for k, m in enumerate(means):
        m = np.asarray(m, dtype=float)
        n = m.shape[1]
        covs = np.broadcast_to((k + 1.0) * np.eye(n), (len(m), n, n))
        out[f"s{k}"] = fo.Estimates(m, covs, None if ids is None else ids[k])
    return out


def _pairs(groups):
    return sorted(sorted(g.pairs) for g in groups)


@pytest.mark.parametrize("method", ["nearest", "assignment"])
def test_two_targets_three_sources(method):
    reports = _reports([[0.0, 0.0], [5.0, 5.0]], [[5.1, 4.9], [0.1, -0.1]], [[0.05, 0.0]])
    groups = fo.associate(reports, threshold=1.0, method=method)
    assert _pairs(groups) == [[("s0", 0), ("s1", 1), ("s2", 0)], [("s0", 1), ("s1", 0)]]


@pytest.mark.parametrize("method", ["nearest", "assignment"])
def test_groups_carry_the_members_estimates_and_source_ids(method):
    rng = np.random.default_rng(0)
    means = [rng.normal(size=(4, 3)) * 10 for _ in range(3)]
    ids = [rng.choice(100, size=4, replace=False) for _ in range(3)]
    reports = _reports(*means, ids=ids)
    groups = fo.associate(reports, threshold=3.0, method=method)
    seen = []
    for g in groups:
        assert len(g) == len(g.means) == len(g.covs) and len(set(g.sources)) == len(g)
        assert list(g.sources) == sorted(g.sources)  # in the order of the reports
        for (source, track), mean, cov in zip(g.pairs, g.means, g.covs, strict=True):
            r = reports[source]
            i = int(np.flatnonzero(r.ids == track)[0])
            np.testing.assert_array_equal(mean, r.means[i])
            np.testing.assert_array_equal(cov, r.covs[i])
            seen.append((source, track))
    assert sorted(seen) == sorted((s, int(i)) for s, r in reports.items() for i in r.ids)


@pytest.mark.parametrize("method", ["nearest", "assignment"])
def test_far_estimates_stay_single_and_one_per_source(method):
    reports = _reports([[0.0, 0.0], [0.3, 0.0]], [[10.0, 0.0]])
    reports["s2"] = fo.Estimates.empty(2)
    groups = fo.associate(reports, threshold=1.0, method=method)
    # the two close estimates come from the same source: they must not be joined
    assert _pairs(groups) == [[("s0", 0)], [("s0", 1)], [("s1", 0)]]


def test_nearest_takes_the_closest_pair_first():
    groups = fo.associate(_reports([[0.0]], [[0.5]], [[0.45]]), threshold=1.0)
    assert _pairs(groups) == [[("s0", 0), ("s1", 0), ("s2", 0)]]
    # s0's two estimates compete for s1's: the closer one (0.9) wins, 0.0 stays alone
    groups = fo.associate(_reports([[0.0], [0.9]], [[0.5]]), threshold=1.0)
    assert _pairs(groups) == [[("s0", 0)], [("s0", 1), ("s1", 0)]]


def _nearest_brute(points, owner, threshold):
    """Reference: join the closest admissible pair, recomputed from scratch each time."""
    groups = [{i} for i in range(len(points))]
    while True:
        best = None
        for a, b in itertools.combinations(range(len(groups)), 2):
            if {owner[i] for i in groups[a]} & {owner[i] for i in groups[b]}:
                continue
            d = min(np.linalg.norm(points[i] - points[j]) for i in groups[a] for j in groups[b])
            if d < threshold and (best is None or d < best[0]):
                best = (d, a, b)
        if best is None:
            return sorted(sorted(g) for g in groups)
        _, a, b = best
        groups[a] |= groups.pop(b)


def test_nearest_equals_brute_force_single_linkage():
    rng = np.random.default_rng(1)
    for _ in range(20):
        means = [rng.uniform(0, 4, size=(rng.integers(0, 5), 2)) for _ in range(4)]
        reports = _reports(*means)
        offsets = np.cumsum([0] + [len(m) for m in means])
        flat = {(f"s{k}", i): offsets[k] + i for k, m in enumerate(means) for i in range(len(m))}
        got = sorted(sorted(flat[p] for p in g.pairs) for g in fo.associate(reports, 1.0))
        points = np.concatenate([m.reshape(-1, 2) for m in means])
        owner = np.concatenate([np.full(len(m), k) for k, m in enumerate(means)])
        assert got == _nearest_brute(points, owner, 1.0)


def test_assignment_is_gated_optimal():
    # s1's 0.6 is nearer to both of s0's; the assignment gives each its best overall match
    groups = fo.associate(_reports([[0.0], [1.0]], [[0.6], [1.7]]), 1.0, "assignment")
    assert _pairs(groups) == [[("s0", 0), ("s1", 0)], [("s0", 1), ("s1", 1)]]
    groups = fo.associate(_reports([[0.0]], [[1.5]]), 1.0, "assignment")  # gated out
    assert len(groups) == 2


def test_dims_select_the_compared_components():
    reports = _reports([[0.0, 0.0, 9.0]], [[0.1, 0.0, -9.0]])
    assert len(fo.associate(reports, 1.0)) == 2
    assert len(fo.associate(reports, 1.0, dims=[0, 1])) == 1


def test_no_reports_no_groups():
    assert fo.associate({}, 1.0) == []
    assert fo.associate({"a": fo.Estimates.empty(3)}, 1.0, "assignment") == []


@pytest.mark.parametrize("kwargs, match", [
    (dict(threshold=0.0), "threshold"),
    (dict(threshold="1"), "threshold"),
    (dict(threshold=True), "threshold"),
    (dict(threshold=np.inf), "threshold"),
    (dict(threshold=1.0, method="magic"), "method"),
    (dict(threshold=1.0, dims=[0, 2]), r"dims \[0, 2\] out of range .* n = 2"),
    (dict(threshold=1.0, dims=[-1]), r"dims must be state components >= 0, got \[-1\]"),
    (dict(threshold=1.0, dims=[0.5]), "dims"),
    (dict(threshold=1.0, dims="xy"), "dims"),
    (dict(threshold=1.0, dims=[]), "dims"),
])
def test_bad_arguments_are_named(kwargs, match):
    with pytest.raises(fo.FusionInputError, match=match):
        fo.associate(_reports([[0.0, 0.0]], [[1.0, 0.0]]), **kwargs)


def test_bad_reports_are_named():
    with pytest.raises(fo.FusionInputError, match="mapping"):
        fo.associate([np.zeros((1, 2))], 1.0)
    with pytest.raises(fo.FusionInputError, match="source 'b'.*Estimates"):
        fo.associate({"a": fo.Estimates.empty(2), "b": np.zeros((1, 2))}, 1.0)
    reports = {"a": fo.Estimates(np.zeros((1, 2)), np.eye(2)[None]),
               "b": fo.Estimates(np.zeros((1, 3)), np.eye(3)[None])}
    with pytest.raises(fo.FusionInputError, match="different state dimensions.*'a': 2.*'b': 3"):
        fo.associate(reports, 1.0)


def test_components_equal_scipys_connected_components():
    """The union of `_nearest` against scipy's graph components on random graphs: the same
    partition, each labelled by its smallest point; and the components holding two points
    of one source against a count of (component, source)."""
    from collections import Counter

    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from fusion_opt.association import _components, _repeats_a_source

    rng = np.random.default_rng(3)
    for M, P in [(1, 0), (5, 0), (10, 4), (50, 40), (200, 150), (200, 600)]:
        pairs = np.sort(rng.integers(0, M, (P, 2)), axis=1).reshape(P, 2)
        label = _components(pairs, M)
        graph = coo_matrix((np.ones(P), (pairs[:, 0], pairs[:, 1])), shape=(M, M))
        ref = connected_components(graph, directed=False)[1]
        same, same_ref = label[:, None] == label[None], ref[:, None] == ref[None]
        np.testing.assert_array_equal(same, same_ref)
        np.testing.assert_array_equal(label, [np.flatnonzero(ref == r).min() for r in ref])
        owner = rng.integers(0, 4, M)
        count = Counter(zip(label.tolist(), owner.tolist(), strict=True))
        repeated = {c for (c, _), k in count.items() if k > 1}
        np.testing.assert_array_equal(_repeats_a_source(label, owner),
                                      [c in repeated for c in label.tolist()])


@pytest.mark.parametrize("method", fo.association.METHODS)
def test_coordinates_and_thresholds_at_the_ends_of_float64(method):
    """Regression: points 3.4e308 apart overflowed scipy's k-d tree (a raw ValueError), a
    threshold of 1e303 overflowed the assignment's gate cost 1e6 x threshold (cost matrix
    infeasible), and squared distances of 1e190 overflowed, so a pair 1e190 apart was not
    within a threshold of 1e195."""
    cases = ((([[1.7e308] * 2], [[-1.7e308] * 2]), 1.0, [[("s0", 0)], [("s1", 0)]]),
             (([[0.0, 0.0]], [[1.0, 1.0]], [[5e307, 0.0]]), 1e303,
              [[("s0", 0), ("s1", 0)], [("s2", 0)]]),
             (([[1e200, 1e200]], [[1e200 + 1e190, 1e200]]), 1e195, [[("s0", 0), ("s1", 0)]]),
             (([[1e200, 1e200]], [[1e200, 1e200]]), 1e-300, [[("s0", 0), ("s1", 0)]]),
             (([[1e-300, 0.0]], [[3e-300, 0.0]]), 1e-300, [[("s0", 0)], [("s1", 0)]]),
             # 2^1024 overflowed the distances' unit: a threshold of 1e308 grouped nothing
             (([[0.0, 0.0]], [[0.1, 0.0]]), np.finfo(float).max, [[("s0", 0), ("s1", 0)]]),
             (([[0.0, 0.0]], [[0.1, 0.0]]), 1e308, [[("s0", 0), ("s1", 0)]]))
    for means, threshold, want in cases:
        groups = fo.associate(_reports(*means), threshold, method)
        assert [list(g.pairs) for g in groups] == want


def test_dims_may_be_an_iterator():
    """Regression: dims was read twice, so a generator was refused as "got []"."""
    groups = fo.associate(_reports([[0.0, 0.0]], [[0.5, 9.0]]), 1.0, dims=(d for d in [0]))
    assert _pairs(groups) == [[("s0", 0), ("s1", 0)]]


def test_joining_pair_by_pair_checks_the_memory_limit(monkeypatch):
    """The compiled joins keep an estimates x sources table: checked before allocating."""
    from fusion_opt import association

    reports = _reports([[0.0, 0.0], [0.2, 0.0]], [[0.1, 0.0]])
    monkeypatch.setattr(fo.limits, "array_memory", fo.limits.array_memory)
    monkeypatch.setattr(association, "_pairs_fit", lambda *args: None)  # the pairs' own check
    fo.limits.array_memory = 4.0  # 2 estimates of s0 and one of s1 in one component: 3 x 2
    with pytest.raises(fo.FusionInputError, match="3 estimates from 2 sources"):
        fo.associate(reports, 1.0)


def test_candidate_pairs_hold_every_pair_closer_than_the_threshold():
    """`_tree_candidates` (the k-d tree's Euclidean query in the normal range, the maximum
    norm beyond it) misses no pair that `_distance` puts within the threshold, at scales
    from 1e-120 to 1e120 and with pairs one ulp either side of it (brute force over all
    pairs)."""
    from fusion_opt.association import _distance
    from fusion_opt.association import _tree_candidates as _candidates

    rng = np.random.default_rng(7)
    for scale in (1e-120, 1e-99, 1e-30, 1.0, 1e30, 1e99, 1e120):
        for _ in range(5):
            points = scale * rng.uniform(0, 3, size=(60, 2))
            # pairs at exactly the threshold's distance and one ulp inside it
            threshold = float(np.linalg.norm(points[1] - points[0]))
            points[2] = points[0] + np.nextafter(points[1] - points[0], 0)
            i, j = np.triu_indices(len(points), 1)
            near = _distance(points[i] - points[j], threshold)[1]
            got = {tuple(p) for p in _candidates(points, threshold).tolist()}
            missed = [(a, b) for a, b, c in zip(i, j, near, strict=True) if c and (a, b) not in got]
            assert not missed, (scale, missed)
            assert near.any()


def test_groups_are_the_same_from_all_pairs_and_from_the_tree(monkeypatch):
    """Up to `_ALL_PAIRS` estimates every pair is a candidate, beyond it the k-d tree's: the
    groups are the same either way (here: 40 estimates from 4 sources, many components
    holding two of one source, so that pairs are joined one by one in their order), at
    scales from 1e-120 to 1e120."""
    from fusion_opt import association

    joins = []
    joined = association._joined
    monkeypatch.setattr(association, "_joined", lambda *a: joins.append(1) or joined(*a))
    rng = np.random.default_rng(11)
    for scale in (1e-120, 1.0, 1e120):
        for _ in range(20):
            reports = {f"s{k}": fo.Estimates(scale * rng.uniform(0, 4, size=(10, 2)),
                                             np.broadcast_to(np.eye(2), (10, 2, 2)))
                       for k in range(4)}
            threshold = scale * rng.uniform(0.2, 1.0)
            small = fo.associate(reports, threshold)
            monkeypatch.setattr(association, "_ALL_PAIRS", 0)
            tree = fo.associate(reports, threshold)
            monkeypatch.setattr(association, "_ALL_PAIRS", 64)
            assert [g.pairs for g in small] == [g.pairs for g in tree]
    assert len(joins) > 100  # most of the 60 cases joined pairs one by one (both ways)


def test_means_near_the_float_limit_raise_no_warning():
    """Fuzz F3: differences of means past float64 (1.7e308 - (-1.7e308)) warned of an
    overflow from inside associate and a processing node (an error under -W error); such a
    difference is a distance past every threshold."""
    def est(x):
        x = np.asarray(x, float)
        return fo.Estimates(x, np.broadcast_to(np.eye(x.shape[1]), (*x.shape, x.shape[1])))

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        groups = fo.associate({"a": est([[-1.7e308]]), "b": est([[1e307]]),
                               "c": est([[1.7e308]])}, 1.7e308)
        assert sorted(len(g) for g in groups) == [1, 2]  # b joins c; a - c overflows
        fo.associate({"a": est([[1e300, -1e300], [-1.7e308, 1.7e308]]),
                      "b": est([[1e300, -1e300], [1.7e308, -1.7e308]])}, 1e-300, "assignment")
        node = fo.ProcessingNode(["a", "b"], threshold=1.0, method="bci")
        for k in range(2):
            scan = est([[1e300 * (k + 1), -1e300]])
            node.step({"a": scan, "b": scan}, time=float(k))


def test_an_assignment_beyond_array_memory_is_refused_before_it_starts(monkeypatch):
    """Fuzz F2: "assignment" built each source's cost matrix against every group without a
    check (16 sources of 4,000 estimates: 28 s and 4.2 GB against a 4 GiB limit), where
    "nearest" checked its own arrays."""
    monkeypatch.setattr(fo.limits, "array_memory", 2**20)
    rng = np.random.default_rng(0)
    reports = {s: fo.Estimates(rng.uniform(0, 1e6, (200, 2)), np.broadcast_to(np.eye(2),
                                                                                (200, 2, 2)))
               for s in "abc"}
    with pytest.raises(fo.FusionInputError, match=r"^reports: 600 estimates, up to 200 from one "
                                                  r"source.*fusion_opt.limits.array_memory"):
        fo.associate(reports, 1.0, "assignment")
    assert len(fo.associate(reports, 1.0, "nearest")) == 600  # what fits is not refused


def test_nearest_with_more_close_pairs_than_memory_is_refused_before_making_them(monkeypatch):
    """Fuzz F9: every estimate within the threshold of every other made all M^2 / 2 pairs
    without a check (4 sources of 3,000: 49 s and 5.7 GB past the 4 GiB limit). The pairs
    are counted only when all of them could not fit; well-apart estimates still group."""
    monkeypatch.setattr(fo.limits, "array_memory", 2**20)
    rng = np.random.default_rng(0)

    def reports(spread):
        return {s: fo.Estimates(rng.uniform(0, spread, (200, 2)),
                                np.broadcast_to(np.eye(2), (200, 2, 2))) for s in "abcd"}

    with pytest.raises(fo.FusionInputError, match=r"^reports: 800 estimates with \d+ pairs "
                                                  r"within the threshold.*array_memory"):
        fo.associate(reports(1e-3), 1.0)
    assert len(fo.associate(reports(1e6), 1.0)) == 800  # 800^2 / 2 pairs would not fit


@pytest.mark.parametrize("d", [1, 2, 4, 8])
@pytest.mark.parametrize("sources", [2, 12, 600])
def test_the_memory_counted_for_close_pairs_covers_what_nearest_allocates(d, sources):
    """Fuzz K5: the pairs' arrays were counted at 5 + d doubles a pair, up to 40% below what
    `_nearest` allocates at its peak (tracemalloc, which sees numpy's arrays), so that a
    step past the limit could pass the check. The count now covers the peak, within 25%."""
    import tracemalloc

    from fusion_opt.association import _nearest, pair_bytes

    rng = np.random.default_rng(d)
    M = 600
    points, owner = 1e-3 * rng.normal(size=(M, d)), np.arange(M) % sources
    _nearest(points, owner, 1.0)  # every pair within the threshold
    tracemalloc.start()
    try:
        _nearest(points, owner, 1.0)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    counted = pair_bytes(d) * M * (M - 1) / 2
    assert 1.0 <= counted / peak <= 1.5, counted / peak


def test_assignment_counts_the_cells_of_the_path_that_runs(monkeypatch):
    """Fuzz K10: "assignment" counted d doubles a cell more for the differences of its
    overflow fallback (coordinates near 1e308), which now runs a row at a time, so that at
    n = 100 it refused steps that need a 26th of that; the fallback still groups alike."""
    from fusion_opt.limits import limits

    rng = np.random.default_rng(4)
    m, d = 50, 100
    T = rng.uniform(0, 1e3, (m, d))
    reports = {s: fo.Estimates(T + 1e-3 * rng.normal(size=T.shape),
                               np.broadcast_to(np.eye(d), (m, d, d))) for s in "ab"}
    monkeypatch.setattr(limits, "array_memory", 8.0 * m * 2 * m * 5)  # 5 doubles a cell
    assert len(fo.associate(reports, 1.0, "assignment")) == m
    # coordinates near 1.7e308 in units of a threshold below 1 overflow: the fallback runs
    # (its differences, 0 or at least 1e300 here, are exact)
    big = 1.7e308 - 1e300 * np.arange(m)[:, None] * np.ones((m, 2))
    groups = fo.associate({s: fo.Estimates(big, np.broadcast_to(np.eye(2), (m, 2, 2)))
                           for s in "ab"}, 0.25, "assignment")
    assert sorted(g.pairs for g in groups) == sorted((("a", i), ("b", i)) for i in range(m))


@pytest.mark.parametrize("method", fo.association.METHODS)
@pytest.mark.parametrize("scale", [1e-170, 1e-300])
def test_distances_whose_squares_underflow_still_order_the_joins(method, scale):
    """Source a reports two estimates 2 scale apart, source b one between them, 0.5 scale
    from a's nearer one: b joins that one. Distances below about 1e-154 of the threshold
    had squares of 0, tied, and b joined a's first estimate by index (both methods)."""
    def at(xs):
        return fo.Estimates(np.array([[x, 0.0] for x in xs]), np.tile(np.eye(2), (len(xs), 1, 1)))

    for a, b, near in (([0.0, 2 * scale], [1.5 * scale], 1), ([2 * scale, 0.0], [0.5 * scale], 1),
                       ([0.0, 2 * scale], [0.5 * scale], 0)):
        groups = fo.associate({"a": at(a), "b": at(b)}, 1.0, method)
        assert sorted(g.pairs for g in groups) == sorted([(("a", near), ("b", 0)),
                                                          (("a", 1 - near),)])


@pytest.mark.parametrize("dims", [np.array(0), np.array([0, 1])[0], np.ma.masked_array(1)])
def test_dims_of_a_0d_array_or_a_scalar_are_refused_by_name(dims):
    """Fuzz U6: a 0-d array has __iter__ but raises TypeError when iterated; dims=[0] is the
    way to give one component."""
    report = {"a": fo.Estimates([[0.0, 0.0]], [np.eye(2)])}
    with pytest.raises(fo.FusionInputError, match="dims must be a sequence of state components"):
        fo.associate(report, 1.0, dims=dims)
    with pytest.raises(fo.FusionInputError, match="dims must be a sequence of state components"):
        fo.ProcessingNode(["a"], method="bci", threshold=1.0, dims=dims)
