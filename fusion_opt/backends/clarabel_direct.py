"""Clarabel called directly: the conic programs of `programs.py` without CVXPY.

Clarabel solves  min q^T x  s.t.  A x + s = b,  s in K.  For a scaled problem (Ys (N, n, n),
trace weight M = B B^T (n, n), B its Cholesky factor) with m = n(n+1)/2:

    trace:   x = (w (N), z (m)), z the upper triangle of a symmetric Z (n, n)
             min tr Z  s.t.  1 - sum w = 0,  w >= 0,  [[Z, B^T], [B, Y(w)]] PSD
             (Schur: Z >= B^T Y(w)^-1 B, so tr Z = tr(M P(w)) at the optimum)
    logdet:  x = (w (N), z (m), t (n)), z the upper triangle of an upper-triangular Z
             min -sum t  s.t.  the same simplex rows,  [[diag(Z), Z], [Z^T, Y(w)]] PSD,
             (t_i, 1, Z_ii) in K_exp (e^t_i <= Z_ii)
             (CVXPY's log_det: the PSD block gives det Y >= prod Z_ii, with equality at the
             scaled LDL factor of Y, so max sum t = log det Y(w))

K = {0}^1 x R+^N x S+^2n (x K_exp^n). Clarabel's PSD triangle cone holds svec(X) of
`fusion_opt/svec.py`: the upper triangle column by column, off-diagonals times sqrt(2).
Only the columns of w in A (the Y(w) block) and the B block of b depend on the data: the
sparsity pattern is built once per (n, N, criterion) and a solve only refills values. Each
solve builds a fresh solver (no data update of a previous one), so equal data give
bit-identical results whatever was solved before. Clarabel's settings are `SETTINGS`,
shared with the CVXPY backend "clarabel".
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from functools import cache

import clarabel
import numpy as np
from scipy import sparse

from ..results import FusionSolverError
from ..svec import index as svec_index
from ..svec import scale as svec_scale
from ..svec import upper
from . import WeightSolution, with_attempts

BACKEND = "clarabel-direct"
SETTINGS = {"tol_gap_abs": 1e-10, "tol_gap_rel": 1e-10, "tol_feas": 1e-10, "tol_ktratio": 1e-9,
            "max_iter": 400}
# Chordal decomposition halves the time at n = 12 (measured: 46 against 88 ms at N = 64),
# but on some well-conditioned log-det problems it ends in InsufficientProgress (seen in
# Table 1): a failed solve is tried once more without it.
ATTEMPTS = (SETTINGS, SETTINGS | {"chordal_decomposition_enable": False})
# Clarabel's statuses as CVXPY reports them, so both Clarabel backends fail alike.
STATUS = {"Solved": "optimal", "AlmostSolved": "optimal_inaccurate",
          "PrimalInfeasible": "infeasible", "AlmostPrimalInfeasible": "infeasible_inaccurate",
          "DualInfeasible": "unbounded", "AlmostDualInfeasible": "unbounded_inaccurate",
          "MaxIterations": "user_limit", "MaxTime": "user_limit"}
_OK = ("optimal", "optimal_inaccurate")
_SQRT2 = np.sqrt(2.0)


@dataclass(frozen=True)
class Template:
    """The data of one (n, N, criterion) with placeholders: A = csc(data, indices, indptr)
    of shape `shape` where data[y_pos] receives the Y(w) block values (N*m: node by node,
    each in svec order), b whose rows b_rows receive sqrt(2) B^T (trace only), q, P = 0,
    cones."""

    shape: tuple[int, int]
    data: np.ndarray
    indices: np.ndarray
    indptr: np.ndarray
    y_pos: np.ndarray
    b: np.ndarray
    b_rows: np.ndarray | None
    q: np.ndarray
    P: sparse.csc_matrix
    cones: list


class _Triplets:
    """Entries (row, col, value) of A; value NaN marks a data slot (filled per solve)."""

    def __init__(self):
        self.rows, self.cols, self.vals = [], [], []

    def add(self, rows, cols, vals):
        rows, cols = np.broadcast_arrays(np.asarray(rows), np.asarray(cols))
        self.rows.append(rows.ravel())
        self.cols.append(cols.ravel())
        self.vals.append(np.broadcast_to(np.asarray(vals, dtype=float), rows.shape).ravel())

    def to_csc(self, shape):
        """data, indices and indptr of the CSC matrix (duplicates are not summed)."""
        rows, cols, vals = (np.concatenate(a) for a in (self.rows, self.cols, self.vals))
        order = np.lexsort((rows, cols))
        indptr = np.concatenate([[0], np.cumsum(np.bincount(cols, minlength=shape[1]))])
        data = vals[order]
        return data, rows[order].astype(np.int64), indptr.astype(np.int64)


@cache
def template(n: int, N: int, criterion: str) -> Template:
    """The data of the module docstring for this shape, built on first use."""
    m = n * (n + 1) // 2
    trace = criterion == "trace"
    n_var = N + m + (0 if trace else n)
    psd = 1 + N  # first row of the PSD cone
    n_row = psd + n * (2 * n + 1) + (0 if trace else 3 * n)
    ui, uj = upper(n)
    off = svec_scale(n)
    A = _Triplets()
    A.add(0, np.arange(N), 1.0)  # s = 1 - sum w in {0}
    A.add(1 + np.arange(N), np.arange(N), -1.0)  # s = w >= 0
    # Y(w) block X[n + i, n + j]: one slot per node and entry, valued per solve.
    y_rows = psd + svec_index(n + ui, n + uj)
    A.add(y_rows[None, :], np.arange(N)[:, None], np.nan)
    z_col = N + np.arange(m)
    b = np.zeros(n_row)
    if trace:
        A.add(psd + svec_index(ui, uj), z_col, -off)  # X[:n, :n] = Z
        ii, jj = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")  # X[i, n + j] = B[j, i]
        b_rows = psd + svec_index(ii.ravel(), n + jj.ravel())
        q = np.zeros(n_var)
        q[N + svec_index(np.arange(n), np.arange(n))] = 1.0  # tr Z
        cones = []
    else:
        A.add(psd + svec_index(ui, n + uj), z_col, -_SQRT2)  # X[i, n + j] = Z_ij, i <= j
        diag = N + svec_index(np.arange(n), np.arange(n))  # columns of Z_ii
        A.add(psd + svec_index(np.arange(n), np.arange(n)), diag, -1.0)  # X[i, i] = Z_ii
        exp_row = psd + n * (2 * n + 1) + 3 * np.arange(n)
        A.add(exp_row, N + m + np.arange(n), -1.0)  # (t_i, 1, Z_ii) in K_exp
        A.add(exp_row + 2, diag, -1.0)
        b[exp_row + 1] = 1.0
        b_rows = None
        q = np.concatenate([np.zeros(N + m), -np.ones(n)])
        cones = [clarabel.ExponentialConeT()] * n
    b[0] = 1.0
    data, indices, indptr = A.to_csc((n_row, n_var))
    y_pos = np.flatnonzero(np.isnan(data))  # column by column: node k, then svec order
    data[y_pos] = 0.0
    for a in (data, b, q):  # shared by every solve of the shape: copied, never changed
        a.setflags(write=False)
    return Template((n_row, n_var), data, indices, indptr, y_pos, b, b_rows, q,
                    sparse.csc_matrix((n_var, n_var)),
                    [clarabel.ZeroConeT(1), clarabel.NonnegativeConeT(N),
                     clarabel.PSDTriangleConeT(2 * n), *cones])


def problem_data(Ys: np.ndarray, M: np.ndarray, criterion: str):
    """A (csc), b of the program for Ys (N, n, n), M (n, n), and its template."""
    N, n = Ys.shape[:2]
    tpl = template(n, N, criterion)
    ui, uj = upper(n)
    data = tpl.data.copy()
    # s = svec(X) = b - A x: the Y(w) entries enter A with the opposite sign.
    data[tpl.y_pos] = (Ys[:, ui, uj] * -svec_scale(n)).ravel()
    A = sparse.csc_matrix((data, tpl.indices, tpl.indptr), shape=tpl.shape)
    b = tpl.b
    if tpl.b_rows is not None:
        b = b.copy()
        b[tpl.b_rows] = _SQRT2 * np.linalg.cholesky(M).T.ravel()
    return A, b, tpl


def settings(options: dict) -> clarabel.DefaultSettings:
    s = clarabel.DefaultSettings()
    s.verbose = False
    for key, value in options.items():
        setattr(s, key, value)
    return s


def solve(Ys: np.ndarray, M: np.ndarray, criterion: str) -> WeightSolution:
    """Ys (N, n, n), M (n, n) of a scaled problem; returns weights and solver stats."""
    t0 = time.perf_counter()
    A, b, tpl = problem_data(Ys, M, criterion)

    def once(options) -> WeightSolution:
        try:
            sol = clarabel.DefaultSolver(tpl.P, tpl.q, A, b, tpl.cones, settings(options)).solve()
        except Exception as exc:  # noqa: BLE001 (Clarabel raises bare exceptions on bad data)
            raise FusionSolverError(BACKEND, "solver_error", str(exc)) from None
        raw = str(sol.status)
        status = STATUS.get(raw, "solver_error")
        w = np.array(sol.x[:len(Ys)])
        if status not in _OK or not np.all(np.isfinite(w)):
            raise FusionSolverError(BACKEND, status, f"Clarabel status {raw}")
        return WeightSolution(w, status, int(sol.iterations), time.perf_counter() - t0,
                              sol.solve_time)

    return with_attempts(BACKEND, ATTEMPTS, once)
