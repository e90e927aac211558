"""Scenes: TOML files that declare a training experiment, validated against a schema.

A scene declares only what its task needs. Sections and keys (defaults in
brackets; ``required`` has none)::

    [scene]      name (required: letters, digits, "-_.": it names the run directory), description [""],
                 task (required: "emulator" | "inverse" | "hybrid" | "sip" | "hig")
    [mesh]       name (required: bundled name or path to a .msh), h [bundled default]
    [pde]        type (required: "heat" | "burgers" for emulators, "poisson" for inverse
                 and hig, "poisson" | "heat" | "marker" for sip, "oseen" for hybrid), degree [1; 2 for oseen, marker], kappa [1.0] (heat, poisson),
                 dt [0.01] (heat, burgers, oseen), theta [1.0] (heat), nu [0.01] (burgers,
                 oseen), inflow [1.0] (oseen: peak of the parabolic inlet profile)
    [data]       seed [0], k_eps_rtol [1e-5] (not sip, hig), and for all but inverse
                 train [64], validation [16], modes [4], rollout [1] (steps of the validation
                 rollout; emulator, hybrid); for sip and hig: truths ["smooth"] ("smooth" |
                 "rectangles": sums of ``modes`` sine modes or boxes), noise [0.0] (Gaussian
                 noise on the observations, relative to their largest value), resample
                 [false] (draw new training truths every epoch)
    [network]    type ["mlp"] ("mlp" | "graph"; heat emulators only), hidden [128],
                 layers [2] (hidden layers, 0: linear; graph convolutions, >= 1)
                                                         (emulator, hybrid, sip, hig)
    [sip]        inverse (required: "exact" | "tikhonov" | "gauss-newton"), eta [1.0],
                 damping [0.0] (Tikhonov alpha; tikhonov, gauss-newton), cg_iterations
                 [20] (gauss-newton)                                          (sip only)
    [marker]     steps [4], smoothing [0.1] (the projection's length ell), speed [1.0] (largest
                 initial speed), shape ["blob"] ("blob" | "band"), width [0.25], placement
                 ["random"] ("random" | "central": the node farthest from the walls), prior [1e-4]
                 (Tikhonov prior of the Gauss-Newton inverse); [pde] dt, nu (fluid), kappa
                 (marker diffusivity), degree [2] (velocity); [sip] inverse "gauss-newton"
                                                                   (sip on pde "marker" only)
    [hig]        lr [1.0], kappa [-0.5], beta [0.0], tau [1e-5], method ["auto"] ("auto" |
                 "svd" | "gram"), max_jacobian_mib [1024]                     (hig only)
    [baseline]   lr [the optimizer's lr; 1e-3 for hig], decay [the optimizer's decay; 1.0
                 for hig]: Adam with backpropagation through the physics, the method's
                 comparison                                                  (sip, hig)
    [inverse]    theta_ref (required), theta_init (required)                  (inverse only)
    [hybrid]     fine_h (required: the reference mesh size), steps [2] (unrolled training
                 steps), spinup [10] (fine steps from rest before sampling),
                 perturbation [0.2] (initial perturbation, relative to inflow) (hybrid only)
    [optimizer]  type ["adam"] ("adam" | "sgd"), lr [1e-3], decay [1.0] (not hig: HIG is
                 its optimizer), epochs [30], batch [16] (not inverse), stop_at [none]: end
                 once the validation metric is <= it
    [solver]     preset ["jacobi"] ("jacobi" | "cg" | "gmres" | "gmres-ilu" | "schur": the
                 capped solver; "schur" is for oseen and only it),
                 diff ["implicit"] ("implicit" | "unrolled"), warm_start [false] (start the
                 capped solve from the state being advanced instead of zero; emulator,
                 hybrid), lag_preconditioner [false] (per-sample matrices share the
                 first sample's preconditioner within a call; KSPOptions)    (not sip, hig)
    [prdp]       k0 [1], dk [1], tau_step [0.95], tau_stop [0.9], delta [3], ema_window [6],
                 k_cap [none], guard [none] (refine at once when the metric rises above
                 guard x its best), growth [1.0] (a refinement sets K to
                 max(K + dk, ceil(growth K)))                              (not sip, hig)

sip and hig scenes solve their physics with LU (exact solutions and
gradients): they compare training methods, not solver caps.

Unknown sections or keys, keys that do not apply to the task or PDE, wrong
types, out-of-range values and missing required keys raise :class:`SceneError`
naming the key and the allowed values. Values are data: strings are never
evaluated. A scene whose data and network would not fit in half the available
memory (estimated from the bundled mesh's size at h, :func:`estimated_memory`),
or that asks for more sine modes than the mesh resolves, is refused with the
estimate; a file that is not UTF-8 is a SceneError too. The fixed cap of a
run is not part of a scene: it is chosen per run (``fempdl run --k K``), as
PRDP and the converged cap K_eps are.

Bundled scenes live in ``fempdl/scenes/``; :func:`load` takes a bundled name
or a path.
"""
from __future__ import annotations

