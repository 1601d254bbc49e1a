"""Fusion rules other than optimised CI, for comparison: `RULES[name](means, covs, criterion,
**args) -> RuleOutput` for one problem; the core (`fuse(method=name)`, `fuse_batch`) calls
`compiled` for the rules of COMPILED, a whole batch in one compiled call (`fuse_fixed`,
`fuse_pair`, which the functions of RULES for them call too), and known-cross problem by
problem.

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
  differences scaled by a power of two, so that no product overflows.
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
from scipy.linalg import lapack

from .assemble import all_finite, fuse_at
from .factored import factor, work
from .linalg import cholesky, jit, lower_inverse, lower_solve, matmul
from .prepare import MAX_CONDITION, scaled
from .results import FusionInputError, FusionSolverError, Status
from .validation import SYMMETRY_RTOL, finite_array

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
    """BLUE given cross (N, N, n, n), cross[i, j] = cov(e_i, e_j), cross[i, i] = covs[i].

    With D = blockdiag(D_i), P_i = D_i D_i^T, the joint is S = D C D^T, C = R R^T, and
    Z = R^-1 D^-1 H = Q U (thin QR): P = U^-1 U^-T, K = U^-1 Q^T R^-1 D^-1.
    """
    N, n = means.shape
    Dinv = _factors(covs) if F is None else F  # (N, n, n)
    R = _correlation_factor(cross, covs, Dinv)
    Z = _solve_lower(R, Dinv.reshape(N * n, n))
    Q, U = np.linalg.qr(Z)
    Uinv = _solve_lower(U.T, np.eye(n)).T
    G = _solve_lower(R, Q, transpose=True).reshape(N, n, n)  # R^-T Q by node
    gains = Uinv @ np.swapaxes(G, -1, -2) @ Dinv
    return _finish("known-cross", means, Uinv @ Uinv.T, gains)


def fast_ci(means, covs, criterion, *, F=None) -> RuleOutput:
    """CI with w_i = (1 / tr P_i) / sum_j (1 / tr P_j) (Niehsen 2002; `fuse_fixed`)."""
    return _one("fast-ci", means, covs, criterion, F)


def ifci(means, covs, criterion, *, F=None) -> RuleOutput:
    """CI with the determinant weights of Franken & Hupper (2005), from ratios to det Y
    (`fuse_fixed`)."""
    return _one("ifci", means, covs, criterion, F)


def _one(method, means, covs, criterion, F) -> RuleOutput:
    """A rule of COMPILED on one problem, means (N, n) and covs (N, n, n), called directly
    (the core calls `compiled` on its prescaled batch)."""
    covs = np.array(covs, dtype=float)
    if F is None:  # the pair rules factor the covariances themselves
        F = covs if method in PAIR_ONLY else _factors(covs)
    weights, mean, cov, _, status, are = compiled(
        method, np.array(means, dtype=float)[None], covs[None], np.array(F, dtype=float)[None],
        np.zeros(1, np.int64), criterion == "trace")
    return RuleOutput(weights[0], mean[0], cov[0], status, are)  # checked by the kernel


def compiled(method, means, covs, F, k, trace: bool):
    """Rule `method` of COMPILED on B problems, means (B, N, n) and covs (B, N, n, n), in
    one compiled call; F (B, N, n, n) are the factors of the covariances scaled by 2^-k
    (B,) (`prepare`), which the pair rules do not use: (weights (B, N), mean (B, n),
    cov (B, n, n), the criterion at it (B,), the status, weights_are). Raises
    FusionSolverError where a result is not positive definite to rounding in the scaled
    units, FusionInputError where it overflows float64 in the input's."""
    B, N, n = means.shape
    W, shares, obj = np.empty((B, N)), np.empty((B, N)), np.empty(B)
    mean, cov = np.empty((B, n)), np.empty((B, n, n))
    rule = COMPILED[method]
    if method in PAIR_ONLY:
        code = fuse_pair(rule, means, covs, k, trace, W, mean, cov, obj, shares)
    else:
        code = fuse_fixed(rule, F, means, covs, k, trace, W, mean, cov, obj, shares)
    if code == NOT_PD and method in PAIR_ONLY:
        raise FusionSolverError(method, "numerical_error", "the fused mean or covariance is "
                                "not finite or not positive definite in double precision",
                                role="method")
    if code == NOT_PD:
        raise _not_positive_definite(method)
    if code == RATIO:
        raise FusionSolverError(method, "numerical_error", "the covariances' ratio exceeds "
                                "the double-precision range", role="method")
    if code == OVERFLOW:
        raise FusionInputError(OVERFLOW_MESSAGE)
    status = Status.OPTIMAL if method == "ici" else Status.CLOSED_FORM
    if method in ("naive", "ei"):
        return shares, mean, cov, obj, status, GAIN_SHARES
    return W, mean, cov, obj, status, CI_WEIGHTS


