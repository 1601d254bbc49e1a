"""Shared, seeded generators of fusion problems for the tests."""

from __future__ import annotations

import multiprocessing
import os

# The tests run in two processes (-n 2 in pyproject.toml) on a 2-core machine: OpenBLAS's
# own threads in each then contend for the same cores, and a small BLAS call (a 4 x 4
# triangular solve, scipy's expm of a 4 x 4) waits for a time slice: 6-15 ms instead of
# microseconds when the machine is busy; test_studies_config.py and test_study_network.py
# took 54-163 s against 19-23 s with one thread each. Set before numpy is first imported
# (pytest loads this file first; the xdist workers inherit it); a user's own setting
# wins. studies/__main__.py does the same for a study's processes.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402
from hypothesis import settings  # noqa: E402

# Property tests draw their examples from a fixed seed, like every other test: a CI run is
# reproducible and cannot fail on an example no earlier run saw.
settings.register_profile("seeded", derandomize=True, database=None)
settings.load_profile("seeded")


def pytest_configure(config):
    """Before any test, processes compile (or load from numba's cache) the library's
    kernels, stage by stage, the parts of a stage at once, as a study's pool does
    (`fusion_opt.core.compile_part`, KERNEL_STAGES): on a machine whose cache is cold,
    each test process (two with the default `-n 2` of pyproject.toml) would otherwise
    compile what its first tests call itself, the same kernels in both. The second stage
    also compiles RBMCDA's association (`_compile`). Not in an xdist worker: the
    controlling process has done it before starting them."""
    if hasattr(config, "workerinput"):
        return
    from fusion_opt.core import KERNEL_STAGES

    stages = (*KERNEL_STAGES[:-1], (*KERNEL_STAGES[-1], "rbmcda"))
    processes = min(max(map(len, stages)), os.cpu_count() or 1)
    with multiprocessing.get_context("fork").Pool(processes) as pool:
        for stage in stages:
            pool.map(_compile, stage, chunksize=1)


def _compile(part: str) -> None:
    """`fusion_opt.core.compile_part`, or for "rbmcda" the trackers' kernel, by one RBMCDA
    step with a measurement (born: birth_prob = 1)."""
    if part != "rbmcda":
        from fusion_opt.core import compile_part

        compile_part(part)
        return
    from trackers import rbmcda, scenarios

    cfg = scenarios.Table2Config()
    m0, P0 = cfg.prior()
    rbmcda.RBMCDA(cfg.filter_model(), m0, P0, rng=np.random.default_rng(0), dt=cfg.dt,
                  birth_prob=1.0).step([[0.0, 0.0]])


def random_spd(rng: np.random.Generator, n: int, log10_range=(-1.0, 1.0)) -> np.ndarray:
    """A random SPD matrix (n, n): random rotation, eigenvalues log-uniform in 10**range."""
    Q, _ = np.linalg.qr(rng.standard_normal((n, n)))
    eig = 10.0 ** rng.uniform(*log10_range, size=n)
    S = (Q * eig) @ Q.T
    return 0.5 * (S + S.T)


def random_instance(rng, n: int, N: int, ill: bool = False):
    """means (N, n) and covs (N, n, n); ill=True spreads eigenvalues over 1e-6 to 1e6."""
    rng_range = (-6.0, 6.0) if ill else (-1.0, 1.0)
    covs = np.stack([random_spd(rng, n, rng_range) for _ in range(N)])
    return rng.standard_normal((N, n)), covs


def objective(covs: np.ndarray, w: np.ndarray, criterion: str) -> np.ndarray:
    """Independent reference: tr or log det of (sum_i w_i P_i^-1)^-1 for w (..., N)."""
    Y = np.einsum("...i,ijk->...jk", w, np.linalg.inv(covs))
    if criterion == "trace":
        return np.trace(np.linalg.inv(Y), axis1=-2, axis2=-1)
    return -np.linalg.slogdet(Y)[1]


def instance(rng: np.random.Generator, N: int, n: int, kind: str) -> np.ndarray:
    """Covariances (N, n, n) of one problem: "random" (P_i = A A^T / n + 0.01 I, A standard
    normal) or "ill-conditioned" (eigenvalues log-uniform over 1e-6..1e6 in a random
    rotation, each node scaled by 10^U(-3, 3))."""
    if kind == "random":
        A = rng.standard_normal((N, n, n))
        return A @ np.swapaxes(A, -1, -2) / n + 0.01 * np.eye(n)
    Q = np.linalg.qr(rng.standard_normal((N, n, n)))[0]
    eig = 10.0 ** rng.uniform(-6, 6, (N, n)) * 10.0 ** rng.uniform(-3, 3, (N, 1))
    P = (Q * eig[:, None, :]) @ np.swapaxes(Q, -1, -2)
    return 0.5 * (P + np.swapaxes(P, -1, -2))


