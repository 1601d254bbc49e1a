"""ProcessingNode: fused tracks against fo.fuse on their groups, persistent fused ids,
time, batching by group size, and bad input named."""

import numpy as np
import pytest
from conftest import random_spd

import fusion_opt as fo
import fusion_opt.processing as processing

P_DETECT = {"a": 0.9, "b": 0.7, "c": 0.8, "d": 0.95}


def _scene(rng, sources, n_targets, n=4, spacing=20.0, p_seen=0.8, noise=0.3):
    """{source: Estimates}: each source sees each target with probability p_seen, with
    a random covariance and random unique track ids; targets `spacing` apart."""
    truth = spacing * np.arange(n_targets)[:, None] * np.ones(n)
    reports = {}
    for s in sources:
        seen = np.flatnonzero(rng.random(n_targets) < p_seen)
        means = truth[seen] + noise * rng.standard_normal((len(seen), n))
        covs = np.array([random_spd(rng, n) for _ in seen]).reshape(len(seen), n, n)
        ids = rng.choice(1000, size=len(seen), replace=False)
        reports[s] = fo.Estimates(means, covs, ids)
    return reports


def _check_as_checked(fused):
    """The node's Estimates, made without checks (`Estimates._of`), are what the checked
    constructor makes of them, bit for bit (covariances exactly symmetric and positive
    definite, means finite, ids unique), and read-only."""
    again = fo.Estimates(fused.means, fused.covs, fused.ids, fused.time, fused.node)
    for name in ("means", "covs", "ids"):
        np.testing.assert_array_equal(getattr(fused, name), getattr(again, name))
        assert getattr(fused, name).dtype == getattr(again, name).dtype
        assert not getattr(fused, name).flags.writeable


def _check_against_fuse(node, reports, fused, method_args):
    """Every fused track is fo.fuse (Clarabel) on its group; singletons unchanged."""
    _check_as_checked(fused)
    assert sorted(sorted(g.pairs) for g in node.groups.values()) == sorted(
        sorted(g.pairs) for g in fo.associate(reports, node.threshold, node.association,
                                              node.dims) if len(g) >= node.min_sources)
    assert fused.ids.tolist() == sorted(node.groups)
    for fid, mean, cov in zip(fused.ids, fused.means, fused.covs, strict=True):
        g = node.groups[int(fid)]
        if len(g) == 1:
            np.testing.assert_array_equal(mean, g.means[0])
            np.testing.assert_array_equal(cov, g.covs[0])
            continue
        args = method_args(g)
        if node.method in processing.CI_FAMILY:  # the conic reference, not the node's newton
            args["backend"] = "clarabel"
        ref = fo.fuse(g.means, g.covs, node.method, node.criterion, **args)
        np.testing.assert_allclose(mean, ref.mean, rtol=1e-9, atol=1e-9 * np.abs(ref.mean).max())
        np.testing.assert_allclose(cov, ref.cov, rtol=1e-9, atol=1e-9 * np.abs(ref.cov).max())


@pytest.mark.parametrize("method, criterion", [
    ("bci", "trace"), ("bci", "logdet"), ("mbci", "trace"), ("mbci", "logdet"),
    ("naive", "trace"), ("fast-ci", "trace"), ("ifci", "trace")])
def test_fused_tracks_equal_fuse_on_their_groups(method, criterion):
    rng = np.random.default_rng(10)
    kw = dict(p_detect=P_DETECT, growth=1.2) if method == "mbci" else {}
    node = fo.ProcessingNode(list(P_DETECT), method=method, criterion=criterion,
                             threshold=3.0, **kw)

    def method_args(g):
        if method != "mbci":
            return {}
        return dict(p_detect=[P_DETECT[s] for s in g.sources], chi=1 / 1.2)

    sizes = set()
    for _ in range(4):
        reports = _scene(rng, P_DETECT, n_targets=6)
        fused = node.step(reports)
        _check_against_fuse(node, reports, fused, method_args)
        sizes |= {len(g) for g in node.groups.values()}
    assert sizes == {1, 2, 3, 4}  # every group size was exercised


