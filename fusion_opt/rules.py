"""Fusion rules other than optimised CI, for comparison: `RULES[name](means, covs, criterion,
**args) -> RuleOutput` for one problem; the core (`fuse(method=name)`, `fuse_batch`) calls
`compiled`, a whole batch of a rule in one compiled call (`fuse_fixed`, `fuse_pair`,
`fuse_known_cross`), which the functions of RULES call too.

Inputs arrive validated: float64 means (N, n) and covs (N, n, n), finite, symmetric and
positive definite, multiplied by a power of two so that the nodes' scales sit around 1
(they may still differ by up to ~1e150 either way, each with a condition number up to ~1e13).
naive, fast-ci, ifci and known-cross also take F (N, n, n), the covariances' square-root factors,
F_i = C_i^-1 lower triangular, P_i = C_i C_i^T, so Y_i = F_i^T F_i: the core passes those
its compiled checks computed (`prepare.py`), so they are not computed twice (`_factors`
computes them for a direct call).
Each rule gives gains K_i (n, n) with sum_i K_i = I, the mean m = sum_i K_i m_i and a
covariance P. What each assumes, and whether P is consistent (>= the true error covariance)
when the cross-correlation of the inputs is unknown:

- "naive" (independent / Kalman): P = (sum Y_i)^-1, K_i = P Y_i, Y_i = P_i^-1. Assumes
  independent errors; optimal then, overconfident (inconsistent) under correlation.
- "known-cross" (BLUE; Bar-Shalom–Campo for N = 2): given the joint covariance S (N n, N n)
  with blocks cross[i, j] = cov(e_i, e_j), P = (H^T S^-1 H)^-1 and K = P H^T S^-1 with
  H = [I; ...; I]. Exact and the smallest error covariance of all linear unbiased rules, if
  S is right; it does not apply when S is unknown.
- "fast-ci" (Niehsen 2002): CI, P = (sum w_i Y_i)^-1 and K_i = P w_i Y_i, with
  w_i proportional to 1 / tr(P_i). Consistent under any correlation (every CI weight is),
  optimal in no criterion.
- "ifci" (improved fast CI, Franken & Hupper 2005): CI with, for Y = sum Y_i,
  w_i proportional to det Y - det(Y - Y_i) + det Y_i. Consistent under any correlation.
- "ici" (inverse CI, Noack et al. 2017; N = 2): with G = w P_a + (1 - w) P_b,
  P^-1 = Y_a + Y_b - G^-1, K_a = P (Y_a - w G^-1), K_b = P (Y_b - (1 - w) G^-1), and w in
  [0, 1] minimising the criterion (convex in w). Consistent when the correlation comes from
  common information of unknown amount, not under arbitrary correlation; w = 0 and 1 give
  P_a and P_b, so it is never worse than the better input.
- "ei" (ellipsoidal intersection, Sijs & Lazar 2012; N = 2): with the mutual covariance
  Gam = T diag(max(mu_k, 1)) T^T, P^-1 = Y_a + Y_b - Gam^-1 and the mutual mean gam,
  m = P (Y_a m_a + Y_b m_b - Gam^-1 gam): per axis of T, the estimate with the smaller
  variance. A heuristic: no consistency guarantee.

How the numbers stay finite and accurate:

- The pair rules (ici, ei) work in the basis that diagonalises both covariances,
  P_b = T T^T and P_a = T diag(mu) T^T (`_pencil`), where each formula is per axis. mu are
  the squared singular values of L_b^-1 L_a (Cholesky factors), so scale differences between
  the nodes cost no accuracy and nothing is squared. ICI's covariance per axis is
  mu (a + b mu) / (a + b mu^2) (a = 1 - w, b = w: a sum of positive terms, so P is positive
  definite), kept in logs; its weight is found by bisection on the sign of the derivative.
  EI's mutual mean needs a regulariser eta only on an axis whose two variances tie to within
  10 eta, eta = eps; there the axis gives the loser's mean the share
  t eta / (1 - t + 2 eta), t <= 1 the ratio of the smaller to the larger variance (1/2 at an
  exact tie, 0 on every other axis, as eta -> 0 in Sijs & Lazar's eq. 16). An exact tie
  is seen as one only where the computed ratio comes within 10 eps of 1, which the pencil
  of two ill-conditioned nodes need not do (1 - t = 318 eps at condition 1e3: the
  winner is then the node rounding favours, and swapping the nodes can change it); a
  tolerance that follows the conditioning made EI depend on the coordinates instead.
- Where one node's gain is 1 on every axis of the pencil (ICI at w = 0 or 1, EI won on
  every axis by one node), ici and ei return that node's estimate as given, mean,
  covariance and objective, as BCI's vertex does (rebuilt from the pencil it was 25 ulps
  off, 2.6e-3 in the node's own metric at condition 1e13: fuzz J4).
- naive, fast-ci and ifci never invert a covariance: node i enters as its factor F_i and the
  weighted sum of informations as the QR of [sqrt(w_i) F_i], as in the compiled path
  (`fuse_fixed`, by `assemble.fuse_at`).
- IFCI's weights are formed from ratios to det Y, which lie in [0, 1]:
  1 - det(Y - Y_i)/det Y = 1 - prod_k (1 - alpha_k), alpha the squared singular values of
  F_i R^-1 (Y = R^T R), by log1p/expm1, and det Y_i / det Y from the triangular
  diagonals.
- known-cross whitens each node by its Cholesky factor (the joint becomes a correlation
  matrix C with identity diagonal blocks) and solves the least-squares form by QR.
- The mean is m_r + sum_i K_i (m_i - m_r), r the node of the largest gain share, with the
  differences scaled by a power of two, so that no product overflows; known-cross forms
  the sum without its gains, which can fall below float64's range where their products
  with the means do not (`_blue_mean`). (naive, fast-ci and ifci: from the QR, above.)
A rule that still meets a non-finite or non-positive-definite result raises
FusionSolverError(method, "numerical_error", ..., role="method"); it never returns one.

`weights` are the CI weights for fast-ci and ifci, (1 - w, w) for ici ("ci_weights": as
for CI, weight 1 on a node gives that node's estimate, since w = 0 gives P_a), and
the gain shares tr(K_i) / n (summing to 1, negative where a gain is, e.g. for known-cross)
for naive, known-cross and ei ("gain_shares").
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from .assemble import all_finite, fuse_at
from .factored import factor, work
from .linalg import (
    cholesky,
    copy,
    fill,
    jit,
    lower_inverse,
    lower_solve,
    lower_t_solve,
    matmul,
    matmul_t,
    qr,
    upper_inverse,
)
from .prepare import MAX_CONDITION, scaled
from .results import FusionInputError, FusionSolverError, Status, overflow_error
from .validation import SYMMETRY_RTOL, kernel_array, real_array, symmetrised

CI_WEIGHTS, GAIN_SHARES = "ci_weights", "gain_shares"
_LN2 = np.log(2.0)
_EPS = np.finfo(float).eps
# EI: regulariser of the mutual mean on a tied axis (Sijs & Lazar's eta), rounding level.
EI_ETA = _EPS
# ICI: the weight is w = 1 / (1 + exp(-u)); u in [-_U_MAX, _U_MAX] spans every float weight.
_U_MAX = 800.0


class RuleOutput(NamedTuple):
    """A rule's result: weights (N,) as `weights_are` says, mean (n,), cov (n, n) symmetric
    positive definite and finite, status CLOSED_FORM (ici: OPTIMAL for its 1-D search)."""

    weights: np.ndarray
    mean: np.ndarray
    cov: np.ndarray
    status: Status
    weights_are: str


def naive(means, covs, criterion, *, F=None) -> RuleOutput:
    """Independent (Kalman) fusion: the CI formula with every weight 1 (`fuse_fixed`)."""
    return _one("naive", means, covs, criterion, F)


def known_cross(means, covs, criterion, *, cross, F=None) -> RuleOutput:
    """BLUE given cross (N, N, n, n), cross[i, j] = cov(e_i, e_j), cross[i, i] = covs[i]
    (`fuse_known_cross`)."""
    N, n = np.shape(means)
    return _one("known-cross", means, covs, criterion, F, cross_array(cross, 1, N, n, False))


def fast_ci(means, covs, criterion, *, F=None) -> RuleOutput:
    """CI with w_i = (1 / tr P_i) / sum_j (1 / tr P_j) (Niehsen 2002; `fuse_fixed`)."""
    return _one("fast-ci", means, covs, criterion, F)


def ifci(means, covs, criterion, *, F=None) -> RuleOutput:
    """CI with the determinant weights of Franken & Hupper (2005), from ratios to det Y
    (`fuse_fixed`)."""
    return _one("ifci", means, covs, criterion, F)


def _one(method, means, covs, criterion, F, cross=None) -> RuleOutput:
    """A rule of COMPILED on one problem, means (N, n) and covs (N, n, n) (known-cross:
    cross (1, N, N, n, n) from `cross_array`), called directly (the core calls `compiled`
    on its prescaled batch)."""
    covs = np.array(covs, dtype=float)
    if F is None:  # the pair rules factor the covariances themselves
        F = covs if method in PAIR_ONLY else _factors(covs)
    weights, mean, cov, _, status, are = compiled(
        method, np.array(means, dtype=float)[None], covs[None], np.array(F, dtype=float)[None],
        np.zeros(1, np.int64), criterion == "trace", cross)
    return RuleOutput(weights[0], mean[0], cov[0], status, are)  # checked by the kernel


def compiled(method, means, covs, F, k, trace: bool, cross=None, batch: bool = False):
    """Rule `method` of COMPILED on B problems, means (B, N, n) and covs (B, N, n, n), in
    one compiled call; F (B, N, n, n) are the factors of the covariances scaled by 2^-k
    (B,) (`prepare`), which the pair rules do not use; known-cross's cross (B, N, N, n, n)
    from `cross_array`: (weights (B, N), mean (B, n), cov (B, n, n), the criterion at it
    (B,), the status, weights_are). Raises FusionInputError for a cross that is no joint
    covariance of the nodes (naming the problem in a batch) and where a result overflows
    float64 in the input's units, FusionSolverError where it is not positive definite to
    rounding in the scaled units."""
    B, N, n = means.shape
    W, shares, obj = np.empty((B, N)), np.empty((B, N)), np.empty(B)
    mean, cov = np.empty((B, n)), np.empty((B, n, n))
    where = np.zeros(3, dtype=np.int64)
    rule = COMPILED[method]
    if rule == KNOWN_CROSS:
        condition = np.empty(B)
        code = fuse_known_cross(F, means, covs, cross, k, trace, mean, cov, obj, shares,
                                where, condition)
        if code >= CROSS_NONFINITE:
            raise _cross_error(code, where, condition, covs, cross, batch)
    elif method in PAIR_ONLY:
        code = fuse_pair(rule, means, covs, k, trace, W, mean, cov, obj, shares, where)
    else:
        code = fuse_fixed(rule, F, means, covs, k, trace, W, mean, cov, obj, shares, where)
    if code == OVERFLOW:
        raise overflow_error(mean, cov, obj, batch, int(where[0]))
    if code != OK:
        raise _numerical_error(method, code, f"problem {where[0]}: " if batch else "")
    if N == 1:  # its checks passed: the node itself (fuzz M4: the formula's rounding of it)
        _single_node(means, covs, F, k, trace, W, shares, mean, cov, obj)
    status = Status.OPTIMAL if method == "ici" else Status.CLOSED_FORM
    if method in ("naive", "known-cross", "ei"):
        return shares, mean, cov, obj, status, GAIN_SHARES
    return W, mean, cov, obj, status, CI_WEIGHTS


@jit
def fuse_fixed(rule, F, means, covs, k, trace: bool, W, mean, cov, obj, shares, where) -> int:
    """naive, fast-ci and ifci on B problems (`compiled` says what each array holds): W receives
    the rule's weights (naive: 1; fast-ci: 1 / tr P_i over its sum, from the traces of
    the scaled covariances, whose ratios are the input's; ifci: its scores over their
    sum), then `fuse_at` the estimate. Returns OK, NOT_PD or OVERFLOW, and the problem
    in where[0]."""
    B, N, n = means.shape
    if rule == IFCI:
        where[0] = _ifci_scores(F, W)
        if where[0] >= 0:
            return NOT_PD
    for b in range(B):
        if rule == NAIVE:
            W[b, :] = 1.0
            continue
        if rule == FAST_CI:
            for i in range(N):
                W[b, i] = 0.0
                for a in range(n):
                    W[b, i] += np.ldexp(covs[b, i, a, a], -k[b])
            low = W[b].min()  # ratios in (0, 1]: no overflow whatever the scales
            for i in range(N):
                W[b, i] = low / W[b, i]
        total = W[b].sum()
        if not 0.0 < total < np.inf:
            where[0] = b
            return NOT_PD
        for i in range(N):
            W[b, i] /= total
    where[0] = fuse_at(F, means, k, W, trace, mean, cov, obj, shares)
    if where[0] >= 0:
        return NOT_PD
    for b in range(B):
        if not (np.isfinite(obj[b]) and all_finite(mean[b]) and all_finite(cov[b])):
            where[0] = b
            return OVERFLOW
    return OK


@jit
def _ifci_scores(F, score) -> int:
    """score (B, N) = 1 - det(Y - Y_i) / det Y + det Y_i / det Y for factors F (B, N, n, n),
    Y = sum_i Y_i = R^T R (the QR of `factored.factor`, weights 1; module docstring):
    1 - prod_k (1 - alpha_k), alpha the squared singular values of F_i R^-1, by log1p and
    expm1, and the triangular diagonals' ratios. Returns the first problem whose Y is not
    positive definite to rounding, or -1."""
    N, n = F.shape[1], F.shape[2]
    ws = work(N, n)
    ones, B = np.ones(N), np.empty((n, n))
    for b in range(F.shape[0]):
        if not factor(F[b], ones, ws.At, ws.Vt, ws.R, ws.Ri)[1]:
            return b
        for i in range(N):
            matmul(F[b, i], ws.Ri, B)
            sigma = np.linalg.svd(B)[1]
            kept, own = 0.0, 0.0
            for k in range(n):
                kept += np.log1p(-min(sigma[k] * sigma[k], 1.0))  # -inf where alpha = 1
                own += 2.0 * np.log(abs(F[b, i, k, k] / ws.R[k, k]))
            score[b, i] = -np.expm1(kept) + np.exp(own)
    return -1


def ici(means, covs, criterion) -> RuleOutput:
    """Inverse covariance intersection of N = 2 estimates (module docstring; `fuse_pair`)."""
    return _one("ici", means, covs, criterion, None)


def ei(means, covs, criterion) -> RuleOutput:
    """Ellipsoidal intersection of N = 2 estimates (module docstring; `fuse_pair`)."""
    return _one("ei", means, covs, criterion, None)


RULES: dict[str, Callable[..., RuleOutput]] = {
    "naive": naive, "known-cross": known_cross, "fast-ci": fast_ci, "ifci": ifci,
    "ici": ici, "ei": ei}
RULE_ARGS: dict[str, frozenset] = {name: frozenset() for name in RULES} | {
    "known-cross": frozenset({"cross"})}
PAIR_ONLY = frozenset({"ici", "ei"})
# Each rule's kernel (`compiled`): the CI formula at fixed weights by `fuse_fixed`, ici and
# ei by `fuse_pair`, known-cross by `fuse_known_cross`.
NAIVE, FAST_CI, IFCI, ICI, EI, KNOWN_CROSS = 0, 1, 2, 3, 4, 5
COMPILED = {"naive": NAIVE, "fast-ci": FAST_CI, "ifci": IFCI, "ici": ICI, "ei": EI,
            "known-cross": KNOWN_CROSS}
OK, NOT_PD, OVERFLOW, RATIO = 0, 1, 2, 3
_LAPACK_ABOVE = 64  # known-cross: the joint's factors by LAPACK above this order (N n)
# known-cross's refusals of cross (`_cross_error` words them)
CROSS_NONFINITE, CROSS_ASYMMETRIC, CROSS_DIAGONAL, CROSS_NOT_PD, CROSS_SINGULAR = range(4, 9)


def _factors(covs):
    """F_i = C_i^-1 (..., N, n, n), lower triangular, C_i C_i^T = P_i: Y_i = F_i^T F_i."""
    return np.linalg.inv(np.linalg.cholesky(covs))


@jit
def gain_mean(means, K, shares, mean):
    """mean (n,) = m_r + sum_i K_i (m_i - m_r) for means (N, n) and gains K (N, n, n) with
    sum_i K_i = I, r the node of the largest gain share, the differences taken in units of
    2^e, e the exponent of the largest |mean|, so that no product overflows (a result
    beyond float64 comes back inf, which the callers refuse)."""
    N, n = means.shape
    r = np.argmax(shares)
    e = math.frexp(np.abs(means).max())[1]
    for a in range(n):
        t = 0.0
        for i in range(N):
            for c in range(n):
                t += K[i, a, c] * (np.ldexp(means[i, c], -e) - np.ldexp(means[r, c], -e))
        mean[a] = _shifted(means[r, a], t, e, e)


def _single_node(means, covs, F, k, trace: bool, W, shares, mean, cov, obj) -> None:
    """One node (N = 1), whose gain is I under every rule: weight and share 1, its mean and
    its covariance symmetrised (`validation.symmetrised`, the whole batch at once), the
    criterion there (log det from its factor F = C^-1, C C^T = P 2^-k)."""
    W[:], shares[:] = 1.0, 1.0
    mean[:] = means[:, 0]
    n = means.shape[2]
    cov[:] = symmetrised(covs[:, 0])
    if trace:
        obj[:] = np.trace(cov, axis1=1, axis2=2)
    else:
        obj[:] = -2.0 * np.log(np.diagonal(F[:, 0], axis1=1, axis2=2)).sum(axis=1) + n * k * _LN2


def _numerical_error(method, code, problem: str) -> FusionSolverError:
    """A rule's NOT_PD (in the scaled units) or RATIO, for the problem named by `problem`."""
    if code == RATIO:
        what = "the covariances' ratio exceeds the double-precision range"
    elif COMPILED[method] in (NAIVE, FAST_CI, IFCI):
        what = "the sum of the informations is not positive definite in double precision"
    else:
        what = "the fused covariance is not positive definite in double precision"
    return FusionSolverError(method, "numerical_error", problem + what, role="method")


