"""One module per PDE, each building a :class:`fempdl.Problem` from UFL forms.

* :mod:`fempdl.forms.poisson` — -div(kappa grad u) = f, controls f, kappa.
* :mod:`fempdl.forms.heat` — one theta-step of the heat equation, controls u0, f, kappa.
"""
from fempdl.forms import heat, poisson

__all__ = ["heat", "poisson"]
