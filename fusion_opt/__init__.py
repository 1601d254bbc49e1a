"""fusion-opt: distributed data fusion as convex optimisation.

    import fusion_opt as fo
    r = fo.bci(means, covs, criterion="trace")      # means (N, n), covs (N, n, n)
    r.weights, r.mean, r.cov, r.objective, r.gap

Covariance intersection (CI), batch CI (BCI) and the detection-aware modified BCI (MBCI)
of Daeichian & Honarvar (2018), each a convex program over the weight simplex, solved
exactly by a compiled Newton method (or by Clarabel, the conic reference), with an
optimality certificate on every result; and the network they serve: `Estimates`,
`associate`, `ProcessingNode`, `Network`.
"""

from .association import Group, associate
from .backends import BACKENDS
from .batch import fuse_batch
from .detection import detection_scales
from .estimates import Estimates
from .fusion import bci, ci, fuse, mbci, optimality_gap, warmup
from .limits import limits
from .network import Network
from .processing import ProcessingNode
from .results import BatchFusionResult, FusionInputError, FusionResult, FusionSolverError, Status

__all__ = [
    "BACKENDS", "BatchFusionResult", "Estimates", "FusionInputError", "FusionResult",
    "FusionSolverError", "Group", "Network", "ProcessingNode", "Status", "associate", "bci",
    "ci", "detection_scales", "fuse", "fuse_batch", "limits", "mbci", "optimality_gap",
    "warmup",
]