@pytest.mark.parametrize("method", ["bci", "mbci", "naive", "fast-ci", "ifci", "ici", "ei"])
def test_fused_estimates_pass_the_checks_at_extreme_scales(method):
    """Covariances from 1e-150 to 1e150 and condition up to 1e10, symmetric only within
    the Estimates' tolerance as reported: every fused step is what the checked Estimates
    constructor makes of it (`_check_as_checked`)."""
    rng = np.random.default_rng(12)
    sources = ["a", "b"] if method in ("ici", "ei") else list(P_DETECT)
    kw = dict(p_detect={s: P_DETECT[s] for s in sources}, growth=1.2) if method == "mbci" \
        else {}
    for scale in (1e-150, 1e-20, 1.0, 1e20, 1e150):
        reports = _scene(rng, sources, n_targets=4, spacing=20.0 * np.sqrt(scale),
                         noise=0.3 * np.sqrt(scale))
        for s, r in reports.items():
            Q = np.linalg.qr(rng.standard_normal((len(r), 4, 4)))[0]
            eig = np.exp(rng.uniform(0, np.log(1e10), (len(r), 4)))
            covs = scale * (Q * eig[:, None, :]) @ Q.transpose(0, 2, 1)
            covs[:, 0, 1] *= 1 + 1e-12  # asymmetric within the tolerance
            reports[s] = fo.Estimates(r.means, covs, r.ids)
        node = fo.ProcessingNode(sources, method=method, threshold=3.0 * np.sqrt(scale), **kw)
        _check_as_checked(node.step(reports))
        assert max(len(g) for g in node.groups.values()) > 1  # something was fused


@pytest.mark.parametrize("method", ["ci", "ici", "ei"])
def test_pairwise_methods_with_two_sources(method):
    rng = np.random.default_rng(11)
    solver = {"backend": "clarabel"} if method == "ci" else {}  # the rules have none
    node = fo.ProcessingNode(["a", "b"], method=method, threshold=3.0, **solver)
    reports = _scene(rng, ["a", "b"], n_targets=5)
    _check_against_fuse(node, reports, node.step(reports), lambda g: {})


def test_min_sources_drops_small_groups_and_assignment_association():
    rng = np.random.default_rng(12)
    node = fo.ProcessingNode(list(P_DETECT), method="bci", association="assignment",
                             threshold=3.0, min_sources=3, dims=[0, 1])
    reports = _scene(rng, P_DETECT, n_targets=8)
    fused = node.step(reports)
    assert {len(g) for g in node.groups.values()} <= {3, 4} and len(fused) > 0
    _check_against_fuse(node, reports, fused, lambda g: {})


def test_mbci_uses_the_detection_of_the_sources_fused():
    # equal p and chi in a group of two: the BCI covariance inflated by 1/s (DESIGN §1)
    est = {s: fo.Estimates([[0.0, 0.0]], [np.diag([1.0, 2.0]) * (k + 1)], [7])
           for k, s in enumerate("abc")}
    node = fo.ProcessingNode(["a", "b", "c"], p_detect={"a": 0.6, "b": 0.6, "c": 0.1},
                             chi=0.5, threshold=1.0)
    fused = node.step({"a": est["a"], "b": est["b"]})
    s = 0.6 + 0.4 * 0.5 * (0.6 + 0.4 * 0.5)  # the product runs over a and b, not c
    bci = fo.bci(np.zeros((2, 2)), np.stack([est["a"].covs[0], est["b"].covs[0]]))
    np.testing.assert_allclose(fused.covs[0], bci.cov / s, rtol=1e-9)


