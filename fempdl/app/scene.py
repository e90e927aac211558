"""Scenes: TOML files that declare a training experiment, parsed into typed, frozen sections.

Each section of a scene file is a frozen dataclass below (:class:`MeshConfig`,
:class:`PdeConfig`, ...); each field carries its type, default, choices, bounds
and a one-line doc, so the schema is written once, there. :func:`schema_text`
renders it (``fempdl scenes --schema``). :func:`parse` is the one place that
validates: a malformed scene raises :class:`SceneError` naming the key and what
is allowed. Bundled scenes live in ``fempdl/app/scenes/``; :func:`load` takes a
bundled name or a path.
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

__all__ = ["Scene", "SceneError", "load", "available", "parse", "schema_text", "SECTIONS", "Spec", "specs",
           "SceneSection", "MeshConfig", "PdeConfig", "DataConfig", "NetworkConfig", "InverseConfig", "SipConfig",
           "MarkerConfig", "HigConfig", "BaselineConfig", "HybridConfig", "OptimizerConfig", "SolverConfig",
           "PrdpConfig"]

_REQUIRED = object()
_POSITIVE = 1e-300      # a minimum of "> 0"


@dataclasses.dataclass(frozen=True)
class Spec:
    """What a scene key accepts: its type, default (``_REQUIRED``: none), choices and bounds, and what it means."""

    kind: type
    default: Any = _REQUIRED
    doc: str = ""
    choices: tuple | None = None
    minimum: float | None = None
    maximum: float | None = None

    @property
    def required(self) -> bool:
        return self.default is _REQUIRED


def _key(kind: type, default: Any = _REQUIRED, doc: str = "", **bounds):
    """A section field whose metadata holds its :class:`Spec` (required keys have no default)."""
    spec = Spec(kind, default, doc, **bounds)
    if spec.required:
        return dataclasses.field(metadata={"spec": spec})
    return dataclasses.field(default=default, metadata={"spec": spec})


_section = dataclasses.dataclass(frozen=True, kw_only=True)


@_section
class SceneSection:
    """[scene]: what the run is called and which task it trains."""

    name: str = _key(str, doc='letters, digits and "-_.": it names the run directory')
    description: str = _key(str, "", doc="free text")
    task: str = _key(str, doc="what is trained", choices=("emulator", "inverse", "hybrid", "sip", "hig"))


@_section
class MeshConfig:
    """[mesh]: the domain."""

    name: str = _key(str, doc="a bundled mesh's name or the path to a .msh file")
    h: float | None = _key(float, None, doc="mesh size (none: the bundled mesh's default)", minimum=_POSITIVE)


@_section
class PdeConfig:
    """[pde]: the physics.

    Keys the PDE type does not use are refused in a file and None here."""

    type: str = _key(str, doc="heat | burgers for emulator, poisson for inverse and hig, poisson | heat | marker "
                              "for sip, oseen for hybrid", choices=("heat", "poisson", "burgers", "oseen", "marker"))
    dt: float | None = _key(float, 0.01, doc="time step (heat, burgers, oseen, marker)", minimum=_POSITIVE)
    theta: float | None = _key(float, 1.0, doc="theta time stepping: 1 implicit Euler (heat)",
                               minimum=0.0, maximum=1.0)
    kappa: float | None = _key(float, 1.0, doc="diffusivity (heat, poisson; marker: the marker's)",
                               minimum=_POSITIVE)
    degree: int | None = _key(int, None, doc="element degree (none: 1; 2 for oseen and marker, "
                                             "the Taylor-Hood velocity)", minimum=1)
    nu: float | None = _key(float, 0.01, doc="viscosity (burgers, oseen, marker)", minimum=_POSITIVE)
    inflow: float | None = _key(float, 1.0, doc="peak of the parabolic inlet profile (oseen)", minimum=_POSITIVE)


@_section
class DataConfig:
    """[data]: the generated samples.

    Keys the task does not use are refused in a file and None here."""

    train: int | None = _key(int, 64, doc="training samples (not inverse)", minimum=1)
    validation: int | None = _key(int, 16, doc="validation samples (not inverse)", minimum=1)
    modes: int | None = _key(int, 4, doc="sine modes (or boxes) per axis of the random fields (not inverse)",
                             minimum=1)
    seed: int = _key(int, 0, doc="seed of the data (and of the network, unless a run sets its own)", minimum=0)
    k_eps_rtol: float | None = _key(float, 1e-5, doc="rtol whose iteration count is the converged cap K_eps "
                                                     "(not sip, hig)", minimum=_POSITIVE, maximum=0.5)
    rollout: int | None = _key(int, 1, doc="steps of the validation rollout (emulator, hybrid)", minimum=1)
    truths: str | None = _key(str, "smooth", doc="sums of `modes` sine modes or boxes (sip, hig)",
                              choices=("smooth", "rectangles"))
    noise: float | None = _key(float, 0.0, doc="Gaussian noise on the observations, relative to their largest "
                                               "value (sip, hig)", minimum=0.0)
    resample: bool | None = _key(bool, False, doc="draw new training truths every epoch (sip, hig)")


@_section
class NetworkConfig:
    """[network]: the trained network."""

    type: str = _key(str, "mlp", doc="graph: heat emulators only", choices=("mlp", "graph"))
    hidden: int = _key(int, 128, doc="width of the hidden layers", minimum=1)
    layers: int = _key(int, 2, doc="hidden layers (0: linear); for graph the convolutions, >= 1", minimum=0)


@_section
class InverseConfig:
    """[inverse]: the source modes to recover."""

    theta_ref: tuple = _key(list, doc="the true source mode coefficients (numbers)")
    theta_init: tuple = _key(list, doc="the initial guess, as long as theta_ref")


@_section
class SipConfig:
    """[sip]: the scale-invariant physics inverse."""

    inverse: str = _key(str, doc="the physics inverse (marker: gauss-newton)",
                        choices=("exact", "tikhonov", "gauss-newton"))
    eta: float = _key(float, 1.0, doc="step along the inverse's update", minimum=_POSITIVE)
    damping: float = _key(float, 0.0, doc="Tikhonov alpha (tikhonov, gauss-newton)", minimum=0.0)
    cg_iterations: int = _key(int, 20, doc="CG iterations of the Gauss-Newton inverse (gauss-newton)", minimum=1)


@_section
class MarkerConfig:
    """[marker]: the advected marker (pde "marker" only)."""

    steps: int = _key(int, 4, doc="time steps of the flow", minimum=1)
    smoothing: float = _key(float, 0.1, doc="the projection's length ell", minimum=_POSITIVE)
    speed: float = _key(float, 1.0, doc="largest initial speed", minimum=_POSITIVE)
    shape: str = _key(str, "blob", doc="the marker's shape", choices=("blob", "band"))
    width: float = _key(float, 0.25, doc="the marker's width", minimum=_POSITIVE)
    prior: float = _key(float, 1e-4, doc="Tikhonov prior of the Gauss-Newton inverse", minimum=0.0)
    placement: str = _key(str, "random", doc="central: the node farthest from the walls",
                          choices=("random", "central"))
    inputs: str = _key(str, "standardized", doc="the network's inputs (m0, m_T): standardized by the initial "
                       "training draw, or raw", choices=("standardized", "raw"))


@_section
class HigConfig:
    """[hig]: the half-inverse gradient optimizer."""

    lr: float = _key(float, 1.0, doc="learning rate", minimum=_POSITIVE)
    kappa: float = _key(float, -0.5, doc="exponent of the half-inverse")
    beta: float = _key(float, 0.0, doc="momentum")
    tau: float = _key(float, 1e-5, doc="relative truncation of small singular values", minimum=0.0, maximum=1.0)
    method: str = _key(str, "auto", doc="how the half-inverse is computed", choices=("auto", "svd", "gram"))
    max_jacobian_mib: float = _key(float, 1024.0, doc="largest Jacobian held in memory, MiB", minimum=_POSITIVE)


@_section
class BaselineConfig:
    """[baseline]: Adam with backpropagation through the physics, the method's comparison."""

    lr: float | None = _key(float, None, doc="none: the optimizer's lr; 1e-3 for hig", minimum=_POSITIVE)
    decay: float | None = _key(float, None, doc="none: the optimizer's decay; 1.0 for hig", minimum=_POSITIVE)


