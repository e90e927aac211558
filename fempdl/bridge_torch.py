"""``from fempdl.bridge_torch import SolveLayer``, the import path of the public API; the layer lives in
:mod:`fempdl.layer.solve_layer` and its differentiation modes in :mod:`fempdl.layer.system_layer`."""
from fempdl.layer.solve_layer import SolveLayer
from fempdl.layer.system_layer import DIFF_MODES

__all__ = ["SolveLayer", "DIFF_MODES"]