import dataclasses
import math
import tomllib
from importlib import resources
from pathlib import Path
from typing import Any

from fempdl.resources import GEOMETRIES, estimated_dofs, format_bytes, memory_budget
from fempdl.app.rundir import check_slug

__all__ = ["Scene", "SceneError", "load", "available", "parse"]

_REQUIRED = object()


@dataclasses.dataclass(frozen=True)
class _Key:
    kind: type | tuple
    default: Any = _REQUIRED
    choices: tuple | None = None
    minimum: float | None = None
    maximum: float | None = None


_POSITIVE = 1e-300
SCHEMA: dict[str, dict[str, _Key]] = {
    "scene": {"name": _Key(str), "description": _Key(str, ""),
              "task": _Key(str, choices=("emulator", "inverse", "hybrid", "sip", "hig"))},
    "mesh": {"name": _Key(str), "h": _Key(float, None, minimum=_POSITIVE)},
    "pde": {"type": _Key(str, choices=("heat", "poisson", "burgers", "oseen", "marker")),
            "dt": _Key(float, 0.01, minimum=_POSITIVE), "theta": _Key(float, 1.0, minimum=0.0, maximum=1.0),
            "kappa": _Key(float, 1.0, minimum=_POSITIVE), "degree": _Key(int, None, minimum=1),
            "nu": _Key(float, 0.01, minimum=_POSITIVE), "inflow": _Key(float, 1.0, minimum=_POSITIVE)},
    "data": {"train": _Key(int, 64, minimum=1), "validation": _Key(int, 16, minimum=1),
             "modes": _Key(int, 4, minimum=1), "seed": _Key(int, 0, minimum=0),
             "k_eps_rtol": _Key(float, 1e-5, minimum=_POSITIVE, maximum=0.5), "rollout": _Key(int, 1, minimum=1),
             "truths": _Key(str, "smooth", choices=("smooth", "rectangles")), "noise": _Key(float, 0.0, minimum=0.0),
             "resample": _Key(bool, False)},
    "network": {"type": _Key(str, "mlp", choices=("mlp", "graph")), "hidden": _Key(int, 128, minimum=1),
                "layers": _Key(int, 2, minimum=0)},
    "inverse": {"theta_ref": _Key(list), "theta_init": _Key(list)},
    "sip": {"inverse": _Key(str, choices=("exact", "tikhonov", "gauss-newton")),
            "eta": _Key(float, 1.0, minimum=_POSITIVE),
            "damping": _Key(float, 0.0, minimum=0.0), "cg_iterations": _Key(int, 20, minimum=1)},
    "marker": {"steps": _Key(int, 4, minimum=1), "smoothing": _Key(float, 0.1, minimum=_POSITIVE),
               "speed": _Key(float, 1.0, minimum=_POSITIVE), "shape": _Key(str, "blob", choices=("blob", "band")),
               "width": _Key(float, 0.25, minimum=_POSITIVE), "prior": _Key(float, 1e-4, minimum=0.0),
               "placement": _Key(str, "random", choices=("random", "central"))},
    "hig": {"lr": _Key(float, 1.0, minimum=_POSITIVE), "kappa": _Key(float, -0.5), "beta": _Key(float, 0.0),
            "tau": _Key(float, 1e-5, minimum=0.0, maximum=1.0),
            "method": _Key(str, "auto", choices=("auto", "svd", "gram")),
            "max_jacobian_mib": _Key(float, 1024.0, minimum=_POSITIVE)},
    "baseline": {"lr": _Key(float, None, minimum=_POSITIVE), "decay": _Key(float, None, minimum=_POSITIVE)},
    "hybrid": {"fine_h": _Key(float, minimum=_POSITIVE), "steps": _Key(int, 2, minimum=1),
               "spinup": _Key(int, 10, minimum=0), "perturbation": _Key(float, 0.2, minimum=0.0)},
    "optimizer": {"type": _Key(str, "adam", choices=("adam", "sgd")), "lr": _Key(float, 1e-3, minimum=_POSITIVE),
                  "decay": _Key(float, 1.0, minimum=_POSITIVE), "epochs": _Key(int, 30, minimum=1),
                  "batch": _Key(int, 16, minimum=1), "stop_at": _Key(float, None, minimum=_POSITIVE)},
    "solver": {"preset": _Key(str, "jacobi", choices=("jacobi", "cg", "gmres", "gmres-ilu", "schur")),
               "diff": _Key(str, "implicit", choices=("implicit", "unrolled")),
               "warm_start": _Key(bool, False), "lag_preconditioner": _Key(bool, False)},
    "prdp": {"k0": _Key(int, 1, minimum=1), "dk": _Key(int, 1, minimum=1),
             "tau_step": _Key(float, 0.95, minimum=_POSITIVE, maximum=1.0),
             "tau_stop": _Key(float, 0.9, minimum=_POSITIVE, maximum=1.0),
             "delta": _Key(int, 3, minimum=2), "ema_window": _Key(int, 6, minimum=1),
             "k_cap": _Key(int, None, minimum=1), "guard": _Key(float, None, minimum=1.0 + 1e-12),
             "growth": _Key(float, 1.0, minimum=1.0)},
}
# Sections each task needs (others must be absent) and may omit (then all defaults).
_TASK_SECTIONS = {
    "emulator": {"required": {"scene", "mesh", "pde"}, "optional": {"data", "network", "optimizer", "solver", "prdp"}},
    "inverse": {"required": {"scene", "mesh", "pde", "inverse"}, "optional": {"data", "optimizer", "solver", "prdp"}},
    "hybrid": {"required": {"scene", "mesh", "pde", "hybrid"},
               "optional": {"data", "network", "optimizer", "solver", "prdp"}},
    "sip": {"required": {"scene", "mesh", "pde", "sip"},
            "optional": {"data", "network", "optimizer", "baseline", "marker"}},
    "hig": {"required": {"scene", "mesh", "pde", "hig"}, "optional": {"data", "network", "optimizer", "baseline"}},
}
# The PDEs each task is built for.
_TASK_PDES = {"emulator": ("heat", "burgers"), "inverse": ("poisson",), "hybrid": ("oseen",),
              "sip": ("poisson", "heat", "marker"), "hig": ("poisson",)}