@_section
class HybridConfig:
    """[hybrid]: the solver-in-the-loop correction of a coarse flow."""

    fine_h: float = _key(float, doc="the reference mesh size", minimum=_POSITIVE)
    steps: int = _key(int, 2, doc="unrolled training steps", minimum=1)
    spinup: int = _key(int, 10, doc="fine steps from rest before sampling", minimum=0)
    perturbation: float = _key(float, 0.2, doc="initial perturbation, relative to inflow", minimum=0.0)


@_section
class OptimizerConfig:
    """[optimizer]: the training loop.

    Keys the task does not use are refused in a file and None here."""

    type: str | None = _key(str, "adam", doc="not hig: HIG is its optimizer", choices=("adam", "sgd"))
    lr: float | None = _key(float, 1e-3, doc="learning rate (not hig)", minimum=_POSITIVE)
    decay: float | None = _key(float, 1.0, doc="learning rate factor per epoch (not hig)", minimum=_POSITIVE)
    epochs: int = _key(int, 30, doc="training epochs", minimum=1)
    batch: int | None = _key(int, 16, doc="mini-batch size (not inverse)", minimum=1)
    stop_at: float | None = _key(float, None, doc="end once the validation metric is <= it (none: never)",
                                 minimum=_POSITIVE)


@_section
class SolverConfig:
    """[solver]: the capped linear solver (sip and hig solve with LU: they compare methods, not caps)."""

    preset: str = _key(str, "jacobi", doc="the capped solver; schur is for oseen and only it",
                       choices=("jacobi", "cg", "gmres", "gmres-ilu", "schur"))
    diff: str = _key(str, "implicit", doc="how gradients pass the solve (unrolled: jacobi or cg)",
                     choices=("implicit", "unrolled"))
    warm_start: bool | None = _key(bool, False, doc="start the capped solve from the state being advanced "
                                                    "(emulator, hybrid) or from the last step's solution "
                                                    "(inverse)")
    lag_preconditioner: bool = _key(bool, False, doc="per-sample matrices share the first sample's "
                                                     "preconditioner within a call")