@jit
def fuse_pair(rule, means, covs, k, trace: bool, W, mean, cov, obj, shares, where) -> int:
    """ICI or EI on B pairs, means (B, 2, n) and covs (B, 2, n, n) (`compiled` says what the
    outputs hold), in the basis of `_pencil`, per axis (module docstring). Returns OK,
    NOT_PD (a covariance or weights not finite or not positive definite in the scaled
    units), RATIO (the covariances' ratio beyond float64) or OVERFLOW (the result beyond it
    in the input's), and the problem in where[0]."""
    B, n = means.shape[0], means.shape[2]
    S, L, K = np.empty((2, n, n)), np.empty((2, n, n)), np.empty((2, n, n))
    T, Tinv, P, M = np.empty((n, n)), np.empty((n, n)), np.empty((n, n)), np.empty((n, n))
    ka, kb, f = np.empty(n), np.empty(n), np.empty(n)
    for b in range(B):
        for i in range(2):
            scaled(covs[b, i], 1.0, k[b], S[i])
        sigma = _pencil(S, L, M, T, Tinv)
        where[0] = b
        if sigma.min() == 0.0:
            return RATIO
        if rule == ICI:
            la, lb = _ici_axes(sigma, T, trace, ka, kb, f)
            W[b, 0], W[b, 1] = np.exp(la), np.exp(lb)  # CI's sense: (1, 0) gives node a
        else:
            _ei_axes(sigma, ka, kb, f)
        v = _outright(ka, kb)
        if v >= 0:  # one node on every axis: its estimate as given, as BCI's vertex
            W[b, v], W[b, 1 - v] = 1.0, 0.0
            shares[b, v], shares[b, 1 - v] = 1.0, 0.0
            if not _node(means[b, v], covs[b, v], L[v], k[b], trace, mean[b], cov[b], obj, b):
                return OVERFLOW
            continue
        _gains(T, Tinv, ka, K[0])
        _gains(T, Tinv, kb, K[1])
        for a in range(n):
            for c in range(n):
                t = 0.0
                for j in range(n):  # (T f)(T f)^T: T f^2 T^T underflowed for nodes 1e560 apart
                    t += (T[a, j] * f[j]) * (T[c, j] * f[j])
                P[a, c] = t
        shares[b, 0], shares[b, 1] = np.trace(K[0]) / n, np.trace(K[1]) / n
        if rule == EI:
            W[b, 0], W[b, 1] = shares[b, 0], shares[b, 1]
        gain_mean(means[b], K, shares[b], mean[b])
        if not cholesky(P, L[0]) or not np.isfinite(W[b]).all():
            return NOT_PD
        if not _unscaled(P, L[0], k[b], trace, mean[b], cov[b], obj, b):
            return OVERFLOW
    return OK