# Tasks that compare a training method with Adam and backpropagation (fempdl.app.tasks.inversion).
METHOD_TASKS = ("sip", "hig")
_INVERSION_DATA = {"truths", "noise", "resample"}


# Keys a task or PDE type does not use: setting them is an error, not a silent no-op.
_NOT_FOR = {
    ("task", "inverse"): {"data": {"train", "validation", "modes", "rollout"} | _INVERSION_DATA,
                          "optimizer": {"batch"}, "solver": {"warm_start"}},
    ("task", "emulator"): {"data": _INVERSION_DATA},
    ("task", "hybrid"): {"data": _INVERSION_DATA},
    ("task", "sip"): {"data": {"k_eps_rtol", "rollout"}},
    ("task", "hig"): {"data": {"k_eps_rtol", "rollout"}, "optimizer": {"type", "lr", "decay"}},
    ("pde", "poisson"): {"pde": {"dt", "theta", "nu", "inflow"}},
    ("pde", "heat"): {"pde": {"nu", "inflow"}},
    ("pde", "burgers"): {"pde": {"theta", "kappa", "inflow"}},
    ("pde", "oseen"): {"pde": {"theta", "kappa"}},
    ("pde", "marker"): {"pde": {"theta", "inflow"}},
}


class SceneError(ValueError):
    """A scene file is malformed; the message names the section, key and what is allowed."""


