"""``from fempdl.prdp import PRDP``, the import path of the public API; PRDP lives in :mod:`fempdl.methods.prdp`,
and :func:`k_start` (the first cap, measured) in :mod:`fempdl.methods.k_start`."""
from fempdl.methods.k_start import k_start
from fempdl.methods.prdp import PRDP, PRDPRecord, PRDPSettings, k_eps

__all__ = ["PRDP", "PRDPRecord", "PRDPSettings", "k_eps", "k_start"]
