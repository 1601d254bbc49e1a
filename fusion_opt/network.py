"""A network of monitoring nodes (trackers) and processing nodes, stepped together.

    net = Network(trackers={"a": ta, "b": tb, "c": tc},
                  processing={"f": ProcessingNode(["a", "b", "c"], threshold=1.0, ...)})
    out = net.step({"a": scan_a, "b": scan_b, "c": scan_c})   # {name: Estimates}
    series = net.run([scans_0, scans_1, ...])                  # {name: [Estimates, ...]}

The tracker protocol: a tracker is any object with `.step(scan) -> Estimates`, where the
scan is whatever that tracker reads (measurements (k, d), a list of detections, ...) and
the Estimates are its tracks after the scan: means (m, n), covs (m, n, n), ids that
persist while a track continues, and the tracker's own time. `KalmanFilter`, RBPF,
RBMCDA, a Stone Soup adapter and a user's own filter all qualify; the network never looks
inside a scan.

A processing node's sources are names of trackers or of other processing nodes, so nodes
may form a hierarchy; the sources of a node are stepped before it (a topological order,
fixed at construction) and a cycle is refused. Each step:

- a tracker steps only if `scans` holds its scan. A missing scan means nothing arrived
  from that node (a silent node or a lost link): the tracker does not step and reports
  nothing. A scan with no detection is not missing: pass the empty scan, the tracker
  steps (predicts) and reports its tracks. The package's trackers predict one model dt
  per step, so one left out is a step behind from then on: RBMCDA stamps its clock, one
  dt behind the others', and a node fusing it refuses the reports' different times at
  every later step; KalmanFilter and RBPF stamp no time and their estimates are fused
  one dt old until measurements pull them back (fuzz K14). To model a lost link with
  them, step the tracker on its scan (or the empty scan) and leave its report out:
  `lost` names such trackers;
- a processing node steps with the reports of those of its sources that reported; if
  none did, it does not step and reports nothing either (its fused ids carry over to its
  next step);
- time: trackers stamp their own estimates; `time`, when given, is passed to every
  processing node, which stamps its fused estimates with it; without it each processing
  node takes the common time of its reports; `run`'s times, a tracker's and a node's must
  not go back (data out of order is not supported). A processing node built without a
  name has its fused Estimates stamped with its name in the network.

`step` returns the Estimates of every node that reported; `run` returns each node's
Estimates in step order (one per step at which it reported: one per step when every
tracker has a scan at every step).

A step that fails raises FusionInputError (or a processing node's FusionSolverError)
naming the node, the group of tracks whose fusion failed, and the nodes that had
stepped before it (the network cannot take a tracker's step back; the trackers of this
package keep their state when they refuse a scan, so the failing one has not stepped).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Hashable, Iterable, Mapping, Sequence, Set
from typing import Any, Protocol

from .estimates import Estimates, check_forward, check_time
from .processing import ProcessingNode
from .results import FusionInputError, FusionSolverError, in_context
from .validation import hashable, is_sequence, safe_repr


class Tracker(Protocol):
    """Anything with `.step(scan) -> Estimates`."""

    def step(self, scan: Any) -> Estimates: ...


class Network:
    """Trackers {name: tracker} and processing nodes {name: ProcessingNode} whose sources
    are names of either (module docstring). `order` lists the processing nodes in the
    order they step, each after its sources."""

    def __init__(self, trackers: Mapping[Hashable, Tracker],
                 processing: Mapping[Hashable, ProcessingNode]):
        self.trackers = _check_trackers(trackers)
        self.processing = _check_processing(processing, self.trackers)
        self.order = _topological_order(self.processing)

    def step(self, scans: Mapping[Hashable, Any], time: float | None = None, *,
             lost: Iterable[Hashable] = ()) -> dict[Hashable, Estimates]:
        """The Estimates of every node that reported at this step (module docstring);
        the trackers named in `lost` step on their scans but their reports do not arrive."""
        if not isinstance(scans, Mapping):
            raise FusionInputError(f"scans must be a mapping tracker name -> scan, got "
                                   f"{type(scans).__name__}")
        unknown = [name for name in scans if name not in self.trackers]
        if unknown:
            raise FusionInputError(f"scans for unknown trackers {safe_repr(unknown)}; the "
                                   f"trackers are {safe_repr(list(self.trackers))}")
        lost = self._check_lost(lost, scans)
        time = check_time(time)  # before any node steps
        out, stepped = {}, []
        try:
            for name, tracker in self.trackers.items():
                if name in scans:
                    estimates = _tracker_step(name, tracker, scans[name])
                    stepped.append(name)  # lost ones too: a retry would step them twice
                    if name not in lost:
                        out[name] = estimates
            for name in self.order:
                node = self.processing[name]
                reports = {s: out[s] for s in node.sources if s in out}
                if reports:
                    out[name] = _processing_step(name, node, reports, time)
                    stepped.append(name)
        except (FusionInputError, FusionSolverError) as exc:
            said = f" (nodes {safe_repr(stepped)} had stepped)" if stepped else ""
            raise in_context(exc, "", said) from exc
        except Exception as exc:
            if stepped:
                exc.add_note(f"nodes {safe_repr(stepped)} of the Network had stepped")
            raise
        return out

    def _check_lost(self, lost, scans) -> frozenset:
        """lost: names of trackers with a scan at this step (a lost link's tracker steps), in
        any order: a sequence or a set."""
        if not (is_sequence(lost) or isinstance(lost, Set)):
            raise FusionInputError(f"lost must be a collection of tracker names, got "
                                   f"{safe_repr(lost)}")
        lost = list(lost)
        bad = [name for name in lost if not hashable(name) or name not in scans]
        if bad:
            raise FusionInputError(
                f"lost names {safe_repr(bad)}, not trackers with a scan at this step: a lost "
                "link's tracker steps on its scan (the empty scan if it detected nothing) and its "
                "report does not arrive")
        return frozenset(lost)

    def run(self, scan_series: Iterable[Mapping[Hashable, Any]],
            times: Sequence[float] | None = None) -> dict[Hashable, list[Estimates]]:
        """`step` over scan_series (one mapping of scans per step), with times[t] as the
        time of step t if given; each node's Estimates in step order."""
        scan_series = _sequence(scan_series, "scan_series")
        times = None if times is None else [check_time(t) for t in _sequence(times, "times")]
        if times is not None and len(times) != len(scan_series):
            raise FusionInputError(f"times must have one entry per step ({len(scan_series)}), "
                                   f"got {len(times)}")
        for t in range(1, 0 if times is None else len(times)):  # before any node steps
            check_forward(times[t], times[t - 1], f"times[{t}]")
        series = {name: [] for name in (*self.trackers, *self.order)}
        for t, scans in enumerate(scan_series):
            for name, estimates in self.step(scans, None if times is None else times[t]).items():
                series[name].append(estimates)
        return series


def _processing_step(name, node, reports, time) -> Estimates:
    """The node's fused Estimates, stamped with its network name if it has none."""
    try:
        fused = node.step(reports, time)
    except (FusionInputError, FusionSolverError) as exc:  # name the node as the network
        raise in_context(exc, f"processing node {safe_repr(name)}: ") from exc  # knows it
    return fused if fused.node is not None else dataclasses.replace(fused, node=name)


def _sequence(value, name: str) -> list:
    """value as a list: an iterable in step order (`validation.is_sequence`: not a string,
    a mapping, a set, whose order changes with the hash seed, or a 0-d array)."""
    if not is_sequence(value):
        raise FusionInputError(f"{name} must be a sequence (one entry per step), got "
                               f"{type(value).__name__}")
    return list(value)


def _tracker_step(name, tracker, scan) -> Estimates:
    """tracker.step(scan), checked; an error of the library's is raised again naming the
    tracker as the network knows it, any other (the user's tracker's own) as it is, with
    a note naming it (fuzz U10: a ZeroDivisionError came through with no word of which
    tracker raised it)."""
    try:
        estimates = tracker.step(scan)
    except (FusionInputError, FusionSolverError) as exc:
        raise in_context(exc, f"tracker {safe_repr(name)}: ") from exc
    except Exception as exc:
        exc.add_note(f"raised by the step of tracker {safe_repr(name)} of a fusion_opt Network")
        raise
    if not isinstance(estimates, Estimates):
        raise FusionInputError(f"tracker {safe_repr(name)} returned {type(estimates).__name__} "
                               f"from step, not an Estimates")
    return estimates


def _check_trackers(trackers) -> dict:
    if not isinstance(trackers, Mapping):
        raise FusionInputError(f"trackers must be a mapping name -> tracker, got "
                               f"{type(trackers).__name__}")
    for name, tracker in trackers.items():
        if isinstance(tracker, type):  # its step would want the instance as its scan
            raise FusionInputError(f"tracker {safe_repr(name)} is the class "
                                   f"{tracker.__name__}, not a tracker: give an instance")
        if not callable(getattr(tracker, "step", None)):
            raise FusionInputError(f"tracker {safe_repr(name)} has no step(scan) method")
    _refuse_shared(trackers, "tracker")
    return dict(trackers)


def _check_processing(processing, trackers) -> dict:
    if not isinstance(processing, Mapping):
        raise FusionInputError(f"processing must be a mapping name -> ProcessingNode, got "
                               f"{type(processing).__name__}")
    both = [name for name in processing if name in trackers]
    if both:
        raise FusionInputError(f"names {safe_repr(both)} are both trackers and processing nodes")
    for name, node in processing.items():
        if not isinstance(node, ProcessingNode):
            raise FusionInputError(f"processing node {safe_repr(name)} must be a "
                                   f"ProcessingNode, got {type(node).__name__}")
        unknown = [s for s in node.sources if s not in trackers and s not in processing]
        if unknown:
            raise FusionInputError(f"processing node {safe_repr(name)} has sources "
                                   f"{safe_repr(unknown)} that are neither trackers nor "
                                   "processing nodes")
    _refuse_shared(processing, "processing node")
    return dict(processing)


def _refuse_shared(nodes: Mapping, kind: str) -> None:
    """One object under two names would be stepped twice per step: refused."""
    names_of = {}
    for name, obj in nodes.items():
        names_of.setdefault(id(obj), []).append(name)
    shared = [names for names in names_of.values() if len(names) > 1]
    if shared:
        raise FusionInputError(f"one {kind} object is registered under several names: "
                               f"{safe_repr(shared[0])}")


def _topological_order(processing: dict) -> list:
    """Processing node names, each after its processing-node sources; a cycle refused,
    naming its nodes in order (depth-first search with a stack of its own: Python's
    recursion limit stopped a chain of 1,000 nodes, fuzz K15)."""
    order, state = [], {}  # state: "open" on the current path, "done" when ordered
    for root in processing:
        if state.get(root) == "done":
            continue
        state[root] = "open"
        path = [(root, iter(processing[root].sources))]  # the nodes open, and what is left
        while path:  # of each one's sources
            name, left = path[-1]
            s = next((s for s in left if s in processing and state.get(s) != "done"), None)
            if s is None:
                path.pop()
                state[name] = "done"
                order.append(name)
            elif state.get(s) == "open":
                names = [n for n, _ in path]
                cycle = names[names.index(s):] + [s]
                raise FusionInputError(f"processing nodes form a cycle, each a source of the "
                                       f"one before it: {' -> '.join(map(safe_repr, cycle))}")
            else:
                state[s] = "open"
                path.append((s, iter(processing[s].sources)))
    return order