@jit
def _outright(ka, kb) -> int:
    """The node whose gain is 1 on every axis (the other's 0): 0 (a), 1 (b), or -1."""
    a = b = True
    for j in range(ka.size):
        a &= ka[j] == 1.0 and kb[j] == 0.0
        b &= kb[j] == 1.0 and ka[j] == 0.0
    return 0 if a else 1 if b else -1


@jit
def _node(m, P, L, k, trace: bool, mean, cov, obj, b) -> bool:
    """A node's own estimate: mean = m, cov = sym(P) as given, obj[b] its criterion (L the
    Cholesky factor of its covariance scaled by 2^-k), as `assemble`'s vertex; False where
    the objective overflows float64."""
    copy(mean, m)
    scaled(P, 1.0, 0, cov)
    if trace:
        obj[b] = np.trace(cov)
    else:
        obj[b] = 2.0 * np.log(np.diag(L)).sum() + P.shape[0] * k * _LN2
    return np.isfinite(obj[b])


@jit
def _unscaled(P, L, k, trace: bool, mean, cov, obj, b) -> bool:
    """cov = sym(P) 2^k in the input's units and obj[b] the criterion at it (L the Cholesky
    factor of P); False where it, or the mean (computed in the input's units), overflows
    float64."""
    scaled(P, 1.0, -k, cov)
    if trace:
        obj[b] = np.ldexp(np.trace(P), k)
    else:
        obj[b] = 2.0 * np.log(np.diag(L)).sum() + P.shape[0] * k * _LN2
    return np.isfinite(obj[b]) and all_finite(cov) and all_finite(mean)