def test_scalar_options_take_0d_arrays_as_numbers():
    """fuzz8: a processing node's p_detect, chi and threshold, and a time stamp, refused a
    0-d array that fo.mbci's p_detect and the trackers' scalar options take."""
    est = {s: fo.Estimates([[0.0, 0.0]], [np.diag([1.0, 2.0]) * (k + 1)], [7])
           for k, s in enumerate("ab")}
    plain = fo.ProcessingNode(["a", "b"], p_detect={"a": 0.6, "b": 0.9}, chi=0.5,
                              threshold=1.0)
    arrays = fo.ProcessingNode(["a", "b"], p_detect={"a": np.array(0.6), "b": np.array(0.9)},
                               chi=np.array(0.5), threshold=np.array(1))
    a, b = plain.step(est, time=2.5), arrays.step(est, time=np.array(2.5))
    np.testing.assert_array_equal(a.covs, b.covs)
    assert a.time == b.time == 2.5
    with pytest.raises(fo.FusionInputError, match="p_detect of source 'a' must be a number"):
        fo.ProcessingNode(["a"], p_detect={"a": np.array(True)}, chi=0.5, threshold=1.0)


def test_groups_of_one_size_are_fused_in_one_batch(monkeypatch):
    calls = []

    def counting(means, *args, **kwargs):
        calls.append(means.shape[:2])
        return fo.fuse_batch(means, *args, **kwargs)

    monkeypatch.setattr(processing, "fuse_batch", counting)
    rng = np.random.default_rng(13)
    node = fo.ProcessingNode(list(P_DETECT), threshold=3.0, p_detect=P_DETECT)
    node.step(_scene(rng, P_DETECT, n_targets=30))
    sizes = [len(g) for g in node.groups.values()]
    assert sorted(N for _, N in calls) == sorted({k for k in sizes if k > 1})
    assert all(B == sizes.count(N) for B, N in calls)


# --- fused ids over time ---

def _two_targets(t):
    """Two well-separated targets (2,) moving in parallel at step t."""
    return np.array([[0.1 * t, 0.0], [0.1 * t, 50.0]])


def _report(rng, truth, ids, noise=0.2):
    return fo.Estimates(truth + noise * rng.standard_normal(truth.shape),
                        np.broadcast_to(noise**2 * np.eye(2), (len(truth), 2, 2)), ids)


def _fused_ids_over(steps, node):
    """Per step, the fused ids; asserts exactly one fused track near each target."""
    out = []
    for t, reports in steps:
        fused = node.step(reports, time=float(t))
        truth = _two_targets(t)
        near = [int(fused.ids[np.argmin(np.linalg.norm(fused.means - x, axis=1))])
                for x in truth]
        assert len(fused) == 2 and len(set(near)) == 2
        out.append(near)
    return np.array(out)  # (T, 2): fused id of target 0 and target 1


def _steps(rng, T=50, miss=None, restart=None):
    """Three sources, two targets; source c's report is missing at steps in `miss`;
    source b's track of target 0 is renumbered from step `restart` on."""
    for t in range(T):
        truth = _two_targets(t)
        b_ids = [11 if restart is None or t < restart else 99, 12]
        reports = {"a": _report(rng, truth, [1, 2]),
                   "b": _report(rng, truth[::-1], b_ids[::-1]),  # another order, other ids
                   "c": _report(rng, truth, [5, 3])}
        if miss is not None and t in miss:
            del reports["c"]
        yield t, reports


@pytest.mark.parametrize("association", ["nearest", "assignment"])
@pytest.mark.parametrize("case", ["plain", "missing reports", "a missed target",
                                  "restarted track"])
def test_two_targets_three_sources_keep_two_fused_ids(case, association):
    rng = np.random.default_rng(14)
    node = fo.ProcessingNode(["a", "b", "c"], method="bci", threshold=5.0,
                             association=association)
    if case == "plain":
        steps = _steps(rng)
    elif case == "missing reports":
        steps = _steps(rng, miss=set(range(10, 50, 3)))
    elif case == "restarted track":
        steps = _steps(rng, restart=25)
    else:  # source a misses target 0 at some steps: its report holds target 1 only
        steps = ((t, r | {"a": r["a"].take([1])} if t % 4 == 1 else r)
                 for t, r in _steps(rng))
    ids = _fused_ids_over(steps, node)
    assert len(np.unique(ids)) == 2
    assert (ids == ids[0]).all()


