"""What every fempdl problem shares: its spaces, named controls, fields and DOF order.

:class:`ProblemBase` holds the solution space V, the Dirichlet conditions, the
controls (DOLFINx Functions named by the layer's keyword arguments), the fields
of a mixed space, the null spaces and the user's constants, and answers the
questions of the tensor contract: sizes (``output_size``, ``control_size``),
DOF coordinates, ``split``, ``to_function``/``from_function``. The linear
:class:`~fempdl.core.problem.Problem` and the
:class:`~fempdl.core.nonlinear_problem.NonlinearProblem` add their forms.

The module knows DOLFINx and UFL but nothing of torch or of solvers.
"""
from __future__ import annotations

import keyword
import math
from collections.abc import Callable, Mapping
from types import MappingProxyType

from mpi4py import MPI
import dolfinx.fem
import numpy as np
import ufl

from fempdl.core import _dolfinx
from fempdl.core.nullspaces import orthonormal
from fempdl.core.pointwise_forms import coefficients_of, roots_in

__all__ = ["ProblemBase", "validated_controls", "validated_constants", "owned_size", "as_array", "describe_form",
           "count_nonpositive", "nonpositive_control_message"]


#: What a problem is built from: its compiled forms, matrix layout and boundary DOFs follow from these, so a
#: value assigned later would be ignored (or drop matrix entries outside the compiled pattern).
FIXED_AT_BUILD = frozenset({"a", "L", "F", "J", "bcs", "V"})


