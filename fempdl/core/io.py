"""Fields out: XDMF files (ParaView, VisIt) of Functions and of layer tensors.

XDMF stores a field at the mesh's nodes (first-order Lagrange) or per cell
(DG0). Any other field (P2, a Taylor-Hood velocity, a vector P3) is
interpolated into the mesh's first-order Lagrange space of the same value
shape before it is written: its values at the mesh's vertices are kept, what
it does between them is not. A mixed (velocity, pressure) Function has no single
node layout: write its fields (``problem.to_function(x, "u")``, ``"p"``).

Every call writes the mesh once and each field at each time step, under the
field's name, so ParaView shows one array per field with a time slider.
:class:`fempdl.core.time_series.TimeSeries` writes a series one step at a time, as a long
rollout advances (:class:`fempdl.Rollout`'s ``series=``), without keeping the states.
``encoding="ascii"`` puts the values into the .xdmf file itself (one process
only); the default HDF5 encoding writes them beside it (``.h5``).
"""
from __future__ import annotations

import contextlib
import fcntl
import math
import os
import socket
from collections.abc import Mapping, Sequence
from pathlib import Path

import dolfinx.fem
import dolfinx.io
import numpy as np

from fempdl.core import _dolfinx
from fempdl.core.locks import same_file

__all__ = ["write_xdmf", "write_fields", "one_writer", "nodal_field", "plot_fields", "plot_data", "ENCODINGS"]

ENCODINGS = {"hdf5": dolfinx.io.XDMFFile.Encoding.HDF5, "ascii": dolfinx.io.XDMFFile.Encoding.ASCII}


def write_xdmf(path, fields, *, times: Sequence[float] | None = None, encoding: str = "hdf5") -> Path:
    """Write Functions to an XDMF file (time series allowed); returns its path.

    Args:
        path: the ``.xdmf`` file to create (replaced if it exists); the HDF5
            encoding also writes ``path`` with suffix ``.h5``.
        fields: a Function, a sequence of Functions (one time step), or a
            mapping ``{name: Function or sequence of Functions}`` (one Function
            per time step; every sequence as long as ``times``, or a single
            Function, written at every step). Names default to the Functions' own.
        times: the time of each step; ``0, 1, 2, ...`` by default.
        encoding: ``"hdf5"`` (default) or ``"ascii"`` (values inline, serial only).
    """
    if encoding not in ENCODINGS:
        raise ValueError(f"encoding must be one of {list(ENCODINGS)}, got {encoding!r}")
    series = _as_series(fields)
    steps = len(next(iter(series.values())))
    if times is None:
        times = [float(i) for i in range(steps)]
    times = [float(t) for t in times]
    if len(times) != steps or not all(math.isfinite(t) for t in times):
        raise ValueError(f"times must hold {steps} finite values (one per time step of fields), got {times!r}")
    msh = next(iter(series.values()))[0].function_space.mesh
    for name, fns in series.items():
        if any(fn.function_space.mesh is not msh for fn in fns):
            raise ValueError(f"fields[{name!r}] lives on another mesh than the first field; "
                             "write one file per mesh")
    path = Path(path).with_suffix(".xdmf")
    path.parent.mkdir(parents=True, exist_ok=True)
    spaces: dict = {}
    with one_writer(path, msh.comm):
        with dolfinx.io.XDMFFile(msh.comm, str(path), "w", encoding=ENCODINGS[encoding]) as out:
            out.write_mesh(msh)
            for step, t in enumerate(times):
                for name, fns in series.items():
                    out.write_function(nodal_field(fns[step], name, spaces), t)
    return path