def near_identical(rng: np.random.Generator, n: int, N: int, cond: float = 1e12,
                   eps: float = 1e-6) -> np.ndarray:
    """Covariances (N, n, n) that differ by a relative eps from one base of condition
    `cond` (eigenvalues log-spaced over 1..cond in a random rotation): the hardest family
    for a certificate, since the optimum barely beats the best node."""
    Q = np.linalg.qr(rng.standard_normal((n, n)))[0]
    P = (Q * np.logspace(0, np.log10(cond), n)) @ Q.T
    out = []
    for _ in range(N):
        E = rng.standard_normal((n, n))
        E = E @ E.T / n
        Pi = P + eps * np.linalg.norm(P, 2) * E * 10 ** rng.uniform(-3, 0)
        out.append(0.5 * (Pi + Pi.T))
    return np.array(out)


EXTREME_KINDS = ("random", "ill-conditioned", "diagonal", "near-identical", "commuting")


def extreme_instance(rng: np.random.Generator, N: int, n: int, kind: str, *,
                     log10_cond: float = 12.0, base: float = 0.0,
                     spread: float = 0.0) -> np.ndarray:
    """Covariances (N, n, n) of one hard problem, node i multiplied by 10^(base + u_i) with
    u_i uniform in [-spread/2, spread/2] (so its nodes lie up to 10^spread apart, around
    10^base: 1e-310 gives denormal entries, 1e300 entries near the float range).

    kind: "random" (as `instance`), "ill-conditioned" (each node its own rotation,
    eigenvalues log-uniform over log10_cond decades), "diagonal" (the same, unrotated),
    "near-identical" (`near_identical` at condition 10^log10_cond, relative differences
    10^U(-12, -3)), "commuting" (one rotation for all nodes, eigenvalues log-uniform per
    node and axis: each node best on other axes)."""
    span = (0.0, log10_cond)
    if kind == "random":
        C = instance(rng, N, n, "random")
    elif kind == "ill-conditioned":
        C = np.stack([random_spd(rng, n, span) for _ in range(N)])
    elif kind == "diagonal":
        C = np.stack([np.diag(10.0 ** rng.uniform(*span, n)) for _ in range(N)])
    elif kind == "near-identical":
        C = near_identical(rng, n, N, 10.0 ** log10_cond, 10.0 ** rng.uniform(-12, -3))
    elif kind == "commuting":
        Q = np.linalg.qr(rng.standard_normal((n, n)))[0]
        eig = 10.0 ** rng.uniform(*span, (N, n))
        C = (Q * eig[:, None, :]) @ Q.T
    else:
        raise ValueError(f"unknown kind {kind!r}")
    scale = 10.0 ** (base + rng.uniform(-spread / 2, spread / 2, N))
    C = C * scale[:, None, None]
    return 0.5 * (C + np.swapaxes(C, -1, -2))


def joint(rng, covs, rho):
    """A joint covariance (N, N, n, n) with diagonal blocks exactly covs: blocks
    R_i C_ij R_j^T (R_i R_i^T = P_i) with C PSD, identity diagonal blocks, mixed with I
    (DESIGN §1, "Consistency")."""
    N, n = covs.shape[:2]
    R = np.linalg.cholesky(covs)
    A = rng.standard_normal((N * n, N * n + 2))
    C = (A @ A.T).reshape(N, n, N, n).transpose(0, 2, 1, 3)
    D = np.linalg.inv(np.linalg.cholesky(C[np.arange(N), np.arange(N)]))
    C = np.einsum("iab,ijbc,jdc->ijad", D, C, D)
    C = rho * C + (1 - rho) * np.eye(N)[:, :, None, None] * np.eye(n)
    S = np.einsum("iab,ijbc,jdc->ijad", R, C, R)
    S = 0.5 * (S + S.transpose(1, 0, 3, 2))
    S[np.arange(N), np.arange(N)] = covs
    return S


def config_with(study: str, path: tuple, value) -> dict:
    """The default configuration of a study with the field at `path` (a tuple of keys)
    set to value: a configuration to hand to the study's check."""
    from studies import config as configs

    config = configs.load(study)
    table = config
    for key in path[:-1]:
        table = table[key]
    table[path[-1]] = value
    return config


def tiny_run(tmp_path, study: str, config_text: str, outputs=()):
    """Run `study` from the command line on the configuration config_text, serially and
    quietly, into tmp_path; asserts success and that every file of outputs is non-empty;
    returns the study's folder."""
    from studies.__main__ import main

    cfg = tmp_path / "tiny.toml"
    cfg.write_text(config_text)
    assert main(["run", study, "--config", str(cfg), "--out", str(tmp_path), "--quiet",
                 "--workers", "1"]) == 0
    folder = tmp_path / study
    for name in outputs:
        assert (folder / name).stat().st_size > 0, name
    return folder


def refused_run(tmp_path, capsys, study: str, config_text: str) -> str:
    """Run `study` from the command line on the configuration config_text into tmp_path;
    asserts that it is refused (exit 2) before it writes anything; returns its stderr."""
    from studies.__main__ import main

    cfg = tmp_path / "bad.toml"
    cfg.write_text(config_text)
    assert main(["run", study, "--config", str(cfg), "--out", str(tmp_path)]) == 2
    assert not (tmp_path / study).exists()
    return capsys.readouterr().err
