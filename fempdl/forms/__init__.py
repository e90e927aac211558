"""One module per PDE, each building a :class:`fempdl.Problem` (or a :class:`fempdl.NonlinearProblem`) from UFL forms.

* :mod:`fempdl.forms.poisson` — -div(kappa grad u) = f, controls f, kappa.
* :mod:`fempdl.forms.elasticity` — linear elasticity, controls f (body force), E (Young's modulus).
* :mod:`fempdl.forms.heat` — one theta-step of the heat equation, controls u0, f, kappa.
* :mod:`fempdl.forms.stokes` — steady Stokes flow (Taylor-Hood), control f.
* :mod:`fempdl.forms.oseen` — one Oseen (linearised Navier-Stokes) step, controls w, u_prev, f.
* :mod:`fempdl.forms.burgers` — one linearised vector Burgers step, controls w, u_prev, f.
* :mod:`fempdl.forms.nonlinear_diffusion` — -div(kappa q(u) grad u) = f, steady or one implicit step,
  a :class:`fempdl.NonlinearProblem` (Newton), controls f, kappa, alpha, u0.
* :mod:`fempdl.forms.hyperelasticity` — compressible neo-Hookean finite strain (2D plane strain, 3D),
  a :class:`fempdl.NonlinearProblem` (Newton), controls T (traction), B (body force), E (Young's modulus).
* :mod:`fempdl.forms.navier_stokes` — steady incompressible Navier-Stokes (Taylor-Hood),
  a :class:`fempdl.NonlinearProblem` (Newton), controls f (body force), nu (viscosity field).
* :mod:`fempdl.forms.transport` — one implicit advection-diffusion step of a scalar marker, controls w, m_prev, f.
"""
from fempdl.forms import (
                          burgers,
                          elasticity,
                          heat,
                          hyperelasticity,
                          navier_stokes,
                          nonlinear_diffusion,
                          oseen,
                          poisson,
                          stokes,
                          transport,
)

__all__ = ["burgers", "elasticity", "heat", "hyperelasticity", "navier_stokes", "nonlinear_diffusion", "oseen",
           "poisson", "stokes", "transport"]
