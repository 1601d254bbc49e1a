"""Detection scales of the modified batch CI (MBCI, the paper's Theorem and Lemma).

Node i detects with probability p_i; over a missed detection its covariance grows by
chi_i^-1 >= 1. The expected information of the paper's mixed game scales each Y_i by

    s_i = p_i + (1 - p_i) chi_i prod_{j != i} (p_j + (1 - p_j) chi_j),    0 < s_i <= 1,

and MBCI is CI/BCI on Yhat_i = s_i Y_i (Phat_i = P_i / s_i >= P_i, so it stays consistent).
"""

from __future__ import annotations

import numpy as np

from .validation import check_detection


def detection_scales(p_detect, chi, n_nodes: int | None = None) -> np.ndarray:
    """s (N,) from p_detect and chi, each a scalar or (N,) (n_nodes fixes N for scalars)."""
    p_arr, c_arr = np.asarray(p_detect, dtype=float), np.asarray(chi, dtype=float)
    if n_nodes is None:
        n_nodes = max(p_arr.size, c_arr.size) if p_arr.ndim or c_arr.ndim else 1
    p, c = check_detection(p_detect, chi, n_nodes)
    t = p + (1.0 - p) * c  # each node's expected factor, > 0 since chi > 0
    # Product over j != i without dividing by t_i: exclusive prefix times exclusive suffix.
    before = np.concatenate(([1.0], np.cumprod(t[:-1])))
    after = np.concatenate((np.cumprod(t[::-1][:-1])[::-1], [1.0]))
    return p + (1.0 - p) * c * before * after