@_section
class PrdpConfig:
    """[prdp]: progressively refined differentiable physics."""

    k0: int = _key(int, 1, doc="first cap", minimum=1)
    dk: int = _key(int, 1, doc="least increase of a refinement", minimum=1)
    tau_step: float = _key(float, 0.95, doc="refine when the metric improves less than this factor",
                           minimum=_POSITIVE, maximum=1.0)
    tau_stop: float = _key(float, 0.9, doc="stop refining when a refinement improves less than this factor",
                           minimum=_POSITIVE, maximum=1.0)
    delta: int = _key(int, 3, doc="epochs compared for a plateau", minimum=2)
    ema_window: int = _key(int, 6, doc="epochs of the metric's moving average", minimum=1)
    k_cap: int | None = _key(int, None, doc="largest cap (none: K_eps)", minimum=1)
    guard: float | None = _key(float, None, doc="refine at once when the metric rises above guard x its best "
                                                "(none: never)", minimum=1.0 + 1e-12)
    growth: float = _key(float, 1.0, doc="a refinement sets K to max(K + dk, ceil(growth K))", minimum=1.0)


# Every section, in file order: the schema.
SECTIONS: dict[str, type] = {
    "scene": SceneSection, "mesh": MeshConfig, "pde": PdeConfig, "data": DataConfig, "network": NetworkConfig,
    "inverse": InverseConfig, "sip": SipConfig, "marker": MarkerConfig, "hig": HigConfig,
    "baseline": BaselineConfig, "hybrid": HybridConfig, "optimizer": OptimizerConfig, "solver": SolverConfig,
    "prdp": PrdpConfig,
}


def specs(section: str) -> dict[str, Spec]:
    """The keys of ``section`` and their specs, in order."""
    return {f.name: f.metadata["spec"] for f in dataclasses.fields(SECTIONS[section])}


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