@dataclasses.dataclass(frozen=True)
class Scene:
    """A validated scene: one dict per section, holding the keys its task and PDE use, defaults filled in."""

    name: str
    task: str
    description: str
    mesh: dict
    pde: dict
    data: dict
    optimizer: dict
    solver: dict | None = None
    prdp: dict | None = None
    network: dict | None = None
    inverse: dict | None = None
    hybrid: dict | None = None
    sip: dict | None = None
    hig: dict | None = None
    baseline: dict | None = None
    marker: dict | None = None
    source: str = ""

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


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
    return parse(text, source=str(path), overrides=overrides)


def parse(text: str, source: str = "<string>", overrides=()) -> Scene:
    """Validate TOML text, with ``overrides`` applied (see :func:`load`), as a scene."""
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise SceneError(f"{source}: not valid TOML: {err}") from None
    _apply_overrides(raw, overrides, source)
    unknown = sorted(set(raw) - set(SCHEMA))
    if unknown:
        raise SceneError(f"{source}: unknown section(s) {unknown}; allowed sections are {sorted(SCHEMA)}")
    if "scene" not in raw:
        raise SceneError(f"{source}: missing section [scene] (with name and task)")
    header = _section(raw, "scene", source)
    try:
        check_slug(header["name"], "[scene] name")
    except ValueError as err:
        raise SceneError(f"{source}: {err}") from None
    task = header["task"]
    sections = _TASK_SECTIONS[task]
    missing = sorted(sections["required"] - set(raw))
    if missing:
        raise SceneError(f"{source}: task {task!r} needs section(s) {missing}")
    extra = sorted(set(raw) - sections["required"] - sections["optional"])
    if extra:
        raise SceneError(f"{source}: section(s) {extra} do not apply to task {task!r}; "
                         f"allowed: {sorted(sections['required'] | sections['optional'])}")
    values = {name: _section(raw, name, source) for name in SCHEMA if name in sections["required"] | sections["optional"]}
    for (what, value), unused in _NOT_FOR.items():
        if (task if what == "task" else values["pde"]["type"]) != value:
            continue
        for name, keys in unused.items():
            given = sorted(keys & set(raw.get(name, {})))
            if given:
                raise SceneError(f"{source}: [{name}] {', '.join(given)} do(es) not apply to {what} {value!r}; "
                                 "remove them")
            for key in keys:     # a section holds only the keys its task and PDE use
                values[name].pop(key, None)
    pde = values["pde"]
    if pde["type"] not in _TASK_PDES[task]:
        raise SceneError(f"{source}: [pde] type {pde['type']!r} does not apply to task {task!r}; "
                         f"it takes {list(_TASK_PDES[task])}")
    if task in METHOD_TASKS:
        _check_method(values, raw, source)
    else:
        _check_flow(values, source)
        solver = values["solver"]
        if solver["diff"] == "unrolled" and solver["preset"] not in ("jacobi", "cg"):
            raise SceneError(f"{source}: [solver] diff = 'unrolled' needs preset 'jacobi' or 'cg', "
                             f"got {solver['preset']!r}")
        prdp = values["prdp"]
        if prdp["k_cap"] is not None and prdp["k_cap"] < prdp["k0"]:
            raise SceneError(f"{source}: [prdp] k_cap must be >= k0 ({prdp['k0']}), got {prdp['k_cap']}")
    if task == "inverse":
        _check_inverse(values["inverse"], source)
    _check_size(task, values, source)
    return Scene(name=header["name"], task=task, description=header["description"], source=source,
                 **{name: values.get(name) for name in SCHEMA if name != "scene"})


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
        raw[section][key] = value


def _section(raw: dict, name: str, source: str) -> dict:
    given = raw.get(name, {})
    if not isinstance(given, dict):
        raise SceneError(f"{source}: [{name}] must be a table, got {type(given).__name__}")
    schema = SCHEMA[name]
    unknown = sorted(set(given) - set(schema))
    if unknown:
        raise SceneError(f"{source}: unknown key(s) {unknown} in [{name}]; allowed keys are {sorted(schema)}")
    out = {}
    for key, spec in schema.items():
        where = f"{source}: [{name}] {key}"
        if key not in given:
            if spec.default is _REQUIRED:
                raise SceneError(f"{where} is required")
            out[key] = spec.default
            continue
        out[key] = _checked(given[key], spec, where)
    return out


