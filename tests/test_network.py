"""Network: equals the same pipeline written by hand, hierarchies, missing scans, cycles
and bad input refused by name, consistency of fusing fused estimates again, and the
README's example."""

import re
from pathlib import Path

import numpy as np
import pytest

import fusion_opt as fo

N_STATE = 2


class RandomWalkTracker:
    """A toy tracker of static targets with known identities: scan {target id: position
    measurement (2,)}; each track is a Kalman filter of a random walk (process noise q,
    measurement noise r); every track is predicted each step and updated when measured."""

    def __init__(self, q=0.01, r=0.04, dt=0.1):
        self.q, self.r, self.dt = q, r, dt
        self.tracks: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.t = 0
        self.steps = 0

    def step(self, scan) -> fo.Estimates:
        self.steps += 1
        self.t += 1
        I = np.eye(N_STATE)
        for i, (m, P) in list(self.tracks.items()):
            self.tracks[i] = (m, P + self.q * I)
        for i, y in scan.items():
            m, P = self.tracks.get(i, (np.zeros(N_STATE), 100.0 * I))
            K = P @ np.linalg.inv(P + self.r * I)
            self.tracks[i] = (m + K @ (y - m), (I - K) @ P)
        ids = sorted(self.tracks)
        return fo.Estimates(np.array([self.tracks[i][0] for i in ids]).reshape(-1, N_STATE),
                            np.array([self.tracks[i][1] for i in ids]).reshape(-1, 2, 2),
                            ids, time=self.t * self.dt)


class EchoTracker:
    """Reports its scan, an Estimates, as it is."""

    def step(self, scan):
        return scan


TARGETS = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]])


def _scans(rng, names, T, p_detect=0.8):
    """T steps of {tracker: {target id: measurement}}; target ids differ per tracker."""
    series = []
    for _ in range(T):
        scans = {}
        for k, name in enumerate(names):
            seen = np.flatnonzero(rng.random(len(TARGETS)) < p_detect)
            scans[name] = {10 * k + int(j): TARGETS[j] + 0.2 * rng.standard_normal(2)
                           for j in seen}
        series.append(scans)
    return series


def _node(sources, **kw):
    p = {s: 0.9 - 0.1 * i for i, s in enumerate(sources)}
    return fo.ProcessingNode(sources, threshold=3.0, p_detect=p, growth=1.1, **kw)


def _assert_same(a: fo.Estimates, b: fo.Estimates, name=None):
    """a from a network equals b by hand; a node without a name is stamped with `name`,
    its name in the network."""
    np.testing.assert_array_equal(a.means, b.means)
    np.testing.assert_array_equal(a.covs, b.covs)
    np.testing.assert_array_equal(a.ids, b.ids)
    assert (a.time, a.node) == (b.time, b.node if b.node is not None else name)


def test_network_equals_the_pipeline_by_hand():
    names = ["a", "b", "c"]
    series = _scans(np.random.default_rng(20), names, T=20)
    net = fo.Network({s: RandomWalkTracker() for s in names},
                     {"f": _node(names, name="f")})
    out = net.run(series)
    trackers = {s: RandomWalkTracker() for s in names}
    node = _node(names, name="f")
    assert all(len(v) == 20 for v in out.values())
    for t, scans in enumerate(series):
        reports = {s: trackers[s].step(scans[s]) for s in names}
        fused = node.step(reports)
        for s in names:
            _assert_same(out[s][t], reports[s])
        _assert_same(out["f"][t], fused)
    assert len(np.unique(np.concatenate([e.ids for e in out["f"]]))) >= 3