@jit
def fuse_fixed(rule, F, means, covs, k, trace: bool, W, mean, cov, obj, shares) -> int:
    """naive, fast-ci and ifci on B problems (`compiled` says what each array holds): W receives
    the rule's weights (naive: 1; fast-ci: 1 / tr P_i over its sum, from the traces of
    the scaled covariances, whose ratios are the input's; ifci: its scores over their
    sum), then `fuse_at` the estimate. Returns OK, NOT_PD or OVERFLOW."""
    B, N, n = means.shape
    if rule == IFCI and not _ifci_scores(F, W):
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
            return NOT_PD
        for i in range(N):
            W[b, i] /= total
    if not fuse_at(F, means, k, W, trace, mean, cov, obj, shares):
        return NOT_PD
    for b in range(B):
        if not (np.isfinite(obj[b]) and all_finite(mean[b]) and all_finite(cov[b])):
            return OVERFLOW
    return OK


@jit
def _ifci_scores(F, score) -> bool:
    """score (B, N) = 1 - det(Y - Y_i) / det Y + det Y_i / det Y for factors F (B, N, n, n),
    Y = sum_i Y_i = R^T R (the QR of `factored.factor`, weights 1; module docstring):
    1 - prod_k (1 - alpha_k), alpha the squared singular values of F_i R^-1, by log1p and
    expm1, and the triangular diagonals' ratios. False if a Y is not positive definite to
    rounding."""
    N, n = F.shape[1], F.shape[2]
    ws = work(N, n)
    ones, B = np.ones(N), np.empty((n, n))
    for b in range(F.shape[0]):
        if not factor(F[b], ones, ws.At, ws.Vt, ws.R, ws.Ri)[1]:
            return False
        for i in range(N):
            matmul(F[b, i], ws.Ri, B)
            sigma = np.linalg.svd(B)[1]
            kept, own = 0.0, 0.0
            for k in range(n):
                kept += np.log1p(-min(sigma[k] * sigma[k], 1.0))  # -inf where alpha = 1
                own += 2.0 * np.log(abs(F[b, i, k, k] / ws.R[k, k]))
            score[b, i] = -np.expm1(kept) + np.exp(own)
    return True


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
# The rules computed by one compiled call for a whole batch (`compiled`: the CI formula at
# fixed weights by `fuse_fixed`, ici and ei by `fuse_pair`); known-cross takes one problem
# at a time.
NAIVE, FAST_CI, IFCI, ICI, EI = 0, 1, 2, 3, 4
COMPILED = {"naive": NAIVE, "fast-ci": FAST_CI, "ifci": IFCI, "ici": ICI, "ei": EI}
OK, NOT_PD, OVERFLOW, RATIO = 0, 1, 2, 3
OVERFLOW_MESSAGE = ("the fused estimate overflows float64 (covariances or means too large, "
                    "or MBCI scales too small for the result to be represented)")


def _factors(covs):
    """F_i = C_i^-1 (..., N, n, n), lower triangular, C_i C_i^T = P_i: Y_i = F_i^T F_i."""
    return np.linalg.inv(np.linalg.cholesky(covs))


def _solve_lower(L, B, transpose=False):
    """L^-1 B (L^-T B if transpose) for L (m, m) lower triangular, B (m, k), by LAPACK
    (scipy's solve_triangular costs a millisecond a call); NaN if L is singular, which
    `_output` refuses."""
    X, info = lapack.dtrtrs(L, B, lower=1, trans=int(transpose))
    return X if info == 0 else np.full(X.shape, np.nan)


def _finish(method, means, P, gains, status=Status.CLOSED_FORM, weights=None) -> RuleOutput:
    """A rule given by its gains (N, n, n) and P; weights are CI weights if given, else the
    gain shares."""
    shares = np.trace(gains, axis1=-2, axis2=-1) / means.shape[-1]
    mean = np.empty(means.shape[-1])
    gain_mean(np.ascontiguousarray(means, dtype=float), np.ascontiguousarray(gains), shares,
              mean)
    if weights is None:
        return _output(method, shares, mean, P, status, GAIN_SHARES)
    return _output(method, weights, mean, P, status, CI_WEIGHTS)


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
        mean[a] = means[r, a] + np.ldexp(t, e)


def _not_positive_definite(method) -> FusionSolverError:
    return FusionSolverError(method, "numerical_error", "the sum of the informations is not "
                             "positive definite in double precision", role="method")


def _output(method, weights, mean, P, status, weights_are) -> RuleOutput:
    """The result, refused (FusionSolverError) if anything is non-finite or P is not
    positive definite."""
    P = 0.5 * (P + np.swapaxes(P, -1, -2))
    finite = all(np.isfinite(x).all() for x in (weights, mean, P))
    try:
        if finite:
            np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        finite = False
    if not finite:
        raise FusionSolverError(method, "numerical_error",
                                "the fused mean or covariance is not finite or not positive "
                                "definite in double precision", role="method")
    return RuleOutput(weights, mean, P, status, weights_are)