@jit
def _pencil(S, L, M, T, Tinv):
    """P_b = T T^T and P_a = T diag(sigma^2) T^T for S (2, n, n) symmetric positive
    definite: returns sigma (n,) >= 0 (0 where the ratio leaves float64), T and T^-1 into
    the buffers (L (2, n, n) and M (n, n) scratch). sigma are the singular values of
    L_b^-1 L_a (Cholesky factors, lower, in L): with L_b^-1 L_a = U diag(sigma) V^T,
    T = L_b U and T^-1 = U^T L_b^-1."""
    n = S.shape[1]
    for i in range(2):
        if not cholesky(S[i], L[i]):
            return np.zeros(n)
    lower_solve(L[1], L[0], M)  # exactly I for equal covariances (ties stay ties)
    U, sigma, _ = np.linalg.svd(M)
    matmul(L[1], U, T)
    lower_inverse(L[1], M)  # L_b^-1, M free again
    matmul(np.ascontiguousarray(U.T), M, Tinv)
    return sigma


@jit
def _ici_axes(sigma, T, trace: bool, ka, kb, f):
    """ICI's weight (log(1 - w), log w) minimising its criterion (`_ici_bisect`), and per
    axis node a's and b's gains ka, kb and the fused factor f (P = T diag(f^2) T^T):
    p = mu (a + b mu) / (a + b mu^2), K_a = a / (a + b mu^2), K_b = b mu^2 / (a + b mu^2),
    kept in logs (a = 1 - w, b = w, mu = sigma^2)."""
    n = sigma.size
    l, sign, log_gap, log_c = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    for j in range(n):
        l[j] = 2.0 * np.log(sigma[j])  # log mu
        sign[j] = np.sign(1.0 - sigma[j])  # sign of p'(w)
        log_gap[j] = np.log(abs(1.0 - sigma[j])) + np.log1p(sigma[j])  # log |1 - mu|
        log_c[j] = np.log((T[:, j] * T[:, j]).sum())  # tr P = sum_j c_j p_j
    la, lb = _ici_bisect(l, sign, log_gap, log_c, trace)
    for j in range(n):
        g1, g2 = np.logaddexp(la, lb + l[j]), np.logaddexp(la, lb + 2.0 * l[j])
        f[j] = np.exp(0.5 * (l[j] + g1 - g2))
        ka[j], kb[j] = np.exp(la - g2), np.exp(lb + 2.0 * l[j] - g2)
    return la, lb


