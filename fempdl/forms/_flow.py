"""Pieces shared by the flow forms (Stokes, Oseen, Burgers): the Taylor-Hood
space and its Problem (fields, enclosed-flow pressure null space), velocity
Dirichlet data per boundary part, vector coefficient Functions, the SUPG
parameter and the Péclet check."""
from __future__ import annotations

import math
import warnings
from collections.abc import Mapping

from mpi4py import MPI
import numpy as np
import ufl

from fempdl.core import _dolfinx
from fempdl.core.checks import is_int
from fempdl.core.mesh import TaggedMesh
from fempdl.core.problem import Problem
from fempdl.forms._common import make_function, positive_constant, tagged_facets

_MAX = MPI.MAX


def vector_function(space, value, name: str):
    """A Function on a vector ``space`` holding ``value``: a float (every
    component), a sequence of gdim floats, or a callable x (3, N) -> (gdim, N)."""
    if isinstance(value, (tuple, list)):
        components = [float(c) for c in value]
        dim = space.dofmap.index_map_bs
        if len(components) != dim or not all(math.isfinite(c) for c in components):
            raise ValueError(f"{name} must have {dim} finite components, got {value!r}")
        column = np.array(components)[:, None]

        def value(x):
            return np.repeat(column, x.shape[1], axis=1)
    return make_function(space, value, name)


def velocity_bcs(tagged: TaggedMesh, W, index: int | None, velocity: Mapping | None, space) -> tuple:
    """Dirichlet conditions for the velocity and whether they close the domain.

    Args:
        W: the solution space; ``index`` the velocity's subspace index in it,
            or ``None`` when W is the velocity space itself.
        velocity: ``{part: value}`` with part a facet tag name or integer (or
            ``None`` for the whole boundary) and value as in :func:`vector_function`
            (0.0 for a no-slip wall). Parts not named are do-nothing
            (traction-free) outflow boundaries.
        space: the (collapsed) velocity space the values live on.

    Returns:
        (bcs, enclosed): ``enclosed`` is True when the Dirichlet parts cover the
        whole boundary (the pressure is then determined up to a constant).
    """
    if velocity is None:
        velocity = {None: 0.0}
    if not isinstance(velocity, Mapping):
        raise TypeError(f"velocity must be a mapping {{boundary part: value}}, got {type(velocity).__name__}")
    boundary = _dolfinx.boundary_facets(tagged.mesh)
    bcs, covered = [], []
    for part, value in velocity.items():
        facets = boundary if part is None else tagged_facets(tagged, (part,))
        fn = vector_function(space, value, f"velocity[{part!r}]")
        bcs.append(_dolfinx.dirichlet_bc(space, fn, facets) if index is None
                   else _dolfinx.dirichlet_bc_on_subspace(W, index, fn, facets))
        covered.append(facets)
    local_uncovered = len(np.setdiff1d(boundary, np.concatenate(covered) if covered else boundary))
    enclosed = tagged.mesh.comm.allreduce(local_uncovered) == 0
    return tuple(bcs), enclosed


def pressure_nullspace(pressure_dofs: np.ndarray, n_owned: int) -> list:
    """The constant-pressure vector (zero velocity) of an enclosed flow."""
    vector = np.zeros(n_owned)
    vector[pressure_dofs] = 1.0
    return [vector]


def supg_tau(msh, w, nu, dt=None):
    """The SUPG parameter per cell (Tezduyar / Shakib et al.):

        tau = ((2/dt)^2 + (2|w|/h)^2 + 9 (4 nu / h^2)^2)^(-1/2),

    h the cell diameter. Written with |w|^2 (no square root), it is a smooth
    function of the advecting velocity w, so its derivative in w exists
    everywhere (w = 0 included)."""
    h = ufl.CellDiameter(msh)
    inverse_square = 4.0 * ufl.dot(w, w) / h ** 2 + 9.0 * (4.0 * nu / h ** 2) ** 2
    if dt is not None:
        inverse_square = inverse_square + (2.0 / dt) ** 2
    return inverse_square ** -0.5


def supg_measure(degree: int):
    """The cell measure for the SUPG terms: quadrature of degree 3k (k the velocity degree).

    Their polynomial part, tau-free, is (w·∇v)·(w·∇u) of degree 3k - 1 (with the
    dt and nu terms lower); UFL would count tau's inverse square root as extra
    degree and pick 4k + 4 (12 for P2: three times the points, most of the
    assembly time of a step). tau varies slowly within a cell, so degree 3k
    integrates the stabilisation as accurately as it is defined."""
    return ufl.dx(metadata={"quadrature_degree": 3 * degree})


def warn_if_convection_dominated(msh, w_fn, nu: float, supg: bool) -> None:
    """Warn when Galerkin without SUPG meets a cell Péclet number |w| h / (2 nu) above 1
    for the given advecting velocity (it then oscillates)."""
    if supg:
        return
    speed = np.linalg.norm(w_fn.x.array.reshape(-1, w_fn.function_space.dofmap.index_map_bs), axis=1)
    h = _dolfinx.cell_diameters(msh)
    comm = msh.comm
    peclet = comm.allreduce(float(speed.max(initial=0.0)), op=_MAX) * comm.allreduce(float(h.max(initial=0.0)),
                                                                                      op=_MAX) / (2.0 * nu)
    if peclet > 1.0:
        warnings.warn(f"cell Péclet number up to {peclet:.3g} > 1 (|w| h / (2 nu) with nu={nu:g}) without "
                      "SUPG: the Galerkin solution will oscillate; pass supg=True or refine the mesh",
                      UserWarning, stacklevel=3)


def taylor_hood(tagged: TaggedMesh, degree, nu, velocity):
    """(W, V, nu Constant, bcs, enclosed): the Taylor-Hood space, its collapsed velocity
    space, the viscosity and the velocity Dirichlet conditions."""
    if not is_int(degree) or degree < 2:
        raise ValueError(f"degree must be an int >= 2 (Taylor-Hood P_k-P_(k-1)), got {degree!r}")
    W = _dolfinx.taylor_hood_space(tagged.mesh, int(degree))
    V, _ = _dolfinx.collapsed_subspace(W, 0)
    nu_c = positive_constant(tagged.mesh, nu, "nu")
    bcs, enclosed = velocity_bcs(tagged, W, 0, velocity, V)
    return W, V, nu_c, bcs, enclosed


def flow_problem(W, a, L, bcs, enclosed, fns, controls, constants) -> Problem:
    """The Problem with fields u, p and, for an enclosed flow, the pressure null space."""
    nullspace = ()
    if enclosed:
        _, p_dofs = _dolfinx.collapsed_subspace(W, 1)
        n_owned = W.dofmap.index_map.size_local * W.dofmap.index_map_bs
        nullspace = pressure_nullspace(p_dofs, n_owned)
    return Problem(a, L, bcs, controls={name: fns[name] for name in controls},
                   fields={"u": 0, "p": 1}, nullspace=nullspace, constants=constants,
                   positive={"nu", "dt"} & set(constants), nonnegative={"grad_div"} & set(constants))