def test_all_sources_of_a_target_restart_gives_a_new_id():
    rng = np.random.default_rng(15)
    node = fo.ProcessingNode(["a", "b"], method="bci", threshold=5.0)
    truth = _two_targets(0)[:1]
    first = node.step({"a": _report(rng, truth, [1]), "b": _report(rng, truth, [2])})
    again = node.step({"a": _report(rng, truth, [1]), "b": _report(rng, truth, [2])})
    new = node.step({"a": _report(rng, truth, [3]), "b": _report(rng, truth, [4])})
    assert first.ids.tolist() == again.ids.tolist() == [0]
    assert new.ids.tolist() == [1]  # nothing shared: a new id, 0 is never reused
    node.reset()
    assert node.step({"a": _report(rng, truth, [3])}).ids.tolist() == [0]


@pytest.mark.parametrize("memory, expected", [(1, [0, 2]), (2, [0, 2]), (3, [0, 0])])
def test_memory_keeps_an_id_through_steps_without_its_group(memory, expected):
    """Target 0 is reported by no source for 2 steps (a lost link, or too few sources for
    min_sources), its source tracks unchanged: with memory >= 3 it comes back with its
    fused id, with less it gets a new one. Target 1, always seen, keeps its id."""
    rng = np.random.default_rng(18)
    node = fo.ProcessingNode(["a", "b"], method="bci", threshold=5.0, memory=memory)
    truth = _two_targets(0)
    both = {"a": _report(rng, truth, [1, 2]), "b": _report(rng, truth, [7, 8])}
    one = {"a": _report(rng, truth[1:], [2]), "b": _report(rng, truth[1:], [8])}
    before = node.step(both)
    node.step(one)
    node.step(one)
    after = node.step(both)
    target_0 = [int(e.ids[np.argmin(np.linalg.norm(e.means - truth[0], axis=1))])
                for e in (before, after)]
    assert target_0 == expected


def test_memory_prefers_the_most_recent_track_holding_a_pair():
    """Source a's track 1 was in fused track 0, then (after a gap) in fused track 1 with
    a new partner; the next group holding a1 inherits 1, the more recent."""
    rng = np.random.default_rng(19)
    node = fo.ProcessingNode(["a", "b"], method="bci", threshold=5.0, memory=5)
    x = np.array([[0.0, 0.0]])
    node.step({"a": _report(rng, x, [1]), "b": _report(rng, x, [5])})  # fused 0: a1 b5
    node.step({"b": _report(rng, x + 20, [6])})                          # fused 1: b6
    node.step({"a": _report(rng, x + 20, [1]), "b": _report(rng, x + 20, [6])})
    assert node.groups[1].pairs == (("a", 1), ("b", 6))
    assert node.step({"a": _report(rng, x + 20, [1])}).ids.tolist() == [1]


def test_an_id_goes_to_the_group_sharing_most_then_to_the_nearest():
    rng = np.random.default_rng(16)
    node = fo.ProcessingNode(["a", "b", "c"], method="bci", threshold=5.0)
    x = np.array([[0.0, 0.0]])
    node.step({s: _report(rng, x, [1]) for s in "abc"})  # fused id 0 from a1, b1, c1
    # now a1 sits apart from b1 and c1: the group {b1, c1} shares two pairs, a1 one
    far = np.array([[20.0, 0.0]])
    fused = node.step({"a": _report(rng, far, [1]), "b": _report(rng, x, [1]),
                       "c": _report(rng, x, [1])})
    assert node.groups[0].pairs == (("b", 1), ("c", 1))
    assert node.groups[1].pairs == (("a", 1),) and fused.ids.tolist() == [0, 1]
    # a tie (one pair each): the nearer group, over dims, keeps the id
    node = fo.ProcessingNode(["a", "b"], method="bci", threshold=5.0, dims=[0])
    node.step({"a": _report(rng, x, [1]), "b": _report(rng, x, [1])})
    node.step({"a": _report(rng, np.array([[30.0, 0.0]]), [1]),
               "b": _report(rng, np.array([[-10.0, 99.0]]), [1])})
    assert node.groups[0].pairs == (("b", 1),)