@jit
def _ei_axes(sigma, ka, kb, f):
    """EI per axis: the smaller variance (f^2), node a's gain 1 or 0 but for the tie rule
    (the loser's share t eta / (1 - t + 2 eta) where the variances tie within 10 eta)."""
    for j in range(sigma.size):
        t = min(sigma[j], 1.0 / sigma[j]) ** 2  # smaller over larger variance
        eta = EI_ETA if 1.0 - t < 10.0 * EI_ETA else 0.0
        lose = t * eta / (1.0 - t + 2.0 * eta)  # 0, or 1/2 at an exact tie
        ka[j] = 1.0 - lose if sigma[j] < 1.0 else lose
        kb[j] = 1.0 - ka[j]
        f[j] = min(sigma[j], 1.0)


@jit
def _gains(T, Tinv, kk, K):
    """K = T diag(kk) T^-1."""
    n = kk.size
    for a in range(n):
        for c in range(n):
            t = 0.0
            for j in range(n):
                t += T[a, j] * kk[j] * Tinv[j, c]
            K[a, c] = t


@jit
def _ici_slope(la: float, lb: float, l, sign, log_gap, log_c, trace: bool) -> float:
    """The sign (and a positive multiple) of f'(w) at a = e^la, b = e^lb, from each axis'
    term in logs: c mu^2 (1 - mu) / (a + b mu^2)^2 ("trace") or
    mu (1 - mu) / ((a + b mu)(a + b mu^2)) ("logdet")."""
    n = l.size
    size = np.empty(n)
    for k in range(n):
        g2 = np.logaddexp(la, lb + 2.0 * l[k])
        if trace:
            size[k] = log_c[k] + 2.0 * l[k] + log_gap[k] - 2.0 * g2
        else:
            size[k] = l[k] + log_gap[k] - np.logaddexp(la, lb + l[k]) - g2
    top = size.max()
    if top == -np.inf:
        return 0.0
    total = 0.0
    for k in range(n):
        total += sign[k] * np.exp(size[k] - top)
    return total


