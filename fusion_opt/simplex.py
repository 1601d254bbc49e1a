"""Weights on the probability simplex {w >= 0, sum w = 1}, exactly in floating point."""

from __future__ import annotations

import numpy as np


def to_simplex(w: np.ndarray) -> np.ndarray:
    """Map near-simplex weights (..., N) from a solver exactly onto the simplex.

    Interior-point solvers return weights a rounding error off the simplex (tiny negatives,
    a sum of 1 +- 1e-12): clip those at 0, renormalise, and give the largest weight the
    remainder 1 - sum(others) so the weights sum to 1 to the last bit.
    """
    w = np.maximum(np.asarray(w, dtype=float), 0.0)
    w = w / w.sum(-1, keepdims=True)
    top = np.argmax(w, axis=-1)[..., None]
    np.put_along_axis(w, top, 0.0, axis=-1)
    rest = w.sum(-1, keepdims=True)
    np.put_along_axis(w, top, 1.0 - rest, axis=-1)
    return w
