"""Scenes: TOML files that declare a training experiment, parsed into a validated :class:`Scene`.

:func:`parse` is the one place that validates: against the schema (:mod:`fempdl.app.schema`: every
section's keys, types, defaults, choices and bounds) and the task registry (:mod:`fempdl.app.tasks`:
the sections, PDEs and keys each task takes). A malformed scene raises :class:`SceneError` naming
the key and what is allowed. :func:`schema_text` renders both (``fempdl scenes --schema``). Bundled
scenes live in ``fempdl/app/scenes/``; :func:`load` takes a bundled name or a path.
"""
from __future__ import annotations

import math
import tomllib
from importlib import resources
from pathlib import Path

from fempdl.app.scene_budget import check_mesh, check_size
from fempdl.app.schema import (
    NONLINEAR_PDES,
    PDE_UNUSED,
    POSITIVE,
    REQUIRED,
    SECTIONS,
    Scene,
    SceneError,
    Spec,
    check_slug,
    specs,
)
from fempdl.app.tasks import SPECS

# The presets of a Newton step's inner solve: LU or a Krylov method for a nonsymmetric Jacobian (no cg).
NEWTON_PRESETS = ("lu", "jacobi", "gmres", "gmres-ilu")

__all__ = ["Scene", "SceneError", "load", "available", "bundled_text", "parse", "schema_text"]


def unused_keys(task: str, pde: str) -> dict[str, frozenset]:
    """The keys, by section, that ``task`` and PDE type ``pde`` do not use."""
    out: dict[str, frozenset] = {}
    for by_section in (SPECS[task].unused, PDE_UNUSED.get(pde, {})):
        for name, keys in by_section.items():
            out[name] = out.get(name, frozenset()) | keys
    return out


def schema_text() -> str:
    """The schema as text: every section (and the tasks that take it), key, type, default, choices, bounds and doc."""
    lines = ["Scene files (TOML): sections and keys. A key a task or PDE does not use is refused.",
             "Tasks ([scene] task) and the PDEs they take: "
             + "; ".join(f"{task} ({', '.join(spec.pdes)})" for task, spec in SPECS.items()), ""]
    for name, cls in SECTIONS.items():
        tasks = [task for task, spec in SPECS.items() if name in spec.sections]
        needed = [task for task, spec in SPECS.items() if name in spec.required]
        usage = "every task" if len(tasks) == len(SPECS) else ", ".join(tasks)
        if needed and needed != tasks:
            usage += f"; required for {', '.join(needed)}"
        elif needed:
            usage += "; required"
        lines.append(f"[{name}]  {cls.__doc__.splitlines()[0].partition(': ')[2].rstrip('.')} ({usage})")
        lines.extend(f"  {key:<19}{_describe(spec)}" for key, spec in specs(name).items())
        lines.append("")
    return "\n".join(lines)


def _describe(spec: Spec) -> str:
    """One key's line of :func:`schema_text`: type, default, choices, bounds, doc."""
    kind = "list of numbers" if spec.kind is list else spec.kind.__name__
    if spec.required:
        default = "required"
    else:
        default = "default " + _toml(spec.default)
    parts = [kind, default]
    if spec.choices is not None:
        parts.append("one of " + " | ".join(f'"{c}"' for c in spec.choices))
    if spec.minimum is not None:
        parts.append("> 0" if spec.minimum == POSITIVE else f">= {_bound(spec.minimum)}")
    if spec.maximum is not None:
        parts.append(f"<= {_bound(spec.maximum)}")
    return ", ".join(parts) + f": {spec.doc}"


def _bound(value) -> str:
    """A key's bound as written: an int in full (a seed's 2^63 - 1 in %g would read 9.22337e+18)."""
    return str(value) if isinstance(value, int) else f"{value:g}"


def _toml(value) -> str:
    """``value`` as TOML writes it (``none``: the key is left out)."""
    if value is None:
        return "none"
    if isinstance(value, bool):
        return str(value).lower()
    return f'"{value}"' if isinstance(value, str) else repr(value)