@jit
def _ici_bisect(l, sign, log_gap, log_c, trace: bool):
    """`_ici_weight`'s search, compiled (a bisection of about 60 steps: 0.7 ms a pair in
    numpy calls, to a batch of 200,000 pairs 145 s): the end w = 0 or 1 where f' does not
    change sign, else bisection in u on [-_U_MAX, _U_MAX]."""
    if _ici_slope(0.0, -np.inf, l, sign, log_gap, log_c, trace) >= 0.0:  # w = 0
        return 0.0, -np.inf
    if _ici_slope(-np.inf, 0.0, l, sign, log_gap, log_c, trace) <= 0.0:  # w = 1
        return -np.inf, 0.0
    lo, hi = -_U_MAX, _U_MAX
    while True:
        u = 0.5 * (lo + hi)
        la, lb = -np.logaddexp(0.0, u), -np.logaddexp(0.0, -u)
        if hi - lo <= _EPS or u == lo or u == hi:
            return la, lb
        if _ici_slope(la, lb, l, sign, log_gap, log_c, trace) > 0.0:
            hi = u
        else:
            lo = u


def cross_array(cross, B: int, N: int, n: int, batch: bool) -> np.ndarray:
    """known-cross's cross as a C-contiguous float array (B, N, N, n, n), its shape checked
    by name: (N, N, n, n) for one problem, (B, N, N, n, n) in a batch."""
    if cross is None:
        raise FusionInputError("method 'known-cross' needs cross, the joint covariance "
                               f"blocks ({'B, ' if batch else ''}N, N, n, n)")
    cross = real_array(cross, "cross")
    want = (B, N, N, n, n) if batch else (N, N, n, n)
    if cross.shape != want:
        raise FusionInputError(f"cross must have shape {want}, got {cross.shape}")
    return kernel_array(cross if batch else cross[None])


def _largest_difference(x, y) -> str:
    """max |x - y| as a message shows it; one past float64 (entries near +-1.8e308, fuzz
    L6: "by inf" and an overflow warning) as twice the largest half-difference."""
    half = np.abs(0.5 * x - 0.5 * y).max()
    return f"{2.0 * half:.3g}" if half < 0.5 * np.finfo(float).max else f"2 x {half:.3g}"


def _cross_error(code, where, condition, covs, cross, batch) -> FusionInputError:
    """The FusionInputError of `_check_cross` or of the whitened joint's factorisation."""
    b, i, j = (int(x) for x in where)
    problem = f"problem {b}: " if batch else ""
    if code == CROSS_NONFINITE:
        idx = np.unravel_index(i, cross.shape[1:])
        idx = tuple(int(x) for x in ((b, *idx) if batch else idx))
        value = cross.reshape(-1)[b * cross[0].size + i]
        return FusionInputError(f"cross has a non-finite value {value} at index {idx}")
    if code == CROSS_ASYMMETRIC:
        return FusionInputError(f"{problem}cross is not symmetric: cross[{i}, {j}] differs "
                                f"from cross[{j}, {i}]^T by "
                                f"{_largest_difference(cross[b, i, j], cross[b, j, i].T)}")
    if code == CROSS_DIAGONAL:
        return FusionInputError(f"{problem}cross[{i}, {i}] differs from covs of node {i} by "
                                f"{_largest_difference(cross[b, i, i], covs[b, i])}")
    if code == CROSS_NOT_PD:
        return FusionInputError(f"{problem}cross: the joint covariance is not positive "
                                "definite")
    return FusionInputError(
        f"{problem}cross: the joint covariance, whitened node by node, is numerically "
        f"singular: its condition estimate |C|_1 |R^-1|_1 |R^-1|_inf (C = R R^T; at least "
        f"its condition number), {condition[b]:.3g}, is beyond {MAX_CONDITION:.3g}, the "
        "limit of a single covariance")

