"""A processing node: associate its sources' estimates, fuse each group, keep fused ids.

    node = ProcessingNode(["a", "b", "c"], method="mbci", threshold=1.0,
                          p_detect={"a": 0.9, "b": 0.7, "c": 0.8}, growth=1.01)
    fused = node.step({"a": est_a, "b": est_b, "c": est_c})     # -> Estimates

Each step:
1. associate the reports (`fusion_opt.association`: "nearest" or "assignment", under
   `threshold`, over the state components `dims`) into groups of at most one estimate
   per source;
2. drop the groups of fewer than `min_sources` sources, pass a group of one on as it is,
   and fuse every group of two or more with `method` (any rule of `fo.fuse` that needs no
   cross-covariance); all the groups of one size go to one `fo.fuse_batch` call (in
   chunks of at most half of `limits.working_memory`). MBCI
   scales each member's information by the product over the group's own sources,
       s_i = p_i + (1 - p_i) chi prod_{j in group, j != i} (p_j + (1 - p_j) chi);
3. give each fused track an id: a group inherits the id of a recent fused track (one
   reported at one of the last `memory` steps; memory = 1: the previous step's) with
   which it shares the most (source, source track id) pairs (a pair counts for every
   recent fused track holding it), ties going to the more
   recent, then to the nearer one over `dims`; greedily, largest overlap first, so an id
   goes to at most one group; a group sharing no pair with a free id gets a new id, never
   reused (until `reset`). A fused track remembers the pairs and the mean of the last
   step it was reported at, so a target keeps its fused id while one of the source tracks
   of that step continues: through a missed report at one source, when one source
   restarts its track, and, for up to `memory` - 1 steps, through steps at which no group
   of it is reported (every source missed it, or too few did for `min_sources`). Not when
   both happen at once: a source that missed the last report and returns as the other
   source restarts brings back a pair the fused track no longer holds, and the group
   gets a new id.

A source whose report is missing contributes nothing that step. The fused `Estimates`
are ordered by id, stamped `node=name` and with `time`: the step's `time` if given, else
the common time of the reports (reports of different times are refused: pass `time=`
to fuse them anyway); a time before the last step's is refused (tracks go forward; data
out of order is not supported). `groups` holds the last step's groups by fused id: which source
tracks each fused track came from.
"""

from __future__ import annotations

from collections import Counter, defaultdict
from collections.abc import Hashable, Mapping
from typing import NamedTuple

import numpy as np

from .association import Group, check_dims, check_method, check_threshold, groups_of
from .backends import BACKENDS
from .batch import fuse_batch
from .core import DEFAULT_BACKEND
from .estimates import Estimates, check_forward, check_time
from .fusion import fuse
from .limits import batch_bytes, limits
from .linalg import row_norms
from .results import FusionInputError, FusionSolverError, in_context
from .validation import finite_real, hashable, is_integer, is_sequence, safe_repr

FUSE_METHODS = ("ci", "bci", "mbci", "naive", "fast-ci", "ifci", "ici", "ei")
PAIRWISE = ("ci", "ici", "ei")
CI_FAMILY = ("ci", "bci", "mbci")
CRITERIA = ("trace", "logdet")