def available() -> list[str]:
    """Names of the bundled scenes."""
    return sorted(p.name[:-5] for p in resources.files("fempdl.app.scenes").iterdir() if p.name.endswith(".toml"))


def bundled_text(name: str) -> str:
    """The TOML text of bundled scene ``name`` (a start for a scene of your own)."""
    if name not in available():
        raise SceneError(f"unknown scene {name!r}; bundled scenes are {available()}")
    return resources.files("fempdl.app.scenes").joinpath(f"{name}.toml").read_text()


def load(name_or_path, overrides=()) -> Scene:
    """A bundled scene by name, or any scene file by path.

    ``overrides``: ``"section.key=value"`` strings applied to the file's values
    before validation (the command line's ``--set``); ``value`` is a TOML value
    (``5``, ``1e-3``, ``true``, ``"cg"``, ``[1, 2]``), and text that is no TOML
    value is taken as a string (``solver.preset=cg``).
    """
    if not isinstance(name_or_path, (str, Path)):
        raise TypeError(f"scene must be a bundled name or a path, got {type(name_or_path).__name__}")
    path = Path(name_or_path)
    if path.suffix != ".toml":
        if str(name_or_path) not in available():
            raise SceneError(f"unknown scene {str(name_or_path)!r}; bundled scenes are {available()}, "
                             "or pass a path to a .toml file")
        return parse(bundled_text(str(name_or_path)), source=f"bundled:{name_or_path}", overrides=overrides)
    if not path.is_file():
        raise FileNotFoundError(f"scene file {str(path)!r} does not exist")
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as err:
        raise SceneError(f"{path}: not a UTF-8 text file (byte {err.start}: {err.reason}); "
                         "TOML scene files are UTF-8: save it as UTF-8") from None
    # A relative mesh path in the file is read from the file's folder; one given by --set from the
    # current directory.
    mesh_set = any(str(item).partition("=")[0].strip() == "mesh.name" for item in
                   ((overrides,) if isinstance(overrides, str) else overrides))
    return parse(text, source=str(path), overrides=overrides, base=None if mesh_set else path.parent)


def parse(text: str, source: str = "<string>", overrides=(), base: Path | None = None) -> Scene:
    """Validate TOML text, with ``overrides`` applied (see :func:`load`), as a scene.

    Unknown sections or keys, keys that do not apply to the task or PDE, wrong
    types, out-of-range values and missing required keys raise :class:`SceneError`;
    values are data, strings are never evaluated. A scene whose data and network
    would not fit in half the available memory (:func:`estimated_memory`), or that
    asks for more sine modes than the mesh resolves, is refused with the estimate.
    The cap K of a run is no part of a scene: it is chosen per run."""
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise SceneError(f"{source}: not valid TOML: {err}") from None
    _apply_overrides(raw, overrides, source)
    unknown = sorted(set(raw) - set(SECTIONS))
    if unknown:
        raise SceneError(f"{source}: unknown section(s) {unknown}; allowed sections are {sorted(SECTIONS)}")
    if "scene" not in raw:
        raise SceneError(f"{source}: missing section [scene] (with name and task)")
    header = _section(raw, "scene", source)
    try:
        check_slug(header["name"], "[scene] name")
    except ValueError as err:
        raise SceneError(f"{source}: {err}") from None
    task = header["task"]
    if task not in SPECS:
        raise SceneError(f"{source}: [scene] task must be one of {list(SPECS)}, got {task!r}")
    spec = SPECS[task]
    values = _task_sections(raw, task, source)
    check_mesh(values["mesh"], source, base)
    pde = values["pde"]
    unused = unused_keys(task, pde["type"])
    _drop_unused(values, raw, task, source)
    if pde["type"] not in spec.pdes:
        raise SceneError(f"{source}: [pde] type {pde['type']!r} does not apply to task {task!r}; "
                         f"it takes {list(spec.pdes)}")
    if spec.trains == "method":
        _check_method(values, raw, source)
    else:
        _check_flow(values, source)
        _check_solver(values, raw, source)
    if "inverse" in values:
        _check_inverse(values["inverse"], source)
    check_size(values, source)
    sections = {name: SECTIONS[name](**values[name]) if name in values else None
                for name in SECTIONS if name != "scene"}
    return Scene(name=header["name"], task=task, description=header["description"], source=source,
                 unused=unused, **sections)