@jit
def fuse_known_cross(F, means, covs, cross, k, trace: bool, mean, cov, obj, shares, where,
                     condition) -> int:
    """known-cross on B problems (`compiled` says what the outputs hold), cross
    (B, N, N, n, n) as given, covs and F as `prepare` left them (factors of the covariances
    scaled by 2^-k). Per problem: `_check_cross`; the joint whitened node by node,
    C = D^-1 S D^-T with the identity as diagonal blocks, C = R R^T (Cholesky), refused
    beyond MAX_CONDITION by `_joint_condition`'s estimate, written to condition (B,); the
    thin QR Z = R^-1 [F_1; ...; F_N] = Q U; P = U^-1 U^-T and the gains
    K_i = P (R^-T Z)_i^T F_i (K = P H^T S^-1 = P Z^T R^-1 F, F = blockdiag(F_i): no Q is
    formed, which at n = 100 cost a fifth of the rule). Returns OK, a CROSS_ code
    (where = (problem, i, j), or (problem, flat index into cross[b])), NOT_PD or
    OVERFLOW."""
    B, N, n = means.shape
    m = N * n
    C, R = np.empty((m, m)), np.empty((m, m))
    At, Zt, Vt, G = np.empty((n, m)), np.empty((n, m)), np.empty((n, m)), np.empty((m, n))
    U, Ui, P, L = np.empty((n, n)), np.empty((n, n)), np.empty((n, n)), np.empty((n, n))
    X = np.empty((2, n, n))
    K, u = np.empty((N, n, n)), np.empty((2, n))
    for b in range(B):
        where[0] = b
        code = _check_cross(covs[b], cross[b], k[b], where)
        if code == OK:
            code, condition[b] = _joint(F[b], cross[b], k[b], X, C, R)
        if code != OK:
            return code
        _design(F[b], R, G, At, Zt, Vt, U, Ui, P)
        for i in range(N):
            matmul_t(P, G[i * n:(i + 1) * n], X[0])  # P G_i^T
            matmul(X[0], F[b, i], K[i])
            shares[b, i] = np.trace(K[i]) / n
        _blue_mean(F[b], G, P, means[b], shares[b], u, mean[b])
        if not cholesky(P, L) or not np.isfinite(shares[b]).all():
            return NOT_PD
        if not _unscaled(P, L, k[b], trace, mean[b], cov[b], obj, b):
            return OVERFLOW
    return OK


@jit
def _joint(F, cross, k, X, C, R):
    """(code, condition estimate) of the joint whitened node by node into C (m, m), its
    Cholesky factor into R and R^-1 into C: CROSS_NOT_PD where it is not positive definite
    (or not finite), CROSS_SINGULAR where `_joint_condition` passes MAX_CONDITION."""
    _whitened_joint(F, cross, k, X, C)
    norm1 = _norm1(C)
    if not np.isfinite(norm1) or not _joint_factor(C, R):
        return CROSS_NOT_PD, np.inf
    condition = _joint_condition(norm1, C)
    return (OK if condition <= MAX_CONDITION else CROSS_SINGULAR), condition


@jit
def _norm1(C) -> float:
    """|C|_1 of the symmetric C (m, m): its largest absolute row sum."""
    top = 0.0
    for a in range(C.shape[0]):
        t = 0.0
        for c in range(C.shape[1]):
            t += abs(C[a, c])
        top = max(top, t) if np.isfinite(t) else np.inf
    return top


@jit
def _joint_condition(norm1, Ri) -> float:
    """|C|_1 |R^-1|_1 |R^-1|_inf from norm1 = |C|_1 and R^-1 in the lower triangle of Ri
    (m, m): at least C's condition number |C|_2 |C^-1|_2 (|S|_2 <= |S|_1 for a symmetric S,
    and C^-1 = R^-T R^-1), and, unlike |C|_F |C^-1|_F (at least m for the identity), not
    raised by nodes independent of the others: for a block-diagonal C it is the largest
    of its blocks' (fuzz L7: a pair correlated at 1 - 1e-13 was refused once 30
    independent nodes joined it)."""
    m = Ri.shape[0]
    columns = np.zeros(m)
    rows = 0.0
    for a in range(m):
        t = 0.0
        for c in range(a + 1):
            x = abs(Ri[a, c])
            t += x
            columns[c] += x
        rows = max(rows, t)
    return norm1 * rows * columns.max()


@jit
def _design(F, R, G, At, Zt, Vt, U, Ui, P):
    """With the joint's factor R: the whitened design R^-1 [F_1; ...; F_N] (m, n), its QR's
    U, P = U^-1 U^-T, and G = R^-T R^-1 [F_i] (At, Zt, Vt, Ui scratch)."""
    N, n = F.shape[0], F.shape[1]
    lower_solve(R, F.reshape(N * n, n), G)  # the stacked factors, a view
    for a in range(N * n):
        for c in range(n):
            Zt[c, a] = At[c, a] = G[a, c]
    qr(At, n, N * n, Vt, U)
    upper_inverse(U, Ui)
    for a in range(n):
        for c in range(n):
            t = 0.0
            for d in range(max(a, c), n):
                t += Ui[a, d] * Ui[c, d]
            P[a, c] = t
    lower_t_solve(R, Zt, G)


@jit
def _shifted(m, t, shift, e) -> float:
    """m + t 2^shift; where t 2^shift alone overflows float64 but the sum does not (m and
    t of opposite signs near 1.8e308: fuzz L10), the sum in units of 2^e, e the exponent
    of the largest |mean|. inf only where the result is beyond float64."""
    x = m + np.ldexp(t, shift)
    return x if np.isfinite(x) else np.ldexp(np.ldexp(m, -e) + np.ldexp(t, shift - e), e)