class ProblemBase:
    """Spaces, controls, fields and DOF order of a problem (see the module docstring).

    Subclasses call :meth:`_init_spaces` from their constructor.
    """

    def __setattr__(self, name: str, value) -> None:
        if name in FIXED_AT_BUILD and name in self.__dict__:
            raise AttributeError(f"problem.{name} is fixed when the problem is built (its forms are compiled and its "
                                 f"matrices laid out from it); build a new {type(self).__name__} with the new {name}, "
                                 "and a layer on it. Values change through the controls, problem.constants and the "
                                 "Functions the forms hold")
        super().__setattr__(name, value)

    def _init_spaces(self, V, bcs, controls: dict, *, fields, nullspace, near_nullspace, constants,
                     positive=(), nonnegative=(), forms=()) -> None:
        """Set V, bcs (checked to be Dirichlet conditions on V), the validated ``controls``, the networks
        (pointwise coefficients) the ``forms`` hold,
        the work Functions ``u`` and ``lam``, BC DOFs, fields, null spaces, constants, the
        controls and Constants that must be positive and the Constants that must be >= 0."""
        self.V = V
        if bcs is None:
            bcs = ()
        elif _dolfinx.is_dirichlet_bc(bcs):
            bcs = (bcs,)         # one condition given bare
        elif not hasattr(bcs, "__iter__"):
            raise TypeError(f"bcs must be a list of dolfinx.fem.dirichletbc, got {type(bcs).__name__}")
        self.bcs = tuple(bcs)
        for i, bc in enumerate(self.bcs):
            if not _dolfinx.is_dirichlet_bc(bc):
                raise TypeError(f"bcs[{i}] must be a dolfinx.fem.dirichletbc, got {type(bc).__name__}")
            if not _dolfinx.bc_on_space(bc, self.V):
                raise ValueError(f"bcs[{i}] is not defined on the solution space (or a subspace of it); "
                                 "create it with the same FunctionSpace")
        self._controls = controls
        self.control_names = tuple(controls)
        networks = roots_in(forms)
        clash = sorted(set(networks) & set(controls))
        if clash:
            raise ValueError(f"the network(s) {clash} have the name of a control; give the network another name=")
        #: ``{name: network}`` of the networks (pointwise coefficients) the forms hold: a layer passes each one's
        #: parameters as a call input under its name (:meth:`refresh_networks` evaluates them).
        self.networks = MappingProxyType(networks)
        self.lam = dolfinx.fem.Function(self.V, name="adjoint")
        imap = self.V.dofmap.index_map
        self._n_owned = imap.size_local * self.V.dofmap.index_map_bs
        self.bc_dofs = _dolfinx.bc_dofs_owned(self.bcs, self._n_owned)
        self._field_spaces = {}
        self.fields = {}
        for name, index in (fields or {}).items():
            space, dofs = _dolfinx.collapsed_subspace(self.V, index)
            self._field_spaces[name] = space
            self.fields[name] = dofs
        self.nullspace = orthonormal(nullspace, "nullspace", self._n_owned, self.V.mesh.comm)
        self.near_nullspace = orthonormal(near_nullspace, "near_nullspace", self._n_owned, self.V.mesh.comm)
        self.constants = MappingProxyType(validated_constants(constants or {}))
        self.positive = positive
        self.nonnegative = nonnegative

    @property
    def input_names(self) -> tuple:
        """The names a layer's call passes tensors for: the controls, then the networks' parameters."""
        return (*self.control_names, *self.networks)

    def refresh_networks(self, strict: bool = True) -> None:
        """Evaluate the networks at the current values of their operands (the state, the controls) and
        parameters, where any of them changed; collective on a distributed mesh. ``strict``: refuse
        non-finite or non-positive values (:meth:`fempdl.core.pointwise.PointwiseCoefficient.refresh`)."""
        for network in self.networks.values():
            network.refresh(strict)

    @property
    def enclosed(self) -> bool:
        """Whether A has a null space (an enclosed flow's pressure constant) that solves project out."""
        return len(self.nullspace) > 0

    # --------------------------------------------------------- control values
    @property
    def positive(self) -> frozenset:
        """Names of the controls and Constants whose values must be > 0 (a diffusivity, a Young's
        modulus, a viscosity, a time step): a layer refuses a call that passes a control value <= 0
        (:meth:`check_control_values`), or is made while such a Constant holds one (:meth:`check_constants`),
        before any solve. Assign ``()`` to solve with such values on purpose."""
        return self._positive

    @positive.setter
    def positive(self, names) -> None:
        self._positive = self._named("positive", names, (*self.control_names, *self.constants))

    @property
    def nonnegative(self) -> frozenset:
        """Names of the Constants whose values must be >= 0 (a stabilisation weight, a Poisson ratio):
        checked like :attr:`positive`'s."""
        return self._nonnegative

    @nonnegative.setter
    def nonnegative(self, names) -> None:
        self._nonnegative = self._named("nonnegative", names, tuple(self.constants))

    @staticmethod
    def _named(what: str, names, allowed: tuple) -> frozenset:
        if isinstance(names, str):
            names = (names,)
        try:
            names = frozenset(names)
        except TypeError:
            raise TypeError(f"{what} must be a collection of names, got {type(names).__name__}") from None
        unknown = sorted(str(n) for n in names - set(allowed))
        if unknown:
            raise ValueError(f"{what} names {unknown}, which are not among this problem's "
                             f"{'controls or Constants' if what == 'positive' else 'Constants'} {list(allowed)}")
        return names

    def check_constants(self, values: Mapping | None = None, *, skip=()) -> None:
        """Refuse a non-finite Constant, or one in :attr:`positive` (> 0) or :attr:`nonnegative` (>= 0)
        whose value breaks its bound, with a ValueError naming it, the value and the fix: the values the
        Constants hold now (but those in ``skip``), or ``values`` (name -> an array of per-step values,
        step first: a rollout's sequence). O(1) per Constant; local (the ranks agree on the Constants
        before: a layer's call check)."""
        names = values if values is not None else [n for n in self.constants if n not in skip]
        for name in names:
            array = np.asarray(values[name] if values is not None else self.constants[name].value, dtype=np.float64)
            strict = name in self._positive
            bad = ~np.isfinite(array)
            if not bad.any() and (strict or name in self._nonnegative):
                bad = array <= 0 if strict else array < 0
            if not bad.any():
                continue
            first = np.unravel_index(int(np.argmax(bad)), array.shape) if array.ndim else ()
            where = "" if values is None else f" at step {first[0]}"
            value = float(array[first])
            if not np.isfinite(value):
                raise ValueError(f"Constant {name!r} is {value:g}{where}; give it a finite value")
            sign = "> 0" if strict else ">= 0"
            raise ValueError(f"Constant {name!r} must be {sign} (problem.{'positive' if strict else 'nonnegative'}), "
                             f"got {value:g}{where}; give it a value {sign}, or take the name out of that set to "
                             "solve with it on purpose")

    def check_control_values(self, name: str, values) -> None:
        """Refuse the values a call passes for control ``name`` (a numpy array or a tensor, any shape:
        this rank's owned DOFs) with a ValueError naming the control, the count of values <= 0 and the
        fix, if ``name`` is in :attr:`positive` and any rank's values have one. O(n); collective on a
        distributed mesh (one allreduce; every rank calls it with the same names); nothing to do for
        other names. NaN values are left to the non-finite check."""
        if name not in self._positive:
            return
        comm = self.V.mesh.comm
        bad, lowest = count_nonpositive(values)
        if comm.size > 1:
            bad = comm.allreduce(bad)
            if bad:             # the count is the same on every rank, so every rank takes this branch
                lowest = comm.allreduce(lowest, op=MPI.MIN)
        if bad:
            raise ValueError(nonpositive_control_message(name, bad, lowest))

    # ------------------------------------------------------------------ sizes
    @property
    def output_size(self) -> int:
        """Number of owned DOF values of the solution on this rank."""
        return self._n_owned

    def control(self, name: str) -> dolfinx.fem.Function:
        """The Function that holds control ``name``."""
        self._check_name(name)
        return self._controls[name]

    def control_size(self, name: str) -> int:
        """Number of owned DOF values a tensor for control ``name`` must have (a network's: its parameter count)."""
        if name in self.networks:
            return self.networks[name].parameter_count
        space = self.control(name).function_space
        return space.dofmap.index_map.size_local * space.dofmap.index_map_bs

    def dof_coordinates(self, name: str | None = None) -> np.ndarray:
        """Coordinates (n_owned, 3) of the owned DOFs of the solution (``name=None``)
        or of control ``name``, in the order tensors use. For a vector (blocked)
        space they are the nodes' coordinates, (n_owned / gdim, 3): tensor entry
        gdim * i + c is component c at node i."""
        space = self.V if name is None else self.control(name).function_space
        n = space.dofmap.index_map.size_local
        return space.tabulate_dof_coordinates()[:n]

    def interpolate(self, expression: Callable[[np.ndarray], np.ndarray], name: str | None = None) -> np.ndarray:
        """Owned DOF values of ``expression`` (x of shape (3, N) -> values (N,))
        interpolated into the solution space or the space of control ``name``."""
        space = self.V if name is None else self.control(name).function_space
        fn = dolfinx.fem.Function(space)
        fn.interpolate(expression)
        n = space.dofmap.index_map.size_local * space.dofmap.index_map_bs
        return fn.x.array[:n].copy()

    def split(self, values) -> dict:
        """The field parts of solution values (..., n) (a tensor or an array):
        ``{name: values[..., fields[name]]}``, each in its collapsed subspace's
        DOF order (so a velocity can be fed back as a control on that space)."""
        if not self.fields:
            raise ValueError("this problem has a single solution space; there is nothing to split")
        if values.shape[-1] != self._n_owned:
            raise ValueError(f"values have {values.shape[-1]} entries in the last dimension, expected "
                             f"{self._n_owned} (problem.output_size)")
        return {name: values[..., dofs] for name, dofs in self.fields.items()}

    def to_function(self, values, name: str | None = None) -> dolfinx.fem.Function:
        """A new Function holding ``values`` (owned DOF values, shape (n,); a
        tensor or an array), ghosts updated, named ``name`` (``"u"`` for the output).

        ``name`` picks the space: a control name (its space; ``control_size``
        values), a field of a mixed solution such as ``"u"`` or ``"p"`` (the
        collapsed subspace; either that field's values, as :meth:`split` gives
        them, or the whole solution), or ``None``/``"u"`` for the solution space
        (``output_size`` values; the whole mixed space for a flow problem).
        Use it to post-process or write a layer's output (:mod:`fempdl.core.io`).
        """
        space, kind = self._space_of(name)
        array = as_array(values, "values")
        n = owned_size(space)
        if kind == "field" and array.shape == (self._n_owned,):
            array = array[self.fields[name]]
        if array.shape != (n,):
            expected = f"({n},)" + (f" or ({self._n_owned},) (the whole solution)" if kind == "field" else "")
            raise ValueError(f"values for {name!r} must have shape {expected} (owned DOFs of its space), got "
                             f"{tuple(array.shape)}; pass one sample (values[i]) of a batch")
        fn = dolfinx.fem.Function(space, name="u" if name is None else name)
        fn.x.array[:n] = array
        fn.x.scatter_forward()
        return fn

    def from_function(self, fn: dolfinx.fem.Function, name: str | None = None) -> np.ndarray:
        """The owned DOF values (n,) (float64) of Function ``fn`` in the space that
        ``name`` picks (as in :meth:`to_function`), the order a layer's tensors use
        (``torch.from_numpy`` makes it a tensor). A Function on another space of
        the same mesh is interpolated into that space first; on the same space
        the values are copied exactly, so ``from_function(to_function(x))`` is x."""
        if not isinstance(fn, dolfinx.fem.Function):
            raise TypeError(f"fn must be a dolfinx.fem.Function, got {type(fn).__name__}")
        space, _ = self._space_of(name)
        if fn.function_space != space:
            if fn.function_space.mesh is not space.mesh:
                raise ValueError(f"fn lives on a different mesh than the space of {name!r}; "
                                 "interpolate it onto this problem's mesh first")
            target = dolfinx.fem.Function(space)
            target.interpolate(fn)
            fn = target
        return np.array(fn.x.array[:owned_size(space)], dtype=np.float64)

    def function_space(self, name: str | None = None):
        """The DOLFINx space a tensor for ``name`` lives in: a control's space, a
        field's collapsed subspace, or (``None``/``"u"``) the solution space."""
        return self._space_of(name)[0]

    def _space_of(self, name: str | None):
        """(space, kind) of ``name``: a control, a field of a mixed solution, or the output."""
        if name is not None and name in self._controls:
            return self._controls[name].function_space, "control"
        if name is not None and name in self._field_spaces:
            return self._field_spaces[name], "field"
        if name is None or name == "u":
            return self.V, "output"
        raise ValueError(f"unknown name {name!r}; use a control {list(self.control_names)}, "
                         + (f"a field {list(self.fields)}, " if self.fields else "")
                         + "or None for the solution space")

    def field_space(self, name: str):
        """The collapsed function space of field ``name``."""
        if name not in self._field_spaces:
            raise ValueError(f"unknown field {name!r}; this problem's fields are {list(self.fields)}")
        return self._field_spaces[name]

    def homogeneous_bcs(self) -> bool:
        """Whether every Dirichlet value is zero (then the RHS has no lifting term)."""
        values = [bc.g.x.array if hasattr(bc.g, "x") else np.asarray(bc.g.value) for bc in self.bcs]
        local = all(not np.any(v) for v in values)
        return self.V.mesh.comm.allreduce(local, op=MPI.LAND)

    def _check_name(self, name: str) -> None:
        if name not in self._controls:
            raise ValueError(f"unknown control {name!r}; this problem's controls are {list(self.control_names)}")