def _task_sections(raw: dict, task: str, source: str) -> dict[str, dict]:
    """The checked keys (defaults filled in) of every section ``task`` takes; refuses missing and extra sections."""
    spec = SPECS[task]
    missing = sorted(spec.required - set(raw))
    if missing:
        raise SceneError(f"{source}: task {task!r} needs section(s) {missing}")
    extra = sorted(set(raw) - spec.sections)
    if extra:
        raise SceneError(f"{source}: section(s) {extra} do not apply to task {task!r}; "
                         f"allowed: {sorted(spec.sections)}")
    return {name: _section(raw, name, source) for name in SECTIONS if name in spec.sections}


def _drop_unused(values: dict, raw: dict, task: str, source: str) -> None:
    """Refuse keys the task or PDE does not use when the file gives them; set them to None otherwise."""
    pde = values["pde"]["type"]
    for what, value, unused in (("task", task, SPECS[task].unused), ("pde", pde, PDE_UNUSED.get(pde, {}))):
        for name, keys in unused.items():
            given = sorted(keys & set(raw.get(name, {})))
            if given:
                raise SceneError(f"{source}: [{name}] {', '.join(given)} do(es) not apply to {what} {value!r}; "
                                 "remove them")
            for key in keys:
                if name in values:
                    values[name][key] = None


def _check_solver(values: dict, raw: dict, source: str) -> None:
    """The choices across [solver] and [prdp] of the tasks with a capped solver."""
    solver = values["solver"]
    if values["pde"]["type"] in NONLINEAR_PDES:
        _check_newton(solver, raw.get("solver", {}), source)
    elif solver["preset"] == "lu":
        raise SceneError(f"{source}: [solver] preset 'lu' has no iteration cap: it is the converged inner solve of "
                         f"a Newton layer (pde {list(NONLINEAR_PDES)}); choose jacobi, cg, gmres or gmres-ilu")
    elif solver["diff"] == "unrolled" and solver["preset"] not in ("jacobi", "cg"):
        raise SceneError(f"{source}: [solver] diff = 'unrolled' needs preset 'jacobi' or 'cg', "
                         f"got {solver['preset']!r}")
    prdp = values["prdp"]
    if prdp["k_cap"] is not None and prdp["k_cap"] < prdp["k0"]:
        raise SceneError(f"{source}: [prdp] k_cap must be >= k0 ({prdp['k0']}), got {prdp['k_cap']}")


def _check_newton(solver: dict, given: dict, source: str) -> None:
    """[solver] of a Newton layer: ``refine`` says what K caps, and the inner solve must fit it."""
    refine = solver["refine"]
    if solver["preset"] not in NEWTON_PRESETS:
        raise SceneError(f"{source}: [solver] preset {solver['preset']!r} does not fit a Newton step: the Jacobian of "
                         "kappa (1 + alpha u^2) grad u is not symmetric (its 2 alpha u grad u term); choose "
                         f"{', '.join(NEWTON_PRESETS[:-1])} or {NEWTON_PRESETS[-1]}")
    if refine != "newton" and solver["preset"] == "lu":
        raise SceneError(f"{source}: [solver] refine = {refine!r} caps the inner Krylov iterations, but preset 'lu' "
                         f"solves each Newton step directly; choose an iterative preset "
                         f"({', '.join(NEWTON_PRESETS[1:])}) or refine = 'newton'")
    if "inner_per_k" in given and refine != "both":
        raise SceneError(f"{source}: [solver] inner_per_k applies to refine = 'both' (K Newton steps of "
                         f"inner_per_k K inner iterations), not {refine!r}; remove it")
    if solver["diff"] == "unrolled" and refine != "newton":
        raise SceneError(f"{source}: [solver] diff = 'unrolled' differentiates exact Newton steps: it needs "
                         f"refine = 'newton' (a converged inner solve), got {refine!r}")


