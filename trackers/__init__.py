"""Trackers: Kalman filter, RBPF and RBMCDA, scenario simulators and metrics.

Each filter steps one scan at a time (``kalman.KalmanFilter``, ``rbpf.RBPF``,
``rbmcda.RBMCDA``: ``.step(scan, time=None) -> fusion_opt.Estimates``) over a pure step
function, and ``run(scans, ...)`` loops over the steps. The filters check every input
and result; the pure step functions (``kalman.predict``, ``update``, ...) are their
unchecked numerical core, for callers that checked their data (``kalman``'s docstring).
Data flows one way: these produce estimates; ``fusion_opt`` fuses them; ``studies``
drives both. Trackers use fusion_opt's ``Estimates``, ``FusionInputError`` and input
checks, and nothing of ``studies``.
"""

from trackers import kalman, metrics, models, rbmcda, rbpf, resampling, scenarios

__all__ = ["kalman", "metrics", "models", "rbmcda", "rbpf", "resampling", "scenarios"]
