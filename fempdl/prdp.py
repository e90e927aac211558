"""``from fempdl.prdp import PRDP``, the import path of the public API; PRDP lives in :mod:`fempdl.methods.prdp`,
:func:`k_start` (the first cap, measured) in :mod:`fempdl.methods.k_start` and :func:`preflight` (what PRDP
can save in a loop) in :mod:`fempdl.methods.preflight`."""
from fempdl.methods.k_start import k_start
from fempdl.methods.prdp import PRDP, PRDPRecord, PRDPSettings, k_eps
from fempdl.methods.preflight import Preflight, preflight

__all__ = ["PRDP", "PRDPRecord", "PRDPSettings", "Preflight", "k_eps", "k_start", "preflight"]