def validated_constants(constants: Mapping) -> dict:
    if not isinstance(constants, Mapping):
        raise TypeError(f"constants must be a mapping name -> dolfinx.fem.Constant, got {type(constants).__name__}")
    for name, value in constants.items():
        if not isinstance(name, str) or not isinstance(value, dolfinx.fem.Constant):
            raise TypeError(f"constants[{name!r}] must be a dolfinx.fem.Constant under a str name, "
                            f"got {type(value).__name__}")
    return dict(constants)


def validated_controls(controls: Mapping, forms: Mapping[str, ufl.Form], msh) -> dict:
    """``controls`` checked: identifier names, Functions on mesh ``msh`` that appear in one of
    ``forms`` ({"a": a, "L": L}: named in the error)."""
    if not isinstance(controls, Mapping):
        raise TypeError(f"controls must be a mapping {{name: dolfinx.fem.Function}}, got {type(controls).__name__}")
    coefficients = set().union(*(coefficients_of(form) for form in forms.values()))
    out = {}
    for name, fn in controls.items():
        if not isinstance(name, str) or not name.isidentifier() or keyword.iskeyword(name):
            raise ValueError(f"control names must be Python identifiers (they become keyword "
                             f"arguments of the layer), got {name!r}")
        if not isinstance(fn, dolfinx.fem.Function):
            raise TypeError(f"controls[{name!r}] must be a dolfinx.fem.Function, got {type(fn).__name__}; "
                            "wrap constants in a Function on a DG0 or P1 space to control them")
        if fn.function_space.mesh is not msh:
            raise ValueError(f"controls[{name!r}] lives on a different mesh than the solution space; "
                             "create it on the same mesh object")
        if fn not in coefficients:
            raise ValueError(f"controls[{name!r}] does not appear in {' or '.join(forms)}; use the same "
                             "Function object when building the forms")
        out[name] = fn
    return out


