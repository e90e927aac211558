"""What a scene would cost and read, checked before anything is built: the mesh file it names, and the
memory its data and network take and the modes its mesh resolves (a bundled mesh by its size at h, a
``.msh`` file by its node count)."""
from __future__ import annotations

from pathlib import Path

from fempdl.app.schema import SceneError
from fempdl.core.resources import GEOMETRIES, estimated_dofs, format_bytes, memory_budget, msh_size

__all__ = ["check_mesh", "check_size", "estimated_memory"]


def check_mesh(mesh: dict, source: str, base: Path | None) -> None:
    """A mesh that is not bundled must be an existing ``.msh`` file (a relative path is taken from
    ``base``, the scene file's folder, when given); ``mesh["name"]`` becomes its path; ``h`` is for
    bundled meshes only."""
    name = mesh["name"]
    if name in GEOMETRIES:
        return
    path = Path(name)
    if not path.is_absolute() and base is not None:
        path = base / path
    if path.suffix != ".msh":
        raise SceneError(f"{source}: [mesh] name {name!r} is neither a bundled mesh {sorted(GEOMETRIES)} nor a "
                         "gmsh .msh file")
    if not path.is_file():
        where = " (a relative path is read from the scene file's folder)" if base is not None else ""
        raise SceneError(f"{source}: [mesh] name {name!r}: no such file {str(path)!r}{where}; bundled meshes are "
                         f"{sorted(GEOMETRIES)}")
    if mesh["h"] is not None:
        raise SceneError(f"{source}: [mesh] h applies to bundled meshes only, got h = {mesh['h']} with the file "
                         f"{name!r}; mesh the file's geometry at that size with gmsh, or remove h")
    mesh["name"] = str(path)


def estimated_memory(values: dict) -> tuple[float, float, dict] | None:
    """(bytes, DOFs, dimension, parts) a scene's data and network take, estimated before anything is
    built; None for a mesh file whose header gives no node count (a binary one). Parts: ``data``
    (float64 states and their float32 copies), ``network`` (parameters, gradients and two Adam
    moments), by the bundled mesh's size at h or the file's node count."""
    name, h = values["mesh"]["name"], values["mesh"]["h"]
    pde = values["pde"]
    degree = pde["degree"] or 1
    if name in GEOMETRIES:
        dim = GEOMETRIES[name].dim
        components = dim if pde["type"] in ("burgers", "oseen") else 1
        dofs = estimated_dofs(name, h if h is not None else _BUNDLED_H[name], degree, components)
    else:
        size = msh_size(name)
        if size is None:
            return None
        nodes, dim = size
        dofs = nodes * degree ** dim * (dim if pde["type"] in ("burgers", "oseen") else 1)
    data, network = values["data"], values.get("network")
    parts = {}
    if data["train"] is not None:          # tasks with a data set (the inverse task has one fixed sample)
        samples = data["train"] + data["validation"]
        # A rollout keeps 2 rollout + 1 states per sample (emulator, hybrid), an inversion its (x, y) pair.
        states = 2 * data["rollout"] + 1 if data["rollout"] is not None else 2
        parts["data"] = samples * dofs * states * 12.0
    if network is not None:
        width, depth = network["hidden"], network["layers"]
        weights = 2 * dofs * width + depth * width ** 2 if network["type"] == "mlp" else depth * width ** 2
        parts["network"] = weights * 8.0 * 4
    return sum(parts.values()), dofs, dim, parts


# The committed meshes' sizes (fempdl.core.meshgen.DEFAULT_H), for the estimate of a scene without h.
_BUNDLED_H = {"lshape": 0.05, "obstacle": 0.035, "box": 0.1}


def check_size(values: dict, source: str) -> None:
    """Refuse a scene whose data and network would not fit in the memory budget, or whose number of
    smooth modes exceeds what the mesh resolves, with the estimate."""
    estimate = estimated_memory(values)
    if estimate is None:
        return
    total, dofs, dim, parts = estimate
    budget = memory_budget()
    if total > budget:
        split = ", ".join(f"{part} {format_bytes(size)}" for part, size in parts.items())
        raise SceneError(f"{source}: the scene needs about {format_bytes(total)} ({split}; about {dofs:.3g} DOFs), "
                         f"more than the memory budget of {format_bytes(budget)} (half the available memory); "
                         "reduce [data] train and validation, [network] hidden and layers, or refine the mesh less")
    modes = values["data"]["modes"]
    most = max(4 * dofs, 1000)      # generous: the DOF estimate of a coarse mesh is rough
    if modes is not None and values["data"]["truths"] in (None, "smooth") and modes ** dim > most:
        raise SceneError(f"{source}: [data] modes = {modes} gives {modes}^{dim} sine modes, far more than the "
                         f"mesh's about {dofs:.3g} DOFs resolve; use at most {int(most ** (1.0 / dim))}")