@contextlib.contextmanager
def one_writer(path: Path, comm, holder: str = "write_xdmf"):
    """Hold ``path`` for one writer: the ranks of ``comm`` (the mesh's: a distributed mesh is written by
    all of them together) take a kernel lock on a hidden file beside it, and a second writer at the same
    time, e.g. every rank of a data-parallel run writing one file from its own copy of the mesh, gets a
    ValueError instead of a corrupted file. The hidden file names the holder (host, process id,
    ``holder``), so that the refusal can say who holds the path."""
    guard = path.with_name(f".{path.name}.writing")
    fd = refusal = None
    if comm.rank == 0:
        fd = os.open(guard, os.O_RDWR | os.O_CREAT, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            # A writer that just finished unlinked the file this one opened: busy all the same.
            busy = not same_file(fd, guard)
        except BlockingIOError:
            busy = True
        if busy:
            os.close(fd)
            fd = None
            refusal = _busy_message(path, guard)
        else:
            os.ftruncate(fd, 0)
            os.write(fd, f"{socket.gethostname()} {os.getpid()} {holder}".encode())
    refusal = comm.bcast(refusal, root=0)
    if refusal:
        raise ValueError(refusal)
    try:
        yield
    finally:
        if fd is not None:
            guard.unlink(missing_ok=True)
            os.close(fd)


def _busy_message(path: Path, guard: Path) -> str:
    """Why ``path`` cannot be written now, from what its holder wrote into ``guard``."""
    try:
        host, pid, holder = guard.read_text().split(" ", 2)
    except (OSError, ValueError):     # gone, or its holder has not written its name yet
        host = pid = holder = ""
    if host == socket.gethostname() and pid == str(os.getpid()):
        if holder == "TimeSeries":
            return (f"{str(path)!r} is held by a TimeSeries in this process that is still open; close it "
                    "(series.close()) or write it inside `with TimeSeries(...) as series:`, or use another path")
        return f"{str(path)!r} is being written by {holder} in another thread of this process; wait for it or " \
               "use another path"
    who = f" (process {pid} on {host}, {holder})" if pid else ""
    return (f"another process is writing {str(path)!r} at this moment{who}: a TimeSeries there still open on "
            "that path, or every rank of a data-parallel run writing one file?; close that TimeSeries (or use "
            "`with`), write from one rank (rank 0), or give each rank its own path")


def write_fields(path, problem, values: Mapping, *, times: Sequence[float] | None = None,
                 encoding: str = "hdf5") -> Path:
    """Write layer tensors of ``problem`` to an XDMF file; returns its path.

    Args:
        values: ``{label: tensor}`` or ``{label: (name, tensor)}``. A tensor is
            one sample (n,) or a time series (T, n). ``name`` picks its space as
            in :meth:`fempdl.Problem.to_function` (a control, a field of a mixed
            solution, ``None`` for the solution); without it a label that is a
            control or field name uses that space, any other label the solution
            space. A mixed solution is written field by field (``label_u``,
            ``label_p``).
        times, encoding: as in :func:`write_xdmf`.

    Example:
        ``write_fields("out/val.xdmf", prob, {"prediction": u_pred[0], "reference": u_ref[0]})``
    """
    if not isinstance(values, Mapping) or not values:
        raise TypeError(f"values must be a non-empty mapping {{label: tensor}}, got {type(values).__name__}")
    series = {}
    for label, value in values.items():
        if isinstance(value, tuple):
            if len(value) != 2:
                raise ValueError(f"values[{label!r}] must be a tensor or a (name, tensor) pair, got a "
                                 f"tuple of {len(value)}")
            name, value = value
        else:
            known = set(problem.control_names) | set(problem.fields)
            name = label if label in known else None
        steps = value if getattr(value, "ndim", 1) == 2 else [value]
        if name is None and problem.fields:
            for field in problem.fields:
                series[f"{label}_{field}"] = [problem.to_function(v, field) for v in steps]
        else:
            series[label] = [problem.to_function(v, name) for v in steps]
    return write_xdmf(path, series, times=times, encoding=encoding)


def plot_fields(path, problem, values: Mapping, *, title: str | None = None, same_scale=()) -> Path:
    """A PNG of one sample of several fields of a 2D triangle mesh side by side
    (matplotlib ``tripcolor``: P1 nodal values, shaded; DG0 per cell; a vector
    field's magnitude); returns its path. One process only.

    Args:
        values: ``{label: tensor (n,)}`` or ``{label: (name, tensor)}``, the
            spaces picked as in :func:`write_fields` (a mixed solution shows
            its first field, e.g. the velocity).
        same_scale: labels whose panels share one colour range (e.g. a
            prediction and its reference).
    """
    if problem.V.mesh.topology.dim != 2 or problem.V.mesh.comm.size != 1:
        raise ValueError("plot_fields draws 2D meshes on one process; write XDMF (write_fields) for others")
    unknown = sorted(set(same_scale) - set(values))
    if unknown:
        raise ValueError(f"same_scale names {unknown}, which are not labels of values {list(values)}")
    from matplotlib.figure import Figure  # drawn without pyplot: the caller's backend stays as it is

    panels = {label: plot_data(problem, label, value) for label, value in values.items()}
    shared = [panels[label][2] for label in same_scale]
    limits = (min(d.min() for d in shared), max(d.max() for d in shared)) if shared else (None, None)
    fig = Figure(figsize=(4.2 * len(values), 3.8))
    axes = fig.subplots(1, len(values), squeeze=False)
    for ax, (label, (xy, triangles, data, per_cell, vector)) in zip(axes[0], panels.items()):
        vmin, vmax = limits if label in same_scale else (None, None)
        if per_cell:
            art = ax.tripcolor(xy[:, 0], xy[:, 1], triangles, facecolors=data, vmin=vmin, vmax=vmax)
        else:
            art = ax.tripcolor(xy[:, 0], xy[:, 1], triangles, data, shading="gouraud", vmin=vmin, vmax=vmax)
        fig.colorbar(art, ax=ax)
        ax.set_title(label + (" (magnitude)" if vector else ""))
        ax.set_aspect("equal")
        ax.set_axis_off()
    if title:
        fig.suptitle(title)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    return path


def plot_data(problem, label: str, value) -> tuple:
    """What :func:`plot_fields` draws for one field: (xy (N, 3), triangles (T, 3),
    data, per_cell, vector): P1 node values (signed; a vector field's magnitude)
    or, for DG0, one value per triangle."""
    name, value = value if isinstance(value, tuple) else (
        label if label in set(problem.control_names) | set(problem.fields) else None, value)
    if name is None and problem.fields:
        name = next(iter(problem.fields))
    fn = nodal_field(problem.to_function(value, name), label)
    space = fn.function_space
    bs = space.dofmap.index_map_bs
    data = fn.x.array.copy() if bs == 1 else np.linalg.norm(fn.x.array.reshape(-1, bs), axis=1)
    if _is_cellwise(space):
        p1 = _dolfinx.function_space(space.mesh, "Lagrange", 1)
        return (p1.tabulate_dof_coordinates(), _dolfinx.cell_dofs(p1), data[_dolfinx.cell_dofs(space)[:, 0]],
                True, bs > 1)
    return space.tabulate_dof_coordinates(), _dolfinx.cell_dofs(space), data, False, bs > 1


def nodal_field(fn: dolfinx.fem.Function, name: str, spaces: dict | None = None) -> dolfinx.fem.Function:
    """``fn`` as XDMF can store it, named ``name``: itself if it is cell-wise
    constant (DG0) or first-order Lagrange, else its interpolant in the mesh's
    first-order Lagrange space of the same value shape (``spaces`` caches those
    spaces by shape)."""
    space = fn.function_space
    shape = tuple(fn.ufl_shape)
    if space.num_sub_spaces and not (len(shape) == 1 and space.dofmap.index_map_bs == shape[0]):
        raise ValueError(f"field {name!r} is on a mixed space; write its parts instead "
                         "(problem.to_function(x, field) for each field)")
    msh = space.mesh
    if _is_cellwise(space) or _is_vertexwise(space):
        out = dolfinx.fem.Function(space, name=name)
        out.x.array[:] = fn.x.array
        return out
    spaces = {} if spaces is None else spaces
    if shape not in spaces:
        spaces[shape] = _dolfinx.function_space(msh, "Lagrange", 1, shape=shape or None)
    out = dolfinx.fem.Function(spaces[shape], name=name)
    out.interpolate(fn)
    return out


def _is_cellwise(space) -> bool:
    """One value (block) per cell: DG0."""
    cells = space.mesh.topology.index_map(space.mesh.topology.dim).size_global
    return space.dofmap.dof_layout.num_dofs == 1 and space.dofmap.index_map.size_global == cells


def _is_vertexwise(space) -> bool:
    """One value (block) per vertex, shared by the cells around it: P1 on an affine mesh."""
    msh = space.mesh
    return (space.dofmap.dof_layout.num_dofs == _dolfinx.vertices_per_cell(msh)
            and space.dofmap.index_map.size_global == msh.topology.index_map(0).size_global)


def _as_series(fields) -> dict:
    if isinstance(fields, dolfinx.fem.Function):
        fields = [fields]
    if isinstance(fields, Mapping):
        series = {str(k): ([v] if isinstance(v, dolfinx.fem.Function) else list(v)) for k, v in fields.items()}
    elif isinstance(fields, Sequence) and not isinstance(fields, str):
        series = {fn.name: [fn] for fn in fields}
        if len(series) != len(fields):
            raise ValueError("fields has two Functions with the same name; pass {name: Function} instead")
    else:
        raise TypeError(f"fields must be a Function, a sequence or a mapping of Functions, got {type(fields).__name__}")
    if not series:
        raise ValueError("fields is empty; give at least one Function")
    lengths = {name: len(fns) for name, fns in series.items()}
    steps = max(lengths.values())
    if any(n not in (1, steps) for n in lengths.values()):
        raise ValueError(f"every field needs one Function per time step (or one for all steps); got "
                         f"{lengths} Functions")
    series = {name: fns * steps if len(fns) == 1 else fns for name, fns in series.items()}
    for name, fns in series.items():
        for fn in fns:
            if not isinstance(fn, dolfinx.fem.Function):
                raise TypeError(f"fields[{name!r}] must hold dolfinx.fem.Functions, got {type(fn).__name__}")
    return series