def test_two_level_hierarchy_in_any_order():
    names = ["a", "b", "c", "d", "e"]
    series = _scans(np.random.default_rng(21), names, T=10)
    processing = {"top": _node(["p1", "p2", "e"]), "p2": _node(["c", "d"]),
                  "p1": _node(["a", "b"])}  # the top first: the network orders them
    net = fo.Network({s: RandomWalkTracker() for s in names}, processing)
    assert net.order.index("top") == 2
    trackers = {s: RandomWalkTracker() for s in names}
    p1, p2, top = _node(["a", "b"]), _node(["c", "d"]), _node(["p1", "p2", "e"])
    for scans in series:
        out = net.step(scans, time=1.5)
        r = {s: trackers[s].step(scans[s]) for s in names}
        f1 = p1.step({"a": r["a"], "b": r["b"]}, time=1.5)
        f2 = p2.step({"c": r["c"], "d": r["d"]}, time=1.5)
        _assert_same(out["top"], top.step({"p1": f1, "p2": f2, "e": r["e"]}, time=1.5), "top")
        assert out["top"].time == 1.5


def test_a_missing_scan_means_the_tracker_does_not_report():
    rng = np.random.default_rng(22)
    trackers = {s: RandomWalkTracker() for s in "abc"}
    net = fo.Network(trackers, {"f": _node(list("abc"))})
    series = _scans(rng, "abc", T=6, p_detect=1.0)
    out = [net.step(scans) for scans in series[:2]]
    ids = out[-1]["f"].ids.tolist()
    out.append(net.step({"a": series[2]["a"], "b": series[2]["b"]}))  # no scan for c
    assert trackers["c"].steps == 2 and "c" not in out[-1]
    assert all("c" not in g.sources for g in net.processing["f"].groups.values())
    assert out[-1]["f"].ids.tolist() == ids  # the fused ids carry on without c
    out.append(net.step({}))  # nothing at all: neither trackers nor f report
    assert out[-1] == {}
    out.append(net.step({"a": {}}))  # an empty scan is not missing: a predicts and reports
    assert set(out[-1]) == {"a", "f"} and len(out[-1]["a"]) == 3
    assert out[-1]["f"].ids.tolist() == ids  # a's tracks continue: same fused ids


def test_run_stamps_times_and_lists_each_node_in_step_order():
    names = ["a", "b"]
    series = _scans(np.random.default_rng(23), names, T=4)
    series[2] = {"a": series[2]["a"]}
    net = fo.Network({s: RandomWalkTracker() for s in names}, {"f": _node(names)})
    out = net.run(series, times=[0.0, 0.1, 0.2, 0.3])
    assert [e.time for e in out["f"]] == [0.0, 0.1, 0.2, 0.3]
    assert len(out["a"]) == 4 and len(out["b"]) == 3  # b reported at 3 of the 4 steps
    with pytest.raises(fo.FusionInputError, match="times must have one entry per step"):
        net.run(series, times=[0.0])


def test_fusing_fused_estimates_again_ci_stays_consistent_naive_does_not():
    """Level 1 fuses a and b; level 2 fuses that with a again (common information). Over
    3000 targets the mean NEES of level 2 stays <= n with BCI and exceeds it with naive
    fusion (expected tr((4Ya + Yb)(2Ya + Yb)^-1) = 3.22 for n = 2)."""
    rng = np.random.default_rng(24)
    M = 3000
    truth = np.stack([100.0 * np.arange(M), np.zeros(M)], axis=1)
    Pa, Pb = np.diag([1.0, 4.0]), np.diag([4.0, 1.0])

    def scan(P):
        err = rng.multivariate_normal(np.zeros(2), P, size=M)
        return fo.Estimates(truth + err, np.broadcast_to(P, (M, 2, 2)))

    nees = {}
    for method in ("bci", "naive"):
        net = fo.Network({"a": EchoTracker(), "b": EchoTracker()},
                         {"f1": fo.ProcessingNode(["a", "b"], method=method, threshold=20.0),
                          "f2": fo.ProcessingNode(["f1", "a"], method=method, threshold=20.0)})
        out = net.step({"a": scan(Pa), "b": scan(Pb)})["f2"]
        assert len(out) == M and all(len(g) == 2 for g in net.processing["f2"].groups.values())
        e = out.means - truth[np.rint(out.means[:, 0] / 100.0).astype(int)]
        nees[method] = float(np.mean(np.einsum("ij,ijk,ik->i", e, np.linalg.inv(out.covs), e)))
    assert nees["bci"] <= 2.0 + 0.15
    assert nees["naive"] > 2.8


# --- refused at construction or at a step, naming the node ---