def test_crossing_targets_switch_ids_at_most_at_the_crossing():
    """Two targets cross at step 25; with the assignment association the fused ids may
    swap only while the targets are within the threshold of each other."""
    rng = np.random.default_rng(17)
    threshold = 1.5
    node = fo.ProcessingNode(["a", "b", "c"], method="bci", association="assignment",
                             threshold=threshold)
    switches, near_steps = [], []
    previous = None
    for t in range(50):
        s = (t - 25) / 25
        truth = np.array([[10 * s, 5 * s], [10 * s, -5 * s]])
        reports = {k: _report(rng, truth, [10 * j + 1, 10 * j + 2])
                   for j, k in enumerate("abc")}
        fused = node.step(reports)
        nearest = [int(fused.ids[np.argmin(np.linalg.norm(fused.means - x, axis=1))])
                   for x in truth]
        if previous is not None and nearest != previous:
            switches.append(t)
        previous = nearest
        if np.linalg.norm(truth[0] - truth[1]) < 2 * threshold:
            near_steps.append(t)
    print(f"crossing: fused id switches at steps {switches}; targets within 2 x threshold "
          f"at steps {near_steps}")
    assert len(switches) <= 2
    assert all(min(near_steps) <= t <= max(near_steps) + 1 for t in switches)


# --- time ---

def test_time_is_the_given_one_or_the_reports_common_time():
    e = fo.Estimates([[0.0]], [[[1.0]]], time=2.0)
    node = fo.ProcessingNode(["a", "b"], method="bci", threshold=1.0, name="p")
    assert node.step({"a": e, "b": e}).time == 2.0
    assert node.step({"a": e, "b": fo.Estimates([[0.0]], [[[1.0]]])}).time == 2.0
    assert node.step({"a": e}, time=5).time == 5.0
    out = node.step({"a": e, "b": fo.Estimates([[0.0]], [[[1.0]]], time=3.0)}, time=6.0)
    assert out.time == 6.0 and out.node == "p"
    with pytest.raises(fo.FusionInputError, match="'p'.*different times.*time="):
        node.step({"a": e, "b": fo.Estimates([[0.0]], [[[1.0]]], time=3.0)})


def test_a_step_before_the_last_one_is_refused_and_changes_nothing():
    """Fuzz I10: reports stamped before the previous step were fused as if in order, and
    the fused track kept its id across; a node, a network's times and each tracker now
    refuse a step back in time, naming it, before their state changes."""
    e = lambda t: fo.Estimates([[0.0]], [[[1.0]]], time=t)  # noqa: E731
    node = fo.ProcessingNode(["a", "b"], method="bci", threshold=1.0, name="p")
    node.step({"a": e(10.0), "b": e(10.0)})
    with pytest.raises(fo.FusionInputError, match=r"'p'.*time = 1.0 is before the previous "
                                                  r"step's, 10.0: steps go forward in time"):
        node.step({"a": e(1.0), "b": e(1.0)})
    assert node.step({"a": e(10.0), "b": e(10.0)}).ids.tolist() == [0]  # equal time: fine
    node.reset()
    assert node.step({"a": e(1.0), "b": e(1.0)}).time == 1.0
    tracker = _Reporter()
    net = fo.Network({"a": tracker}, {"f": fo.ProcessingNode(["a"], threshold=1.0,
                                                            method="bci")})
    with pytest.raises(fo.FusionInputError, match=r"times\[2\] = 1.0 is before the previous "
                                                  r"step's, 2.0"):
        net.run([{"a": None}] * 3, times=[1.0, 2.0, 1.0])
    assert tracker.steps == 0  # refused before any node stepped


class _Reporter:
    """A tracker that reports one estimate at 0 at every step."""

    steps = 0

    def step(self, scan, time=None):
        self.steps += 1
        return fo.Estimates([[0.0]], [[[1.0]]], time=time)


def test_no_reports_gives_no_estimates_once_n_is_known():
    node = fo.ProcessingNode(["a"], method="bci", threshold=1.0, name="p")
    with pytest.raises(fo.FusionInputError, match="'p'.*dimension is unknown"):
        node.step({})
    node.step({"a": fo.Estimates.empty(3)})
    assert len(node.step({})) == 0 and node.step({}).n == 3


# --- bad input, each named ---