@jit
def _blue_mean(F, G, P, means, shares, u, mean):
    """known-cross's mean m_r + P sum_i G_i^T F_i (m_i - m_r) (r the node of the largest
    gain share; G = R^-T Z, so that P G_i^T F_i = K_i) without forming the gains: a gain
    below float64's range (2^-1100 for a node 2^1100 above another) dropped its node's
    share of the mean, 2^-500 of 2^-499, where the product is in range (fuzz J5). The
    differences in units of 2^e (e the exponent of the largest |mean|) and the sum u
    normalised before P multiplies it, so that nothing overflows or underflows before the
    result; u (2, n) scratch."""
    N, n = means.shape
    r = np.argmax(shares)
    e = math.frexp(np.abs(means).max())[1]
    v, y = u[0], u[1]
    fill(v, 0.0)
    for i in range(N):
        for a in range(n):  # y = F_i (m_i - m_r) 2^-e
            t = 0.0
            for c in range(a + 1):
                t += F[i, a, c] * (np.ldexp(means[i, c], -e) - np.ldexp(means[r, c], -e))
            y[a] = t
        for c in range(n):  # v += G_i^T y
            t = 0.0
            for a in range(n):
                t += G[i * n + a, c] * y[a]
            v[c] += t
    top = np.abs(v).max()
    eu = math.frexp(top)[1] if top > 0.0 and np.isfinite(top) else 0
    for c in range(n):
        y[c] = np.ldexp(v[c], -eu)
    for a in range(n):
        t = 0.0
        for c in range(n):
            t += P[a, c] * y[c]
        mean[a] = _shifted(means[r, a], t, e + eu, e)


@jit
def _joint_factor(C, R) -> bool:
    """R = the Cholesky factor of C (m, m), and C = R^-1 (for the condition estimate);
    False if C is not positive definite to rounding. Above _LAPACK_ABOVE rows the factor
    by LAPACK (numba's np.linalg), whose blocked algorithm is then the faster (22 against
    123 ms at m = 1024), so that known-cross at N = 256 nodes of n = 4 takes about what
    its numpy form took; the inverse by `lower_inverse`'s rows (60 ms there, LAPACK's
    general inverse 70, and 4 s less to compile)."""
    m = C.shape[0]
    if m <= _LAPACK_ABOVE:
        if not cholesky(C, R):
            return False
    else:
        try:
            L = np.linalg.cholesky(C)
        except Exception:  # noqa: BLE001 (numba raises LinAlgError, and catches only this)
            return False
        for a in range(m):
            if not (L[a, a] > 0.0 and np.isfinite(L[a, a])):
                return False
        R[:, :] = L
    lower_inverse(R, C)
    return True


@jit
def _check_cross(covs, cross, k, where) -> int:
    """cross (N, N, n, n) finite; in the units of the covariances scaled by 2^-k, each block
    cross[i, j] within SYMMETRY_RTOL sqrt(s_i s_j) of cross[j, i]^T and each diagonal
    block of covs[i] (s_i the largest diagonal entry of node i: |cross[i, j]| <=
    sqrt(s_i s_j)). where[1:] = (i, j) or (flat index, 0) of a failure."""
    N, n = covs.shape[0], covs.shape[1]
    for t in range(cross.size):
        if not np.isfinite(cross.flat[t]):
            where[1], where[2] = t, 0
            return CROSS_NONFINITE
    root = np.empty(N)
    for i in range(N):
        top = 0.0
        for a in range(n):
            top = max(top, abs(np.ldexp(covs[i, a, a], -k)))
        root[i] = np.sqrt(top)
    for i in range(N):
        for j in range(i, N):
            tol = SYMMETRY_RTOL * root[i] * root[j]
            for a in range(n):
                for c in range(n):
                    x = np.ldexp(cross[i, j, a, c], -k)
                    if abs(x - np.ldexp(cross[j, i, c, a], -k)) > tol:
                        where[1], where[2] = i, j
                        return CROSS_ASYMMETRIC
                    if i == j and abs(x - _sym_pair(covs[i], covs[i], a, c, k)) > tol:
                        where[1], where[2] = i, i
                        return CROSS_DIAGONAL
    return OK


@jit
def _whitened_joint(F, cross, k, X, C):
    """C (N n, N n): block (i, j) = F_i sym(cross)[i, j] F_j^T (cross scaled by 2^-k), the
    diagonal blocks exactly I; X (2, n, n) scratch."""
    N, n = F.shape[0], F.shape[1]
    for i in range(N):
        for a in range(n):
            for c in range(n):
                C[i * n + a, i * n + c] = 1.0 if a == c else 0.0
        for j in range(i + 1, N):
            S, T = X[0], X[1]
            for a in range(n):  # S = sym(cross)[i, j] 2^-k, then T = S F_j^T
                for d in range(n):
                    S[a, d] = _sym_pair(cross[i, j], cross[j, i], a, d, k)
            for a in range(n):
                for c in range(n):
                    t = 0.0
                    for d in range(c + 1):
                        t += S[a, d] * F[j, c, d]
                    T[a, c] = t
            for a in range(n):
                for c in range(n):
                    t = 0.0
                    for d in range(a + 1):
                        t += F[i, a, d] * T[d, c]
                    C[i * n + a, j * n + c] = t
                    C[j * n + c, i * n + a] = t


@jit
def _sym_pair(X, Y, a, c, k) -> float:
    """(X[a, c] + Y[c, a]) / 2 * 2^-k, without overflow for entries near 1.8e308."""
    return 0.5 * np.ldexp(X[a, c], -k) + 0.5 * np.ldexp(Y[c, a], -k)