def test_cycles_are_refused_naming_the_nodes():
    with pytest.raises(fo.FusionInputError, match="cycle.*'p' -> 'q' -> 'p'"):
        fo.Network({"a": EchoTracker()},
                   {"p": fo.ProcessingNode(["a", "q"], method="bci", threshold=1.0),
                    "q": fo.ProcessingNode(["p"], method="bci", threshold=1.0)})
    with pytest.raises(fo.FusionInputError, match="cycle.*'p' -> 'p'"):
        fo.Network({"a": EchoTracker()},
                   {"p": fo.ProcessingNode(["a", "p"], method="bci", threshold=1.0)})


def test_bad_networks_are_refused_by_name():
    node = fo.ProcessingNode(["a"], method="bci", threshold=1.0)
    with pytest.raises(fo.FusionInputError, match="trackers must be a mapping"):
        fo.Network([EchoTracker()], {})
    with pytest.raises(fo.FusionInputError, match="tracker 'a' has no step"):
        fo.Network({"a": object()}, {})
    with pytest.raises(fo.FusionInputError, match="processing must be a mapping"):
        fo.Network({"a": EchoTracker()}, [node])
    with pytest.raises(fo.FusionInputError, match=r"names \['a'\] are both"):
        fo.Network({"a": EchoTracker()}, {"a": node})
    with pytest.raises(fo.FusionInputError, match="processing node 'f' must be a Process"):
        fo.Network({"a": EchoTracker()}, {"f": EchoTracker()})
    with pytest.raises(fo.FusionInputError, match=r"'f' has sources \['z'\]"):
        fo.Network({"a": EchoTracker()},
                   {"f": fo.ProcessingNode(["a", "z"], method="bci", threshold=1.0)})
    with pytest.raises(fo.FusionInputError, match=r"several names: \['f', 'g'\]"):
        fo.Network({"a": EchoTracker()}, {"f": node, "g": node})
    echo = EchoTracker()
    with pytest.raises(fo.FusionInputError, match=r"several names: \['a', 'b'\]"):
        fo.Network({"a": echo, "b": echo}, {})


def test_bad_steps_are_refused_by_name():
    net = fo.Network({"a": EchoTracker()},
                     {"f": fo.ProcessingNode(["a"], method="bci", threshold=1.0)})
    with pytest.raises(fo.FusionInputError, match=r"unknown trackers \['z'\]"):
        net.step({"z": fo.Estimates.empty(2)})
    with pytest.raises(fo.FusionInputError, match="scans must be a mapping"):
        net.step([fo.Estimates.empty(2)])
    with pytest.raises(fo.FusionInputError, match="tracker 'a' returned ndarray"):
        net.step({"a": np.zeros((1, 2))})
    net.step({"a": fo.Estimates.empty(2)})
    with pytest.raises(fo.FusionInputError, match=r"processing node 'f'.*n = 2 expected"):
        net.step({"a": fo.Estimates.empty(3)})


# --- the README's example runs as written ---

def test_readme_network_examples_run():
    """Both: recorded tracks replayed (target 1 fused, target 2 passed on), and the
    package's trackers on simulated scans (one fused track, within 0.3 of the truth)."""
    readme = (Path(__file__).parents[1] / "README.md").read_text()
    section = readme.split("## Fusing your own sensor network", 1)[1].split("\n## ", 1)[0]
    replay, own = re.findall(r"```python\n(.*?)```", section, re.S)
    namespace = {}
    exec(compile(replay, "README.md", "exec"), namespace)
    assert namespace["fused"].ids.tolist() == [0, 1]
    namespace = {}
    exec(compile(own, "README.md", "exec"), namespace)
    fused, x = namespace["fused"], namespace["x"]
    assert len(fused) == 1 and np.linalg.norm(fused.means[0, :2] - x[:2]) < 0.3