GOOD = dict(threshold=1.0, p_detect={"a": 0.9, "b": 0.8})


@pytest.mark.parametrize("sources, kwargs, match", [
    ("ab", {}, "sources must be a sequence"),
    ([], {}, "sources is empty"),
    (["a", "a"], {}, "more than once: 'a'"),
    (["a", ["b"]], {}, "hashable"),
    (["a", np.timedelta64(5)], {}, "sources must be hashable"),  # hash(): ValueError (fuzz4)
    (["a", "b"], dict(name=np.timedelta64(5)), "name must be hashable"),
    (["a", "b"], dict(method="magic"), "method must be one of"),
    (["a", "b"], dict(method="known-cross"), "cross-covariances"),
    (["a", "b", "c"], dict(method="ci", p_detect=None), "'ci' fuses pairs.*3 sources"),
    # fuzz I12: accepted, then refused at the first group of three
    (["a", "b", "c"], dict(method="bci", backend="closed-form"),
     "backend 'closed-form' fuses pairs, but 3 sources can form larger groups"),
    (["a", "b"], dict(criterion="max"), "criterion"),
    (["a", "b"], dict(backend="magic"), "backend"),
    (["a", "b"], dict(association="magic"), "association method"),
    (["a", "b"], dict(threshold="1"), "threshold"),
    (["a", "b"], dict(threshold=-1.0), "threshold"),
    (["a", "b"], dict(dims=[1.5]), "dims"),
    (["a", "b"], dict(p_detect=None), "needs p_detect"),
    (["a", "b"], dict(p_detect={"a": 0.9}), r"missing \['b'\]"),
    (["a", "b"], dict(p_detect={"a": 0.9, "b": 0.8, "z": 1.0}), r"unknown \['z'\]"),
    (["a", "b"], dict(p_detect={"a": 0.9, "b": 1.5}), "p_detect of source 'b'"),
    (["a", "b"], dict(p_detect={"a": 0.9, "b": "x"}), "p_detect of source 'b'"),
    (["a", "b"], dict(chi=0.9, growth=1.1), "not both"),
    (["a", "b"], dict(chi=0.0), "chi"),
    (["a", "b"], dict(growth=0.5), "growth"),
    (["a", "b"], dict(method="bci", p_detect={"a": 1, "b": 1}), "p_detect applies to .*mbci"),
    (["a", "b"], dict(method="bci", p_detect=None, chi=0.5), "chi applies to method .mbci. only"),
    (["a", "b"], dict(method="bci", p_detect=None, growth=1.5), "growth applies to .*mbci"),
    (["a", "b"], dict(memory=0), "memory must be an integer >= 1"),
    (["a", "b"], dict(memory=2.5), "memory must be an integer >= 1"),
    (["a", "b"], dict(method=np.array(["bci", "mbci"])), "method must be one of"),
    (["a", "b"], dict(backend=["newton"]), "backend must be one of"),
    (["a", "b"], dict(method="naive", p_detect=None, backend="newton"),
     "method 'naive' has no weight solver: leave backend unset"),
    (["a", "b"], dict(method="fast-ci", p_detect=None, backend="clarabel"), "no weight solver"),
    (["a", "b"], dict(method="bci", p_detect=None, chi=0.5, growth=2.0),
     "chi and growth apply to method .mbci. only, not .bci."),
    (["a", "b"], dict(min_sources=3), r"min_sources must be an integer in \[1, 2\]"),
    (["a", "b"], dict(min_sources=1.0), "min_sources"),
    (["a", "b"], dict(name=["x"]), "name"),
    ({"a", "b"}, {}, "sources must be a sequence .*a set has no order"),  # fuzz U11
    (frozenset("ab"), {}, "a set has no order"),
])
def test_bad_construction_is_named(sources, kwargs, match):
    with pytest.raises(fo.FusionInputError, match=match):
        fo.ProcessingNode(sources, **(GOOD | kwargs))


