"""Trackers: Kalman filter, RBPF and RBMCDA, scenario simulators and metrics.

Data flows one way: these produce estimates; ``fusion_opt`` fuses them; ``studies`` drives
both. Nothing here imports ``fusion_opt`` or ``studies``.
"""

from trackers import kalman, metrics, models, rbmcda, rbpf, resampling, scenarios

__all__ = ["kalman", "metrics", "models", "rbmcda", "rbpf", "resampling", "scenarios"]