def _check_flow(values: dict, source: str) -> None:
    """Fill the per-PDE degree default and check the choices that depend on the PDE."""
    pde, solver, network = values["pde"], values["solver"], values.get("network")
    flow = pde["type"] in ("burgers", "oseen")
    if pde["degree"] is None:
        pde["degree"] = 2 if pde["type"] == "oseen" else 1
    if pde["type"] == "oseen" and pde["degree"] < 2:
        raise SceneError(f"{source}: [pde] degree must be >= 2 for oseen (Taylor-Hood P_k-P_(k-1)), "
                         f"got {pde['degree']}")
    if (pde["type"] == "oseen") != (solver["preset"] == "schur"):
        raise SceneError(f"{source}: [solver] preset 'schur' is the saddle-point solver: oseen needs it and "
                         f"other PDEs cannot use it (pde {pde['type']!r}, preset {solver['preset']!r})")
    if flow and network is not None and network["type"] != "mlp":
        raise SceneError(f"{source}: [network] type {network['type']!r} works on scalar fields; "
                         f"{pde['type']} states are vector fields: use 'mlp'")
    if network is not None and network["type"] == "graph" and network["layers"] < 1:
        raise SceneError(f"{source}: [network] layers must be >= 1 for a graph network (its layers are the "
                         f"graph convolutions; with none no node sees its neighbours), got {network['layers']}")


def _check_method(values: dict, raw: dict, source: str) -> None:
    """The SIP / HIG scenes: degree default, an MLP, the inverse's keys, the baseline's learning rate and decay."""
    pde, network = values["pde"], values["network"]
    if pde["degree"] is None:
        pde["degree"] = 2 if pde["type"] == "marker" else 1
    _check_marker(values, raw, source)
    if network["type"] != "mlp":
        raise SceneError(f"{source}: [network] type must be 'mlp' for the {values['scene']['task']} task "
                         f"(a dense network from the observation to the source), got {network['type']!r}")
    sip = values.get("sip")
    if sip is not None and pde["type"] in NONLINEAR_PDES and sip["inverse"] != "exact":
        raise SceneError(f"{source}: [sip] inverse must be 'exact' for {pde['type']} (f = M^-1 N(u): the source "
                         f"from the residual of the nonlinear operator, no PDE solve), got {sip['inverse']!r}")
    if sip is not None:
        unused = {"exact": {"damping", "cg_iterations"}, "tikhonov": {"cg_iterations"}}.get(sip["inverse"], set())
        given = sorted(unused & set(raw["sip"]))
        if given:
            raise SceneError(f"{source}: [sip] {', '.join(given)} do(es) not apply to inverse {sip['inverse']!r} "
                             "(cg_iterations sets the Gauss-Newton inverse, damping the damped ones); remove "
                             "them or choose another inverse")
    baseline = values["baseline"]
    for key, hig_default in (("lr", 1e-3), ("decay", 1.0)):
        if baseline[key] is None:
            baseline[key] = values["optimizer"][key] if sip is not None else hig_default