def test_a_failing_step_names_its_tracker_and_what_had_stepped():
    """Regression: a tracker's refusal did not say which tracker, a bad time was found
    only after every tracker had stepped, and run(times=5) or run(None) raised TypeError."""
    from trackers import kalman, models
    eye = np.eye(2)

    def kf():
        return kalman.KalmanFilter(models.LinearGaussian(eye, eye, eye, eye), np.zeros(2), eye)

    net = fo.Network({"a": kf(), "b": kf()},
                     {"f": fo.ProcessingNode(["a", "b"], threshold=10.0, method="bci")})
    with pytest.raises(fo.FusionInputError,
                       match=r"tracker 'b': scan contains non-finite.*nodes \['a'\] had stepped"):
        net.step({"a": [[0.0, 0.0]], "b": [[np.nan, 0.0]]})
    assert net.trackers["a"].steps == 1 and net.trackers["b"].steps == 0
    for time in ("x", np.nan):
        with pytest.raises(fo.FusionInputError, match="time must be a finite real number"):
            net.step({"a": [[0.0, 0.0]]}, time)
    assert net.trackers["a"].steps == 1  # refused before any node stepped
    with pytest.raises(fo.FusionInputError, match="times must be a sequence"):
        net.run([{"a": []}], times=5)
    with pytest.raises(fo.FusionInputError, match="scan_series must be a sequence"):
        net.run(None)
    # a 0-d array has __iter__ but raises TypeError when iterated, and a set's order (which
    # numbers the steps) changes with the hash seed (fuzz of 2026-11-29)
    for times in (np.array(0.0), {1.0, 2.0}):
        with pytest.raises(fo.FusionInputError, match="times must be a sequence"):
            net.run([{"a": []}, {"a": []}], times=times)
    with pytest.raises(fo.FusionInputError, match="scan_series must be a sequence"):
        net.run(np.array(1.0))
    assert len(net.run([{"a": []}], times=(t for t in [1.0]))["f"]) == 1


def test_a_fusion_that_fails_names_the_node_the_group_and_what_had_stepped():
    """Fuzz E9 and E10: a FusionSolverError inside a processing node escaped the network
    with neither the node nor the nodes that had stepped, and a refusal of the node's
    fuse_batch named "problem 0", a position in a batch the caller never sees."""
    eye = np.eye(2)
    means = np.array([[0.0, 0.0], [50.0, 0.0]])  # two groups, the second's scales apart
    scan = {"a": fo.Estimates(means, np.stack([eye, 1e-300 * eye]), [4, 5]),
            "b": fo.Estimates(means, np.stack([eye, 1e300 * eye]), [7, 8])}
    node = fo.ProcessingNode(["a", "b"], threshold=5.0, method="bci", name="P")
    with pytest.raises(fo.FusionInputError, match=r"^ProcessingNode 'P': fusing source 'a' "
                                                  r"track 5 \(node 0\) with source 'b' track "
                                                  r"8 \(node 1\): covs span a ratio"):
        node.step(scan)
    n = 200
    big = fo.Estimates(np.zeros((1, n)), np.eye(n)[None])
    net = fo.Network({"a": EchoTracker(), "b": EchoTracker()},
                     {"f": fo.ProcessingNode(["a", "b"], threshold=1.0, method="bci",
                                              backend="clarabel")})
    with pytest.raises(fo.FusionSolverError) as err:
        net.step({"a": big, "b": big})
    assert err.value.status == "memory_limit" and err.value.backend == "clarabel"
    assert re.search(r"processing node 'f': ProcessingNode: fusing source 'a' track 0 "
                     r"\(node 0\) with source 'b' track 0 \(node 1\): n = 200.*"
                     r"nodes \['a', 'b'\] had stepped\)$", str(err.value))