@jit
def fuse_pair(rule, means, covs, k, trace: bool, W, mean, cov, obj, shares) -> int:
    """ICI or EI on B pairs, means (B, 2, n) and covs (B, 2, n, n) (`compiled` says what the
    outputs hold), in the basis of `_pencil`, per axis (module docstring). Returns OK,
    NOT_PD (a result not finite or not positive definite in the scaled units), RATIO (the
    covariances' ratio beyond float64) or OVERFLOW (the result beyond it in the input's)."""
    B, n = means.shape[0], means.shape[2]
    S, L, K = np.empty((2, n, n)), np.empty((2, n, n)), np.empty((2, n, n))
    T, Tinv, P, M = np.empty((n, n)), np.empty((n, n)), np.empty((n, n)), np.empty((n, n))
    ka, kb, f = np.empty(n), np.empty(n), np.empty(n)
    for b in range(B):
        for i in range(2):
            scaled(covs[b, i], 1.0, k[b], S[i])
        sigma = _pencil(S, L, M, T, Tinv)
        if sigma.min() == 0.0:
            return RATIO
        if rule == ICI:
            la, lb = _ici_axes(sigma, T, trace, ka, kb, f)
            W[b, 0], W[b, 1] = np.exp(la), np.exp(lb)  # CI's sense: (1, 0) gives node a
        else:
            _ei_axes(sigma, ka, kb, f)
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
        if not cholesky(P, L[0]) or not all_finite(mean[b]) or not np.isfinite(W[b]).all():
            return NOT_PD
        scaled(P, 1.0, -k[b], cov[b])  # sym(P) 2^k: back to the input's units
        if trace:
            obj[b] = np.ldexp(np.trace(P), k[b])
        else:
            obj[b] = 2.0 * np.log(np.diag(L[0])).sum() + n * k[b] * _LN2
        if not (np.isfinite(obj[b]) and all_finite(cov[b])):
            return OVERFLOW
    return OK


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


def _correlation_factor(cross, covs, Dinv):
    """cross (N, N, n, n) checked, and the Cholesky factor R (N n, N n) of the joint
    whitened node by node, C = R R^T with C[i, j] = D_i^-1 cross[i, j] D_j^-T (identity
    diagonal blocks): well scaled whatever the nodes' scales."""
    N, n = covs.shape[:2]
    cross = finite_array(cross, "cross")
    if cross.shape != (N, N, n, n):
        raise FusionInputError(f"cross must have shape {(N, N, n, n)}, got {cross.shape}")
    # Tolerances per block, from the nodes' own scales (|cross[i, j]| <= sqrt(s_i s_j)).
    root = np.sqrt(np.abs(np.diagonal(covs, axis1=-2, axis2=-1)).max(-1))  # (N,)
    tol = SYMMETRY_RTOL * root[:, None] * root[None, :]
    asym = np.abs(cross - np.swapaxes(cross.transpose(1, 0, 2, 3), -1, -2)).max((-2, -1))
    if (asym > tol).any():
        i, j = np.argwhere(asym > tol)[0]
        raise FusionInputError(f"cross is not symmetric: cross[{i}, {j}] differs from "
                               f"cross[{j}, {i}]^T by {asym[i, j]:.3g}")
    diag = np.abs(cross[np.arange(N), np.arange(N)] - covs).max((-2, -1))
    if (diag > np.diagonal(tol)).any():
        i = int(np.argmax(diag > np.diagonal(tol)))
        raise FusionInputError(f"cross[{i}, {i}] differs from covs of node {i} by "
                               f"{diag[i]:.3g}")
    with np.errstate(over="ignore", invalid="ignore"):  # overflow: refused below
        # by blocks D_i^-1 cross[i, j] D_j^-T, matrix products: a three-operand einsum
        # summed over b and c at once, N^2 n^4 (21 s at N = 8, n = 128, against 0.034 s)
        C = Dinv[:, None] @ cross @ np.swapaxes(Dinv, -1, -2)[None]
    C = 0.5 * (C + np.swapaxes(C.transpose(1, 0, 2, 3), -1, -2))
    C[np.arange(N), np.arange(N)] = np.eye(n)
    C = C.transpose(0, 2, 1, 3).reshape(N * n, N * n)
    try:
        if not np.isfinite(C).all():
            raise np.linalg.LinAlgError
        R = np.linalg.cholesky(C)
    except np.linalg.LinAlgError:
        raise FusionInputError("cross: the joint covariance is not positive definite") \
            from None
    # the limit a single covariance has (prepare.MAX_CONDITION), on the whitened joint
    condition = np.sqrt((C * C).sum()) * (_solve_lower(R, np.eye(N * n)) ** 2).sum()
    if not condition <= MAX_CONDITION:
        raise FusionInputError(
            f"cross: the joint covariance, whitened node by node, is numerically singular: "
            f"its condition estimate |C|_F |C^-1|_F, {condition:.3g}, is beyond "
            f"{MAX_CONDITION:.3g}, as for a single covariance")
    return R