def _checked(value, spec: _Key, where: str):
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
        bound = "> 0" if spec.minimum == _POSITIVE else f">= {spec.minimum:g}"
        raise SceneError(f"{where} must be {bound}, got {value!r}")
    if spec.maximum is not None and value > spec.maximum:
        raise SceneError(f"{where} must be <= {spec.maximum:g}, got {value!r}")
    return value


def estimated_memory(task: str, values: dict) -> tuple[float, float, dict] | None:
    """(bytes, DOFs, parts) a scene's data and network take, estimated before anything is built; None
    for a mesh file (its size is unknown until read). Parts: ``data`` (float64 states and their float32
    copies), ``network`` (parameters, gradients and two Adam moments), by the bundled mesh's size at h."""
    name, h = values["mesh"]["name"], values["mesh"]["h"]
    if name not in GEOMETRIES:
        return None
    from_h = h if h is not None else _BUNDLED_H[name]
    pde = values["pde"]
    components = GEOMETRIES[name].dim if pde["type"] in ("burgers", "oseen") else 1
    dofs = estimated_dofs(name, from_h, pde["degree"] or 1, components)
    data, network = values["data"], values.get("network")
    parts = {}
    if task != "inverse":
        samples = data["train"] + data["validation"]
        states = 2 * data.get("rollout", 1) + 1 if task in ("emulator", "hybrid") else 2
        parts["data"] = samples * dofs * states * 12.0
    if network is not None:
        width, depth = network["hidden"], network["layers"]
        weights = 2 * dofs * width + depth * width ** 2 if network["type"] == "mlp" else depth * width ** 2
        parts["network"] = weights * 8.0 * 4
    return sum(parts.values()), dofs, parts


# The committed meshes' sizes (fempdl.meshgen.DEFAULT_H), for the estimate of a scene without h.
_BUNDLED_H = {"lshape": 0.05, "obstacle": 0.035, "box": 0.1}


def _check_size(task: str, values: dict, source: str) -> None:
    """Refuse a scene whose data and network would not fit in the memory budget, or whose number of
    smooth modes exceeds what the mesh resolves, with the estimate."""
    estimate = estimated_memory(task, values)
    if estimate is None:
        return
    total, dofs, parts = estimate
    budget = memory_budget()
    if total > budget:
        split = ", ".join(f"{part} {format_bytes(size)}" for part, size in parts.items())
        raise SceneError(f"{source}: the scene needs about {format_bytes(total)} ({split}; about {dofs:.3g} DOFs), "
                         f"more than the memory budget of {format_bytes(budget)} (half the available memory); "
                         "reduce [data] train and validation, [network] hidden and layers, or refine the mesh less")
    modes = values["data"].get("modes")
    dim = GEOMETRIES[values["mesh"]["name"]].dim
    most = max(4 * dofs, 1000)      # generous: the DOF estimate of a coarse mesh is rough
    if modes is not None and values["data"].get("truths", "smooth") == "smooth" and modes ** dim > most:
        raise SceneError(f"{source}: [data] modes = {modes} gives {modes}^{dim} sine modes, far more than the "
                         f"mesh's about {dofs:.3g} DOFs resolve; use at most {int(most ** (1.0 / dim))}")


def _check_inverse(section: dict, source: str) -> None:
    lengths = set()
    for key in ("theta_ref", "theta_init"):
        values = section[key]
        if not values or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                 and math.isfinite(v) for v in values):
            raise SceneError(f"{source}: [inverse] {key} must be a non-empty list of finite numbers, got {values!r}")
        section[key] = [float(v) for v in values]
        lengths.add(len(values))
    if len(lengths) != 1:
        raise SceneError(f"{source}: [inverse] theta_ref and theta_init must have the same length "
                         f"(the number of source modes P), got {section['theta_ref']} and {section['theta_init']}")