def count_nonpositive(values) -> tuple[int, float]:
    """(entries <= 0, lowest entry) of ``values`` on this rank: a numpy array or a tensor (read
    through its own ``min`` and comparison, so no conversion), any shape. NaN entries are not
    counted (the non-finite check names them). One pass when every entry is > 0."""
    if hasattr(values, "detach"):
        values = values.detach()
        size = values.numel()
    else:
        values = np.asarray(values)
        size = values.size
    if size == 0:
        return 0, math.inf
    lowest = float(values.min())
    if not lowest <= 0:         # the usual case (a NaN minimum too): no second pass
        return 0, lowest
    return int((values <= 0).sum()), lowest


def nonpositive_control_message(name: str, bad: int, lowest: float) -> str:
    return (f"control {name!r} must be > 0 everywhere (it is in problem.positive: zero or negative values make the "
            f"operator singular or indefinite, and a solve can return garbage without an error), got {bad} "
            f"value(s) <= 0, the lowest {lowest:.6g}; pass a positive map of the network output, e.g. "
            "torch.exp(out) or torch.nn.functional.softplus(out) + a floor, or set problem.positive = () to "
            "solve with such values on purpose")


def owned_size(space) -> int:
    return space.dofmap.index_map.size_local * space.dofmap.index_map_bs


def as_array(values, argname: str) -> np.ndarray:
    """A float64 numpy copy of a tensor (detached, on the CPU) or array-like."""
    if hasattr(values, "detach"):
        values = values.detach().cpu().numpy()
    try:
        return np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"{argname} must be a tensor or an array of numbers, got {type(values).__name__}") from None


def describe_form(form) -> str:
    if isinstance(form, ufl.Form):
        return f"a form with {len(form.arguments())} argument(s)"
    return type(form).__name__

