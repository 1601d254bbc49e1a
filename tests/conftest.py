"""Shared, seeded generators of fusion problems for the tests."""

from __future__ import annotations

import numpy as np
from hypothesis import settings

# Property tests draw their examples from a fixed seed, like every other test: a CI run is
# reproducible and cannot fail on an example no earlier run saw.
settings.register_profile("seeded", derandomize=True, database=None)
settings.load_profile("seeded")


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
