"""``from fempdl.prdp import PRDP``, the import path of the public API; PRDP lives in :mod:`fempdl.methods.prdp`."""
from fempdl.methods.prdp import PRDP, PRDPRecord, PRDPSettings, k_eps

__all__ = ["PRDP", "PRDPRecord", "PRDPSettings", "k_eps"]