# Keys a task or PDE type does not use: setting them is an error, not a silent no-op; they are None in the scene.
_NOT_FOR = {
    ("task", "inverse"): {"data": {"train", "validation", "modes", "rollout"} | _INVERSION_DATA,
                          "optimizer": {"batch"}},
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


def _unused(task: str, pde: str) -> dict[str, set]:
    """The keys, by section, that ``task`` and PDE type ``pde`` do not use."""
    out: dict[str, set] = {}
    for by_section in (_NOT_FOR.get(("task", task), {}), _NOT_FOR.get(("pde", pde), {})):
        for name, keys in by_section.items():
            out.setdefault(name, set()).update(keys)
    return out


class SceneError(ValueError):
    """A scene file is malformed; the message names the section, key and what is allowed."""


@dataclasses.dataclass(frozen=True)
class Scene:
    """A validated scene: one frozen section object per section its task uses (None for the others).

    Change one with :func:`dataclasses.replace` (``replace(scene, optimizer=replace(scene.optimizer,
    epochs=5))``); the values are not validated again."""

    name: str
    task: str
    description: str
    mesh: MeshConfig
    pde: PdeConfig
    data: DataConfig
    optimizer: OptimizerConfig
    solver: SolverConfig | None = None
    prdp: PrdpConfig | None = None
    network: NetworkConfig | None = None
    inverse: InverseConfig | None = None
    hybrid: HybridConfig | None = None
    sip: SipConfig | None = None
    hig: HigConfig | None = None
    baseline: BaselineConfig | None = None
    marker: MarkerConfig | None = None
    source: str = ""

    def as_dict(self) -> dict:
        """Plain (JSON-able) values: one dict per section, holding the keys its task and PDE use."""
        unused = _unused(self.task, self.pde.type)
        out = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if dataclasses.is_dataclass(value):
                value = {key: list(v) if isinstance(v, tuple) else v
                         for key, v in dataclasses.asdict(value).items() if key not in unused.get(f.name, ())}
            out[f.name] = value
        return out


def schema_text() -> str:
    """The schema as text: every section (and the tasks that take it), key, type, default, choices, bounds and doc."""
    lines = ["Scene files (TOML): sections and keys. A key a task or PDE does not use is refused.", ""]
    for name, cls in SECTIONS.items():
        tasks = [task for task, sections in _TASK_SECTIONS.items()
                 if name in sections["required"] | sections["optional"]]
        needed = [task for task, sections in _TASK_SECTIONS.items() if name in sections["required"]]
        usage = "every task" if len(tasks) == len(_TASK_SECTIONS) else ", ".join(tasks)
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
        parts.append("> 0" if spec.minimum == _POSITIVE else f">= {spec.minimum:g}")
    if spec.maximum is not None:
        parts.append(f"<= {spec.maximum:g}")
    return ", ".join(parts) + f": {spec.doc}"


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
    return parse(text, source=str(path), overrides=overrides)


def parse(text: str, source: str = "<string>", overrides=()) -> Scene:
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
    values = _task_sections(raw, task, source)
    _drop_unused(values, raw, task, source)
    pde = values["pde"]
    if pde["type"] not in _TASK_PDES[task]:
        raise SceneError(f"{source}: [pde] type {pde['type']!r} does not apply to task {task!r}; "
                         f"it takes {list(_TASK_PDES[task])}")
    if task in METHOD_TASKS:
        _check_method(values, raw, source)
    else:
        _check_flow(values, source)
        _check_solver(values, source)
    if task == "inverse":
        _check_inverse(values["inverse"], source)
    _check_size(task, values, source)
    sections = {name: SECTIONS[name](**values[name]) if name in values else None
                for name in SECTIONS if name != "scene"}
    return Scene(name=header["name"], task=task, description=header["description"], source=source, **sections)


def _task_sections(raw: dict, task: str, source: str) -> dict[str, dict]:
    """The checked keys (defaults filled in) of every section ``task`` takes; refuses missing and extra sections."""
    sections = _TASK_SECTIONS[task]
    missing = sorted(sections["required"] - set(raw))
    if missing:
        raise SceneError(f"{source}: task {task!r} needs section(s) {missing}")
    extra = sorted(set(raw) - sections["required"] - sections["optional"])
    if extra:
        raise SceneError(f"{source}: section(s) {extra} do not apply to task {task!r}; "
                         f"allowed: {sorted(sections['required'] | sections['optional'])}")
    taken = sections["required"] | sections["optional"]
    return {name: _section(raw, name, source) for name in SECTIONS if name in taken}


def _drop_unused(values: dict, raw: dict, task: str, source: str) -> None:
    """Refuse keys the task or PDE does not use when the file gives them; set them to None otherwise."""
    for (what, value), unused in _NOT_FOR.items():
        if (task if what == "task" else values["pde"]["type"]) != value:
            continue
        for name, keys in unused.items():
            given = sorted(keys & set(raw.get(name, {})))
            if given:
                raise SceneError(f"{source}: [{name}] {', '.join(given)} do(es) not apply to {what} {value!r}; "
                                 "remove them")
            for key in keys:
                if name in values:
                    values[name][key] = None


def _check_solver(values: dict, source: str) -> None:
    """The choices across [solver] and [prdp] of the tasks with a capped solver."""
    solver = values["solver"]
    if solver["diff"] == "unrolled" and solver["preset"] not in ("jacobi", "cg"):
        raise SceneError(f"{source}: [solver] diff = 'unrolled' needs preset 'jacobi' or 'cg', "
                         f"got {solver['preset']!r}")
    prdp = values["prdp"]
    if prdp["k_cap"] is not None and prdp["k_cap"] < prdp["k0"]:
        raise SceneError(f"{source}: [prdp] k_cap must be >= k0 ({prdp['k0']}), got {prdp['k_cap']}")


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
            if spec.default is _REQUIRED:
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
        states = 2 * data["rollout"] + 1 if task in ("emulator", "hybrid") else 2
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
    modes = values["data"]["modes"]
    dim = GEOMETRIES[values["mesh"]["name"]].dim
    most = max(4 * dofs, 1000)      # generous: the DOF estimate of a coarse mesh is rough
    if modes is not None and values["data"]["truths"] in (None, "smooth") and modes ** dim > most:
        raise SceneError(f"{source}: [data] modes = {modes} gives {modes}^{dim} sine modes, far more than the "
                         f"mesh's about {dofs:.3g} DOFs resolve; use at most {int(most ** (1.0 / dim))}")


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
                         f"(the number of source modes P), got {list(section['theta_ref'])} and {list(section['theta_init'])}")