def test_bad_reports_are_named():
    node = fo.ProcessingNode(["a", "b"], name="p", dims=[2], **GOOD)
    e3 = fo.Estimates(np.zeros((1, 3)), np.eye(3)[None])
    with pytest.raises(fo.FusionInputError, match=r"'p'.*unknown sources \['z'\]"):
        node.step({"a": e3, "z": e3})
    with pytest.raises(fo.FusionInputError, match="'p'.*mapping"):
        node.step([e3])
    with pytest.raises(fo.FusionInputError, match="'p'.*source 'b' must be an Estimates"):
        node.step({"a": e3, "b": np.zeros((1, 3))})
    with pytest.raises(fo.FusionInputError, match=r"'p'.*n = 3 expected.*\['b'\]"):
        node.step({"a": e3, "b": fo.Estimates(np.zeros((1, 4)), np.eye(4)[None])})
    node.step({"a": e3})
    with pytest.raises(fo.FusionInputError, match=r"'p'.*n = 3 expected.*\['a'\]"):
        node.step({"a": fo.Estimates(np.zeros((1, 4)), np.eye(4)[None])})
    low = fo.ProcessingNode(["a", "b"], dims=[2], **GOOD)
    with pytest.raises(fo.FusionInputError, match=r"dims \[2\] out of range .* n = 2"):
        low.step({"a": fo.Estimates(np.zeros((1, 2)), np.eye(2)[None])})


def test_a_step_refused_for_its_time_changes_nothing():
    """Regression: time was checked only when the fused Estimates were built, after the
    ids were handed out, so the refused step used up fused id 1."""
    def est(x, i):
        return fo.Estimates(np.array([[x, 0.0]]), np.eye(2)[None], [i])

    node = fo.ProcessingNode(["a", "b"], method="bci", threshold=1.0)
    assert node.step({"a": est(0.0, 1), "b": est(0.0, 1)}).ids.tolist() == [0]
    with pytest.raises(fo.FusionInputError, match="time must be a finite real number"):
        node.step({"a": est(100.0, 20), "b": est(100.0, 20)}, time=float("nan"))
    assert node.step({"a": est(300.0, 50), "b": est(300.0, 50)}).ids.tolist() == [1]


def test_a_failed_group_of_many_sources_is_named_in_a_line_of_reasonable_length():
    """Fuzz I13: a group of 2,000 sources that failed to fuse listed every member, 78,000
    characters before the reason; now its first three and last two, and the count between."""
    sources = [f"s{i}" for i in range(2000)]
    e = fo.Estimates(np.zeros((1, 2)), np.eye(2)[None])
    node = fo.ProcessingNode(sources, method="bci", threshold=1.0)
    with pytest.MonkeyPatch.context() as m:
        m.setattr(processing, "fuse_batch", _refuse)
        m.setattr(processing, "fuse", _refuse)
        with pytest.raises(fo.FusionInputError) as err:
            node.step(dict.fromkeys(sources, e))
    message = str(err.value)
    assert len(message) < 400
    assert "source 's2' track 0 (node 2) with 1995 more with source 's1998'" in message
    assert message.endswith("refused for the test")


def _refuse(*args, **kwargs):
    raise fo.FusionInputError("refused for the test")


def test_a_step_of_many_groups_is_fused_in_chunks_within_the_memory_limit(monkeypatch):
    """Fuzz K4: all groups of one size went into one fuse_batch, whose arrays (1,500 groups
    of 8 estimates of n = 60: 1.3 GB) were refused as a solver's memory_limit though each
    group is small. Now in chunks of half the limit; the fused tracks are those of one
    batch, to the bit."""
    from fusion_opt.limits import batch_bytes

    rng = np.random.default_rng(3)
    n, m, K = 3, 40, 3
    truth = rng.uniform(0, 1e3, size=(m, n))
    reports = {k: fo.Estimates(truth + 1e-3 * rng.normal(size=truth.shape),
                               np.tile(np.diag([1.0, 2.0, 3.0]) * (k + 1), (m, 1, 1)), None, 0.0)
               for k in range(K)}
    whole = fo.ProcessingNode(list(range(K)), method="bci", threshold=1.0).step(reports)
    monkeypatch.setattr(fo.limits, "working_memory", 7.5 * batch_bytes(1, K, n))  # 3 a chunk
    chunked = fo.ProcessingNode(list(range(K)), method="bci", threshold=1.0).step(reports)
    assert len(whole) == m
    np.testing.assert_array_equal(chunked.means, whole.means)
    np.testing.assert_array_equal(chunked.covs, whole.covs)