def _check_marker(values: dict, raw: dict, source: str) -> None:
    """[marker] belongs to the marker PDE (elsewhere it is dropped, or refused if given); it needs
    Taylor-Hood (degree >= 2) and the Gauss-Newton inverse (the physics is nonlinear)."""
    if values["pde"]["type"] != "marker":
        if "marker" in raw:
            raise SceneError(f"{source}: [marker] applies to [pde] type 'marker' only; remove it")
        values.pop("marker", None)
        return
    if values["pde"]["degree"] < 2:
        raise SceneError(f"{source}: [pde] degree must be >= 2 for marker (the Taylor-Hood velocity P_k-P_(k-1)), "
                         f"got {values['pde']['degree']}")
    if values["sip"]["inverse"] != "gauss-newton":
        raise SceneError(f"{source}: [sip] inverse must be 'gauss-newton' for the marker PDE (its physics is "
                         f"nonlinear in the velocity), got {values['sip']['inverse']!r}")


def _apply_overrides(raw: dict, overrides, source: str) -> None:
    """Set ``raw[section][key] = value`` for each ``"section.key=value"``; the schema checks them after."""
    if isinstance(overrides, str):
        overrides = (overrides,)
    for item in overrides:
        target, sep, text = str(item).partition("=")
        section, dot, key = target.strip().partition(".")
        if not sep or not dot or not section or not key or "." in key:
            raise SceneError(f"{source}: --set {item!r} must have the form section.key=value, "
                             "e.g. optimizer.epochs=5")
        try:
            value = tomllib.loads(f"value = {text.strip()}")["value"]
        except tomllib.TOMLDecodeError:
            value = text.strip()            # plain text: a string
        if section not in raw:
            raw[section] = {}
        if not isinstance(raw[section], dict):
            raise SceneError(f"{source}: --set {item!r}: [{section}] is not a table")
        if value == "none":                 # TOML has no null: "none" unsets the key (its default applies)
            raw[section].pop(key, None)
        else:
            raw[section][key] = value


def _section(raw: dict, name: str, source: str) -> dict:
    """The checked values of section ``name`` as given in ``raw``, with the defaults of the keys it omits."""
    given = raw.get(name, {})
    if not isinstance(given, dict):
        raise SceneError(f"{source}: [{name}] must be a table, got {type(given).__name__}")
    schema = specs(name)
    unknown = sorted(set(given) - set(schema))
    if unknown:
        raise SceneError(f"{source}: unknown key(s) {unknown} in [{name}]; allowed keys are {sorted(schema)}")
    out = {}
    for key, spec in schema.items():
        where = f"{source}: [{name}] {key}"
        if key not in given:
            if spec.default is REQUIRED:
                raise SceneError(f"{where} is required")
            out[key] = spec.default
            continue
        out[key] = _checked(given[key], spec, where)
    return out


def _checked(value, spec: Spec, where: str):
    kind = spec.kind
    if kind is float and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if (isinstance(value, bool) and kind is not bool) or not isinstance(value, kind):
        raise SceneError(f"{where} must be of type {kind.__name__}, got {value!r} ({type(value).__name__})")
    if kind is float and not math.isfinite(value):
        raise SceneError(f"{where} must be finite, got {value!r}")
    if spec.choices is not None and value not in spec.choices:
        raise SceneError(f"{where} must be one of {list(spec.choices)}, got {value!r}")
    if spec.minimum is not None and value < spec.minimum:
        bound = "> 0" if spec.minimum == POSITIVE else f">= {_bound(spec.minimum)}"
        raise SceneError(f"{where} must be {bound}, got {value!r}")
    if spec.maximum is not None and value > spec.maximum:
        raise SceneError(f"{where} must be <= {_bound(spec.maximum)}, got {value!r}")
    return value


def _check_inverse(section: dict, source: str) -> None:
    lengths = set()
    for key in ("theta_ref", "theta_init"):
        values = section[key]
        if not values or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                 and math.isfinite(v) for v in values):
            raise SceneError(f"{source}: [inverse] {key} must be a non-empty list of finite numbers, got {values!r}")
        section[key] = tuple(float(v) for v in values)
        lengths.add(len(values))
    if len(lengths) != 1:
        raise SceneError(f"{source}: [inverse] theta_ref and theta_init must have the same length "
                         f"(the number of source modes P), got {list(section['theta_ref'])} "
                         f"and {list(section['theta_init'])}")
