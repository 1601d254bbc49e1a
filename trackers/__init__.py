"""Trackers: Kalman filter, RBPF and RBMCDA, scenario simulators and metrics."""