def test_a_refused_first_step_does_not_fix_the_state_dimension():
    """Fuzz K9: a first step refused at the fusion (nodes 1e600 apart) left the node's n set
    to that step's, and a next step of another dimension was refused against an n no step
    had succeeded with."""
    node = fo.ProcessingNode(["a", "b"], method="bci", threshold=1.0)
    E = fo.Estimates
    with pytest.raises(fo.FusionInputError, match="beyond float64"):
        node.step({"a": E(np.zeros((1, 2)), 1e-300 * np.eye(2)[None]),
                   "b": E(np.zeros((1, 2)), 1e300 * np.eye(2)[None])})
    assert node.step({"a": E(np.zeros((1, 3)), np.eye(3)[None])}).n == 3
    with pytest.raises(fo.FusionInputError, match="n = 3 expected"):
        node.step({"a": E(np.zeros((1, 2)), np.eye(2)[None])})


def test_a_pair_counts_for_every_recent_fused_track_that_holds_it():
    """Fuzz K8: a (source, track id) pair counted only for the most recent fused track
    holding it, so target X, whose source track a1 joined target Y's group for one step,
    got a new id at the next step although its own fused track 0 (reported two steps
    before, memory 3) holds a1 and is free: the docstring's rule gives it 0 back."""
    def est(ms):
        ms = np.atleast_2d(np.array(ms, float))
        return fo.Estimates(ms, np.tile(np.eye(2), (len(ms), 1, 1)), [1])

    node = fo.ProcessingNode(["a", "b", "c"], method="bci", threshold=1.0, memory=3)
    y = {"b": est([10, 0]), "c": est([10.2, 0])}
    assert node.step({"a": est([0, 0]), **y}).ids.tolist() == [0, 1]
    assert node.step({"a": est([10.1, 0]), **y}).ids.tolist() == [1]  # a1 joins Y's group
    out = node.step({"a": est([0, 0]), **y})
    assert out.ids.tolist() == [0, 1]
    assert node.groups[0].pairs == (("a", 1),)


def test_no_memory_limit_fuses_every_group_in_one_batch(monkeypatch):
    """Fuzz L5: limits.working_memory = inf ("no limit", as its message says) made the
    chunk size inf // x = NaN and every step raised ValueError."""
    monkeypatch.setattr(fo.limits, "working_memory", float("inf"))
    rng = np.random.default_rng(2)
    reports = {k: fo.Estimates(rng.normal(size=(5, 2)) * 1e-3 + np.arange(5)[:, None] * 10,
                               np.tile(np.eye(2), (5, 1, 1)), None, 0.0) for k in "ab"}
    assert len(fo.ProcessingNode(["a", "b"], method="bci", threshold=1.0).step(reports)) == 5


@pytest.mark.parametrize("scale", [1.0, 1e200, 1e-170])
def test_the_nearer_fused_track_keeps_its_id_at_any_scale(scale):
    """A group that shares one source track with each of two fused tracks (equal counts and
    ages) takes the id of the nearer one. Its distances were np.linalg.norm's: at 1e200
    both squares overflowed, the tie went to the lower id (fuzz N1's kind); at 1e-170 both
    were 0."""
    node = fo.ProcessingNode(["a", "b"], method="bci", threshold=2.0 * scale)
    one = np.ones((1, 1, 1))

    def report(x, t):
        return fo.Estimates(np.array([[x * scale]]), one, [0], t)

    first = node.step({"a": report(0.0, 1.0), "b": report(10.0, 1.0)}, 1.0)
    assert first.ids.tolist() == [0, 1] and first.means[1, 0] == 10.0 * scale
    second = node.step({"a": report(9.0, 2.0), "b": report(9.1, 2.0)}, 2.0)
    assert second.ids.tolist() == [1]  # nearer to fused track 1 (at 10) than 0 (at 0)
