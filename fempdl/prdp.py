"""``from fempdl.prdp import PRDP``, the import path of the public API; PRDP lives in :mod:`fempdl.methods.prdp`,
:func:`k_eps` (the converged cap) in :mod:`fempdl.methods.k_eps`, :func:`k_start` (the first cap, measured) in
:mod:`fempdl.methods.k_start`, :func:`preflight` (what PRDP can save in a loop) in
:mod:`fempdl.methods.preflight` and :func:`reference_physics` (converged solves, to judge a model with) in
:mod:`fempdl.layer.reference`."""
from fempdl.layer.reference import reference_physics
from fempdl.methods.k_eps import k_eps, newton_k_eps
from fempdl.methods.k_start import k_start
from fempdl.methods.prdp import PRDP, PRDPGapWarning, PRDPValidationWarning
from fempdl.methods.prdp_settings import PRDPFinish, PRDPRecord, PRDPSettings
from fempdl.methods.preflight import Preflight, preflight

__all__ = ["PRDP", "PRDPFinish", "PRDPGapWarning", "PRDPRecord", "PRDPSettings", "PRDPValidationWarning",
           "Preflight", "k_eps", "k_start", "newton_k_eps", "preflight", "reference_physics"]
