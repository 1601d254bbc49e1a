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
    """s (..., N) from p_detect and chi, each a scalar, (N,) or (..., N) with leading batch
    axes (n_nodes fixes N when both are scalars; default 1)."""
    if n_nodes is None:
        shapes = [np.shape(x) for x in (p_detect, chi) if np.ndim(x)]
        n_nodes = shapes[0][-1] if shapes else 1
    p, c = check_detection(p_detect, chi, n_nodes)
    t = p + (1.0 - p) * c  # each node's expected factor, > 0 since chi > 0
    # Product over j != i without dividing by t_i: exclusive prefix times exclusive suffix.
    ones = np.ones((*t.shape[:-1], 1))
    before = np.cumprod(np.concatenate((ones, t[..., :-1]), axis=-1), axis=-1)
    after = np.cumprod(np.concatenate((ones, t[..., :0:-1]), axis=-1), axis=-1)[..., ::-1]
    return p + (1.0 - p) * c * before * after