def test_a_lost_link_keeps_a_clocked_tracker_in_time_where_a_missing_scan_does_not():
    """Fuzz K14: a scan left out puts RBMCDA, which stamps its clock (k + 1) dt, one step
    behind for good, and its node refuses every later step; `lost` steps the tracker on its
    scan and drops the report, so the network goes on."""
    from trackers.models import turn_model
    from trackers.rbmcda import RBMCDA

    def network():
        def make(seed):
            return RBMCDA(turn_model(0.0, 0.1, 1.0, 1.0), np.zeros(4),
                          np.diag([100.0, 100, 10, 10]), rng=np.random.default_rng(seed),
                          dt=1.0, birth_prob=0.5, clutter_density=1e-6)
        return fo.Network({"a": make(0), "b": make(1)},
                          {"f": fo.ProcessingNode(["a", "b"], method="bci", threshold=5.0)})

    def scans(k):
        return {"a": [[k * 1.0, 0.0]], "b": [[k * 1.0 + 0.1, 0.0]]}

    left_out, lost = network(), network()
    for k in range(5):
        out = lost.step(scans(k), lost=["b"] if k == 2 else ())
        assert out["f"].time == k + 1.0
        assert ("b" in out) == (k != 2)
        if k == 2:
            left_out.step({"a": scans(k)["a"]})
        elif k < 3:
            left_out.step(scans(k))
    with pytest.raises(fo.FusionInputError, match=r"reports carry different times"):
        left_out.step(scans(3))
    for bad in (["c"], "b", [["b"]], np.array("b")):  # a 0-d array: fuzz of 2026-11-29
        with pytest.raises(fo.FusionInputError, match="lost"):
            lost.step({"a": []}, lost=bad)
    assert "b" not in lost.step(scans(5), lost={"b"})  # a set names them as well as a list


def test_a_chain_of_1200_processing_nodes_is_ordered_and_steps():
    """Fuzz K15: the topological order was a recursive search, and a chain deeper than
    Python's recursion limit (about 1,000 nodes) raised RecursionError; cycles are still
    refused by name (test above)."""
    class Replay:
        def step(self, scan):
            return fo.Estimates(*scan)

    proc = {"n0": fo.ProcessingNode(["t"], method="bci", threshold=1.0)}
    for i in range(1, 1200):
        proc[f"n{i}"] = fo.ProcessingNode([f"n{i - 1}"], method="bci", threshold=1.0)
    net = fo.Network({"t": Replay()}, dict(reversed(list(proc.items()))))
    assert net.order == [f"n{i}" for i in range(1200)]
    out = net.step({"t": (np.ones((1, 2)), np.eye(2)[None])})
    np.testing.assert_array_equal(out["n1199"].means, [[1.0, 1.0]])


def test_a_failed_step_names_the_lost_trackers_that_stepped():
    """Fuzz L4: a failed step listed the nodes that had stepped from its reports only, so
    a lost tracker, which steps too, was left out and a caller retrying would step it
    twice."""
    net = fo.Network({"a": EchoTracker(), "b": EchoTracker()},  # dims beyond n = 2:
                     {"p": fo.ProcessingNode(["a", "b"], method="bci", threshold=1.0,
                                             dims=[3])})  # the node refuses its step
    e = fo.Estimates(np.zeros((1, 2)), np.eye(2)[None])
    with pytest.raises(fo.FusionInputError, match=r"\(nodes \['a', 'b'\] had stepped\)$"):
        net.step({"a": e, "b": e}, lost=["a"])


def test_a_trackers_own_error_keeps_its_type_and_says_where_it_came_from():
    """Fuzz U10: a user tracker's own exception came through the network with no word of
    which tracker raised it or which nodes had stepped; it keeps its type (the network
    does not know what it means) and gains notes saying both. A class given as a tracker
    is refused at construction: its step would take the scan as its instance."""
    class Broken:
        def step(self, scan):
            raise ZeroDivisionError("the user's own bug")

    from trackers import kalman, models
    eye = np.eye(2)
    kf = kalman.KalmanFilter(models.LinearGaussian(eye, eye, eye, eye), np.zeros(2), eye)
    net = fo.Network({"a": kf, "b": Broken()},
                     {"f": fo.ProcessingNode(["a", "b"], threshold=10.0, method="bci")})
    with pytest.raises(ZeroDivisionError, match="the user's own bug") as info:
        net.step({"a": [[0.0, 0.0]], "b": []})
    assert info.value.__notes__ == [
        "raised by the step of tracker 'b' of a fusion_opt Network",
        "nodes ['a'] of the Network had stepped"]
    with pytest.raises(fo.FusionInputError, match="tracker 'b' is the class Broken, not a "
                                                  "tracker: give an instance"):
        fo.Network({"b": Broken}, {})