class ProcessingNode:
    """Fuses the estimates of `sources` (source names) step by step (module docstring).

    method, criterion, backend: as in `fo.fuse_batch` ("known-cross" is not offered: a
    processing node does not know the cross-covariances of its sources); backend is the
    weight solver of "ci", "bci" and "mbci" (None: "newton"), and the rules, which have
    none, refuse one, as `fo.fuse` does;
    association ("nearest" | "assignment"), threshold (> 0), dims (state components
    compared; None: all): as in `fo.associate`;
    p_detect: {source: detection probability in [0, 1]} for every source, for "mbci" only;
    chi in (0, 1] or growth = 1 / chi >= 1 (the paper's chi^-1), "mbci" only: chi = 1.0 by
    default (MBCI then equals BCI), growth replaces it when given (with chi left at 1);
    min_sources: groups of fewer sources are dropped (1 passes single estimates on);
    memory: steps a fused track's id stays claimable after it was last reported (>= 1;
    1: only the previous step's tracks);
    name: stamped on the fused Estimates as `node` and named in errors."""

    def __init__(self, sources, *, method="mbci", criterion="trace", backend=None,
                 association="nearest", threshold, dims=None, p_detect=None, chi=1.0,
                 growth=None, min_sources=1, memory=1, name=None):
        self.name = _check_name(name)
        self.sources = self._check_sources(sources)
        self._known = frozenset(self.sources)  # membership in O(1): 16,000 sources (fuzz K12)
        self.method = self._check_method(method)
        self.criterion = self._check_choice("criterion", criterion, CRITERIA)
        self.backend = self._check_backend(backend)
        self.association = check_method(association)
        self.threshold = check_threshold(threshold)
        self.dims = check_dims(dims)
        self.p_detect, self.chi = self._check_detection(p_detect, chi, growth)
        self.min_sources = self._check_min_sources(min_sources)
        self.memory = self._check_memory(memory)
        self.reset()

    def reset(self) -> None:
        """Forget the fused tracks and restart ids at 0, as newly built."""
        self.groups: dict[int, Group] = {}
        self._tracks: dict[int, _Track] = {}  # fused id -> what it was when last reported
        self._steps = 0
        self._next_id = 0
        self._n: int | None = None
        self._time: float | None = None  # stamped on the last step

    def step(self, reports: Mapping[Hashable, Estimates], time: float | None = None
             ) -> Estimates:
        """Fused estimates of this step from reports {source: Estimates} (module docstring)."""
        reports, n = self._check_reports(reports)
        time = self._step_time(reports, time)
        groups = [g for g in groups_of(list(reports), list(reports.values()), self.threshold,
                                       self.association, self.dims)
                  if len(g) >= self.min_sources]
        means, covs = self._fuse(groups, n)
        ids = self._ids(groups, means)
        order = np.argsort(ids, kind="stable")
        fused = Estimates._of(means[order], covs[order], ids[order], time, self.name)
        self.groups = {int(ids[i]): groups[i] for i in order}
        self._remember(fused)
        self._time = self._time if time is None else time
        self._n = n  # only a step that succeeds sets it (fuzz K9)
        return fused

    def _fuse(self, groups: list[Group], n: int) -> tuple[np.ndarray, np.ndarray]:
        """Fused means (G, n) and covs (G, n, n): one fuse_batch call per group size, in
        chunks whose arrays take at most half of limits.working_memory (fuzz K4: 1,500
        groups of 8 estimates of n = 60 made one batch of 1.3 GB, refused as a solver's
        memory_limit; fuse_batch gives each problem what fuse gives it, so chunks change
        no number)."""
        means, covs = np.empty((len(groups), n)), np.empty((len(groups), n, n))
        by_size = defaultdict(list)
        for i, g in enumerate(groups):
            by_size[len(g)].append(i)
        for size, same in by_size.items():
            fit = limits.working_memory / (2.0 * batch_bytes(1, size, n))  # inf: no limit
            step = max(1, int(min(fit, len(same))))
            for start in range(0, len(same), step):
                self._fuse_chunk(groups, same[start:start + step], means, covs)
        return means, covs

    def _fuse_chunk(self, groups: list[Group], idx: list[int], means, covs) -> None:
        """Fuse groups[idx], all of one size, into means[idx] and covs[idx]."""
        size = len(groups[idx[0]])
        M = np.stack([groups[i].means for i in idx])  # (B, size, n)
        C = np.stack([groups[i].covs for i in idx])  # (B, size, n, n)
        if size == 1:
            means[idx], covs[idx] = M[:, 0], C[:, 0]
            return
        extra = {}
        if self.method == "mbci":
            p = [[self.p_detect[s] for s in groups[i].sources] for i in idx]
            extra = dict(p_detect=np.array(p), chi=self.chi)  # p (B, size)
        try:
            r = fuse_batch(M, C, self.method, self.criterion, self.backend, **extra)
        except (FusionInputError, FusionSolverError) as exc:
            raise self._failed(exc, [groups[i] for i in idx], extra) from None
        means[idx], covs[idx] = r.mean, r.cov

    def _failed(self, exc, groups: list[Group], extra: dict):
        """The error of a fuse_batch of groups, naming this node and the first group that
        fails when fused alone (the batch's message says "problem b", which the caller does
        not know): its sources, in the order its message numbers them as nodes, and their
        track ids. Only after a failure, so one fusion per group at most."""
        for b, g in enumerate(groups):
            one = {k: v[b] if np.ndim(v) == 2 else v for k, v in extra.items()}
            try:
                fuse(g.means, g.covs, self.method, self.criterion, self.backend, **one)
            except (FusionInputError, FusionSolverError) as alone:
                members = [f"source {safe_repr(s)} track {i} (node {k})" for k, (s, i)
                           in enumerate(zip(g.sources, g.ids.tolist(), strict=True))]
                if len(members) > 6:  # a group of 2,000 listed 78,000 characters (fuzz I13)
                    members[3:-2] = [f"{len(members) - 5} more"]
                return in_context(alone, f"{self._where()}: fusing {' with '.join(members)}: ")
        return in_context(exc, f"{self._where()}: ")

    def _ids(self, groups: list[Group], means: np.ndarray) -> np.ndarray:
        """Fused track ids (G,): inherited by shared (source, track id) pairs, else new."""
        holders = defaultdict(list)  # (source, track id) -> every recent fused track holding
        for f, track in self._tracks.items():  # it, not only the latest (fuzz K8: a target
            for p in track.pairs:  # misjoined for a step lost its id where the docstring
                holders[p].append(f)  # says it keeps it)
        group, fid, shared = [], [], []  # one entry per (group, recent track) sharing pairs
        for i, g in enumerate(groups):
            counts: dict[int, int] = {}  # a Counter costs more than a small group's count
            for p in g.pairs:
                for f in holders.get(p, ()):
                    counts[f] = counts.get(f, 0) + 1
            for f, count in counts.items():
                group.append(i)
                fid.append(f)
                shared.append(count)
        age = [self._steps - self._tracks[f].step for f in fid]
        distance = self._distances(means[group], fid)
        ids = np.full(len(groups), -1, dtype=np.int64)
        taken = set()
        for k in np.lexsort((fid, group, distance, age, np.negative(shared))).tolist():
            if ids[group[k]] < 0 and fid[k] not in taken:
                ids[group[k]] = fid[k]
                taken.add(fid[k])
        for i in np.flatnonzero(ids < 0):
            ids[i] = self._next_id
            self._next_id += 1
        return ids

    def _distances(self, means: np.ndarray, fids: list[int]) -> np.ndarray:
        """Distances over dims from fused means (K, n) to the last means of fused tracks
        fids (K,)."""
        if not fids:  # also at the first step, before any fused track
            return np.zeros(0)
        with np.errstate(over="ignore"):  # past float64 (means near 1e308): inf, the
            d = means - np.array([self._tracks[f].mean for f in fids])  # farthest
        return row_norms(d if self.dims is None else d[:, self.dims])  # (fuzz N1's kind)

    def _remember(self, fused: Estimates) -> None:
        """Keep this step's fused tracks, forget those older than `memory` steps."""
        self._steps += 1
        for f, mean in zip(fused.ids.tolist(), fused.means, strict=True):
            self._tracks[f] = _Track(self.groups[f].pairs, mean, self._steps)
        oldest = self._steps - self.memory + 1
        self._tracks = {f: t for f, t in self._tracks.items() if t.step >= oldest}

    # --- input checks, each naming the node and the argument or source ---

    def _err(self, message: str) -> FusionInputError:
        return FusionInputError(f"{self._where()}: {message}")

    def _where(self) -> str:
        return "ProcessingNode" if self.name is None else f"ProcessingNode {safe_repr(self.name)}"

    def _check_sources(self, sources) -> tuple:
        if not is_sequence(sources):
            raise self._err(f"sources must be a sequence of source names (a list or tuple: "
                            f"a set has no order), got {safe_repr(sources)}")
        sources = tuple(sources)
        if not sources:
            raise self._err("sources is empty: a processing node needs at least one source")
        bad = [s for s in sources if not hashable(s)]
        if bad:
            raise self._err(f"sources must be hashable names, got {safe_repr(bad)}")
        repeated = sorted(safe_repr(s) for s, k in Counter(sources).items() if k > 1)
        if repeated:
            raise self._err(f"sources are listed more than once: {', '.join(repeated)}")
        return sources

    def _check_method(self, method) -> str:
        if isinstance(method, str) and method == "known-cross":
            raise self._err("method 'known-cross' needs the sources' cross-covariances, "
                            "which a processing node does not have")
        self._check_choice("method", method, FUSE_METHODS)
        if method in PAIRWISE and len(self.sources) > 2:
            raise self._err(f"method {safe_repr(method)} fuses pairs, but {len(self.sources)} "
                            f"sources can form larger groups: use 'bci' or 'mbci'")
        return method

    def _check_backend(self, backend) -> str | None:
        if self.method not in CI_FAMILY:
            if backend is not None:
                raise self._err(f"method {safe_repr(self.method)} has no weight solver: leave "
                                f"backend unset (got {safe_repr(backend)})")
            return None
        backend = DEFAULT_BACKEND if backend is None else backend
        self._check_choice("backend", backend, BACKENDS)
        if backend == "closed-form" and self.method in CI_FAMILY and len(self.sources) > 2:
            raise self._err(f"backend 'closed-form' fuses pairs, but {len(self.sources)} "
                            f"sources can form larger groups: use 'newton'")
        return backend

    def _check_choice(self, name: str, value, choices) -> str:
        if not isinstance(value, str) or value not in choices:
            raise self._err(f"{name} must be one of {tuple(choices)}, got {safe_repr(value)}")
        return value

    def _check_detection(self, p_detect, chi, growth) -> tuple[dict | None, float | None]:
        """({source: p}, chi) for "mbci"; (None, None) otherwise."""
        if self.method != "mbci":
            given = [name for name, stray in (("p_detect", p_detect is not None),
                                              ("chi", finite_real(chi) != 1.0),
                                              ("growth", growth is not None)) if stray]
            if given:
                verb = "apply" if len(given) > 1 else "applies"
                raise self._err(f"{' and '.join(given)} {verb} to method 'mbci' only, not "
                                f"{safe_repr(self.method)}")
            return None, None
        if not isinstance(p_detect, Mapping):
            raise self._err(f"method 'mbci' needs p_detect, a mapping source -> detection "
                            f"probability, got {safe_repr(p_detect)}")
        missing = [s for s in self.sources if s not in p_detect]
        unknown = [s for s in p_detect if s not in self._known]
        if missing or unknown:
            raise self._err(f"p_detect must name exactly the sources: missing "
                            f"{safe_repr(missing)}, unknown {safe_repr(unknown)}")
        p = {s: finite_real(p_detect[s]) for s in self.sources}
        for s, value in p.items():
            if value is None or not 0.0 <= value <= 1.0:
                raise self._err(f"p_detect of source {safe_repr(s)} must be a number in [0, 1], "
                                f"got {safe_repr(p_detect[s])}")
        value = finite_real(chi)
        if growth is not None:
            if value != 1.0:
                raise self._err("give chi or growth (= 1 / chi), not both")
            g = finite_real(growth)
            if g is None or g < 1.0:
                raise self._err(f"growth must be one finite number >= 1, the same for every "
                                f"source, got {safe_repr(growth)}")
            value = 1.0 / g
        if value is None or not 0.0 < value <= 1.0:
            raise self._err(f"chi must be one number in (0, 1], the same for every source, "
                            f"got {safe_repr(chi)}")
        return p, value

    def _check_min_sources(self, min_sources) -> int:
        if not is_integer(min_sources) or not 1 <= min_sources <= len(self.sources):
            raise self._err(f"min_sources must be an integer in [1, {len(self.sources)}] "
                            f"(the number of sources), got {safe_repr(min_sources)}")
        return int(min_sources)

    def _check_memory(self, memory) -> int:
        if not is_integer(memory) or memory < 1:
            raise self._err(f"memory must be an integer >= 1 (steps), got {safe_repr(memory)}")
        return int(memory)

    def _check_reports(self, reports) -> tuple[dict[Hashable, Estimates], int]:
        """The reports in the order of `sources`, and their state dimension n; unknown
        sources, non-Estimates and another n than earlier steps' refused by name."""
        if not isinstance(reports, Mapping):
            raise self._err(f"reports must be a mapping source -> Estimates, got "
                            f"{type(reports).__name__}")
        unknown = [s for s in reports if s not in self._known]
        if unknown:
            raise self._err(f"reports from unknown sources {safe_repr(unknown)}; its sources "
                            f"are {safe_repr(list(self.sources))}")
        ordered = {s: reports[s] for s in self.sources if s in reports}
        for s, r in ordered.items():
            if not isinstance(r, Estimates):
                raise self._err(f"report of source {safe_repr(s)} must be an Estimates, got "
                                f"{type(r).__name__}")
        ns = {s: r.n for s, r in ordered.items()}
        n = self._n if self._n is not None else next(iter(ns.values()), None)
        other = {s: k for s, k in ns.items() if k != n}
        if other:
            raise self._err(f"estimates of state dimension n = {n} expected, got "
                            f"{safe_repr(other)} from sources {safe_repr(list(other))}")
        if n is None:
            raise self._err("no reports at its first step: the state dimension is unknown")
        if n != self._n:  # the first step (later steps have n = self._n, checked above)
            check_dims(self.dims, n)
        return ordered, n

    def _step_time(self, reports: dict[Hashable, Estimates], time) -> float | None:
        """time, or the reports' common time; not before the last step's (checked before
        anything changes)."""
        if time is None:
            times = {s: r.time for s, r in reports.items() if r.time is not None}
            if len(set(times.values())) > 1:
                raise self._err(f"reports carry different times {safe_repr(times)}; pass time= to "
                                f"stamp the fused estimates")
            time = next(iter(times.values()), None)
        try:
            time = check_time(time)
            check_forward(time, self._time)
        except FusionInputError as exc:
            raise self._err(str(exc)) from None
        return time


class _Track(NamedTuple):
    """A fused track as last reported: its group's pairs, its mean (n,), the step."""

    pairs: tuple
    mean: np.ndarray
    step: int


def _check_name(name):
    if name is not None and not hashable(name):
        raise FusionInputError(f"ProcessingNode: name must be hashable, got {safe_repr(name)}")
    return name

