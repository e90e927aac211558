"""The scene schema: every section of a scene file as a frozen dataclass, and what a task declares.

Each section is a frozen dataclass below (:class:`MeshConfig`, :class:`PdeConfig`, ...); each field
carries its type, default, choices, bounds and a one-line doc, so the schema is written once, here.
``[prdp]`` is :class:`fempdl.methods.prdp.PRDPSettings` itself: the controller and the scene file
share one definition. :class:`TaskSpec` is what each task class declares (its name, the PDEs and
sections it takes, its parallel modes and outputs); :mod:`fempdl.app.tasks` collects them into the
registry that :mod:`fempdl.app.scene` validates scenes against.
"""
from __future__ import annotations

import dataclasses
import re
from collections.abc import Mapping
from typing import Any

from fempdl.methods.newton_caps import REFINE
from fempdl.methods.prdp_settings import PRDPSettings

__all__ = ["Scene", "SceneError", "Spec", "TaskSpec", "SECTIONS", "PDE_UNUSED", "NONLINEAR_PDES", "PARALLEL_MODES",
           "REQUIRED", "SEED_MAX", "POSITIVE", "specs", "check_slug",
           "SceneSection", "MeshConfig", "PdeConfig", "DataConfig", "NetworkConfig", "InverseConfig", "SipConfig",
           "MarkerConfig", "HigConfig", "BaselineConfig", "HybridConfig", "OptimizerConfig", "SolverConfig",
           "PRDPSettings"]

#: The PDE types solved by Newton (a NonlinearSolveLayer): [pde] alpha and [solver] refine apply to them.
NONLINEAR_PDES = ("nonlinear-heat", "nonlinear-poisson")

#: The ways a task may train on several ranks (``--parallel``): ``"data"`` spreads every batch over
#: them, ``"mesh"`` distributes the mesh.
PARALLEL_MODES = ("data", "mesh")

#: The largest seed of a scene or run, as of the command's --seed: TOML's largest integer (a signed
#: 64-bit one); torch's generators fail beyond 2^64 - 1 ("Overflow when unpacking long long").
SEED_MAX = 2 ** 63 - 1
REQUIRED = object()
POSITIVE = 1e-300      # a minimum of "> 0"
_SLUG = re.compile(r"[A-Za-z0-9._-]{1,128}")


class SceneError(ValueError):
    """A scene file is malformed; the message names the section, key and what is allowed."""


def check_slug(name, what: str = "name") -> str:
    """``name`` if it is a safe path component: letters, digits and ``-_.``, at most 128, not ``.``/``..``
    (a scene's name becomes the directory of its runs)."""
    if not isinstance(name, str) or not _SLUG.fullmatch(name) or name in (".", ".."):
        raise ValueError(f"{what} must be 1-128 letters, digits, '-', '_' or '.' (and not '.' or '..'), "
                         f"got {name!r}; it becomes a directory name")
    return name


@dataclasses.dataclass(frozen=True)
class Spec:
    """What a scene key accepts: its type, default (``REQUIRED``: none), choices and bounds, and what it means."""

    kind: type
    default: Any = REQUIRED
    doc: str = ""
    choices: tuple | None = None
    minimum: float | None = None
    maximum: float | None = None

    @property
    def required(self) -> bool:
        return self.default is REQUIRED


def _key(kind: type, default: Any = REQUIRED, doc: str = "", **bounds):
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
    task: str = _key(str, doc="what is trained: a task of the registry (fempdl.app.tasks)")


@_section
class MeshConfig:
    """[mesh]: the domain."""

    name: str = _key(str, doc="a bundled mesh's name or the path to a .msh file")
    h: float | None = _key(float, None, doc="mesh size (none: the bundled mesh's default)", minimum=POSITIVE)


@_section
class PdeConfig:
    """[pde]: the physics.

    Keys the PDE type does not use are refused in a file and None here."""

    type: str = _key(str, doc="heat | burgers | nonlinear-heat for emulator, poisson for inverse, poisson | "
                              "nonlinear-poisson for hig, poisson | heat | nonlinear-poisson | marker for sip, "
                              "oseen for hybrid",
                     choices=("heat", "poisson", "burgers", "oseen", "marker") + NONLINEAR_PDES)
    dt: float | None = _key(float, 0.01, doc="time step (heat, burgers, oseen, marker, nonlinear-heat)",
                            minimum=POSITIVE)
    theta: float | None = _key(float, 1.0, doc="theta time stepping: 1 implicit Euler (heat)",
                               minimum=0.0, maximum=1.0)
    kappa: float | None = _key(float, 1.0, doc="diffusivity (heat, poisson, nonlinear-heat, nonlinear-poisson; "
                                               "marker: the marker's)",
                               minimum=POSITIVE)
    degree: int | None = _key(int, None, doc="element degree (none: 1; 2 for oseen and marker, "
                                             "the Taylor-Hood velocity)", minimum=1)
    nu: float | None = _key(float, 0.01, doc="viscosity (burgers, oseen, marker)", minimum=POSITIVE)
    inflow: float | None = _key(float, 1.0, doc="peak of the parabolic inlet profile (oseen)", minimum=POSITIVE)
    alpha: float | None = _key(float, 1.0, doc="the conductivity's nonlinearity kappa (1 + alpha u^2) "
                                               "(nonlinear-heat, nonlinear-poisson)", minimum=0.0)


@_section
class DataConfig:
    """[data]: the generated samples.

    Keys the task does not use are refused in a file and None here."""

    train: int | None = _key(int, 64, doc="training samples (not inverse)", minimum=1)
    validation: int | None = _key(int, 16, doc="validation samples (not inverse)", minimum=1)
    modes: int | None = _key(int, 4, doc="sine modes (or boxes) per axis of the random fields (not inverse)",
                             minimum=1)
    seed: int = _key(int, 0, doc="seed of the data (and of the network, unless a run sets its own); at most "
                                 "2^63 - 1, what torch's and numpy's generators take", minimum=0, maximum=SEED_MAX)
    k_eps_rtol: float | None = _key(float, 1e-5, doc="rtol whose iteration count is the converged cap K_eps "
                                                     "(not sip, hig)", minimum=POSITIVE, maximum=0.5)
    rollout: int | None = _key(int, 1, doc="steps of the validation rollout (emulator, hybrid)", minimum=1)
    train_rollout: int | None = _key(int, 1, doc="(network, physics) pairs the training loss covers, fed "
                                                 "back autoregressively (emulator)", minimum=1)
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
    eta: float = _key(float, 1.0, doc="step along the inverse's update", minimum=POSITIVE)
    damping: float = _key(float, 0.0, doc="Tikhonov alpha (tikhonov, gauss-newton)", minimum=0.0)
    cg_iterations: int = _key(int, 20, doc="CG iterations of the Gauss-Newton inverse (gauss-newton)", minimum=1)


@_section
class MarkerConfig:
    """[marker]: the advected marker (pde "marker" only)."""

    steps: int = _key(int, 4, doc="time steps of the flow", minimum=1)
    smoothing: float = _key(float, 0.1, doc="the projection's length ell", minimum=POSITIVE)
    speed: float = _key(float, 1.0, doc="largest initial speed", minimum=POSITIVE)
    shape: str = _key(str, "blob", doc="the marker's shape", choices=("blob", "band"))
    width: float = _key(float, 0.25, doc="the marker's width", minimum=POSITIVE)
    prior: float = _key(float, 1e-4, doc="Tikhonov prior of the Gauss-Newton inverse", minimum=0.0)
    placement: str = _key(str, "random", doc="central: the node farthest from the walls",
                          choices=("random", "central"))
    inputs: str = _key(str, "standardized", doc="the network's inputs (m0, m_T): standardized by the initial "
                       "training draw, or raw", choices=("standardized", "raw"))


@_section
class HigConfig:
    """[hig]: the half-inverse gradient optimizer."""

    lr: float = _key(float, 1.0, doc="learning rate", minimum=POSITIVE)
    kappa: float = _key(float, -0.5, doc="exponent of the half-inverse")
    beta: float = _key(float, 0.0, doc="momentum")
    tau: float = _key(float, 1e-5, doc="relative truncation of small singular values", minimum=0.0, maximum=1.0)
    method: str = _key(str, "auto", doc="how the half-inverse is computed", choices=("auto", "svd", "gram"))
    max_jacobian_mib: float = _key(float, 1024.0, doc="largest Jacobian held in memory, MiB", minimum=POSITIVE)


@_section
class BaselineConfig:
    """[baseline]: Adam with backpropagation through the physics, the method's comparison."""

    lr: float | None = _key(float, None, doc="none: the optimizer's lr; 1e-3 for hig", minimum=POSITIVE)
    decay: float | None = _key(float, None, doc="none: the optimizer's decay; 1.0 for hig", minimum=POSITIVE)


@_section
class HybridConfig:
    """[hybrid]: the solver-in-the-loop correction of a coarse flow."""

    fine_h: float = _key(float, doc="the reference mesh size", minimum=POSITIVE)
    steps: int = _key(int, 2, doc="unrolled training steps", minimum=1)
    spinup: int = _key(int, 10, doc="fine steps from rest before sampling", minimum=0)
    perturbation: float = _key(float, 0.2, doc="initial perturbation, relative to inflow", minimum=0.0)


@_section
class OptimizerConfig:
    """[optimizer]: the training loop.

    Keys the task does not use are refused in a file and None here."""

    type: str | None = _key(str, "adam", doc="not hig: HIG is its optimizer", choices=("adam", "sgd"))
    lr: float | None = _key(float, 1e-3, doc="learning rate (not hig)", minimum=POSITIVE)
    decay: float | None = _key(float, 1.0, doc="learning rate factor per epoch (not hig)", minimum=POSITIVE)
    epochs: int = _key(int, 30, doc="training epochs", minimum=1)
    batch: int | None = _key(int, 16, doc="mini-batch size (not inverse)", minimum=1)
    stop_at: float | None = _key(float, None, doc="end once the validation metric is <= it (none: never)",
                                 minimum=POSITIVE)


@_section
class SolverConfig:
    """[solver]: the capped linear solver (sip and hig solve with LU: they compare methods, not caps).

    On a nonlinear PDE the layer is a Newton solve whose inner linear solve is ``preset``; ``refine``
    says what the cap K counts (:class:`fempdl.methods.newton_caps.NewtonCaps`)."""

    preset: str = _key(str, "jacobi", doc="the capped solver; schur is for oseen and only it; lu is a Newton "
                                          "layer's converged inner solve (nonlinear PDEs, refine = newton)",
                       choices=("jacobi", "cg", "gmres", "gmres-ilu", "schur", "lu"))
    diff: str = _key(str, "implicit", doc="how gradients pass the solve (unrolled: jacobi or cg)",
                     choices=("implicit", "unrolled"))
    warm_start: bool | None = _key(bool, False, doc="start the capped solve from the state being advanced "
                                                    "(emulator, hybrid) or from the last step's solution "
                                                    "(inverse)")
    lag_preconditioner: bool | None = _key(bool, False, doc="per-sample matrices share the first sample's "
                                                            "preconditioner within a call (linear PDEs)")
    refine: str | None = _key(str, "newton", doc="what K caps in a Newton layer (nonlinear PDEs): newton steps "
                                                 "(the inner solve converged), inner Krylov iterations per step "
                                                 "(Newton steps: as many as converged solves need), or both "
                                                 "(K steps of inner_per_k K iterations, neither cap past what "
                                                 "converged solves need)", choices=REFINE)
    inner_per_k: int | None = _key(int, 1, doc="inner iterations per Newton step per unit of K (refine = both)",
                                   minimum=1)


# Every section, in file order: the schema.
SECTIONS: dict[str, type] = {
    "scene": SceneSection, "mesh": MeshConfig, "pde": PdeConfig, "data": DataConfig, "network": NetworkConfig,
    "inverse": InverseConfig, "sip": SipConfig, "marker": MarkerConfig, "hig": HigConfig,
    "baseline": BaselineConfig, "hybrid": HybridConfig, "optimizer": OptimizerConfig, "solver": SolverConfig,
    "prdp": PRDPSettings,
}


def specs(section: str) -> dict[str, Spec]:
    """The keys of ``section`` and their specs, in order. A section defined outside the app (``[prdp]``)
    states kind, doc and bounds in its fields' metadata."""
    out = {}
    for f in dataclasses.fields(SECTIONS[section]):
        meta = f.metadata
        out[f.name] = meta["spec"] if "spec" in meta else Spec(
            meta["kind"], f.default, meta["doc"], meta.get("choices"), meta.get("minimum"), meta.get("maximum"))
    return out


# Keys a PDE type does not use: setting them is an error, not a silent no-op; they are None in the scene.
_LINEAR_SOLVER = frozenset({"refine", "inner_per_k"})       # what K caps in a Newton layer
PDE_UNUSED: dict[str, dict[str, frozenset]] = {
    "poisson": {"pde": frozenset({"dt", "theta", "nu", "inflow", "alpha"}), "solver": _LINEAR_SOLVER},
    "heat": {"pde": frozenset({"nu", "inflow", "alpha"}), "solver": _LINEAR_SOLVER},
    "burgers": {"pde": frozenset({"theta", "kappa", "inflow", "alpha"}), "solver": _LINEAR_SOLVER},
    "oseen": {"pde": frozenset({"theta", "kappa", "alpha"}), "solver": _LINEAR_SOLVER},
    "marker": {"pde": frozenset({"theta", "inflow", "alpha"}), "solver": _LINEAR_SOLVER},
    # One backward-Euler step (no theta) of -div(kappa (1 + alpha u^2) grad u) by Newton.
    "nonlinear-heat": {"pde": frozenset({"theta", "nu", "inflow"}), "solver": frozenset({"lag_preconditioner"})},
    "nonlinear-poisson": {"pde": frozenset({"dt", "theta", "nu", "inflow"}),
                          "solver": frozenset({"lag_preconditioner"})},
}


@dataclasses.dataclass(frozen=True)
class TaskSpec:
    """What a task class declares (its ``specs``); the scene parser, the runner and the command read it.

    Attributes:
        name: the scene's ``[scene] task``.
        pdes: the ``[pde] type`` values the class is built for.
        required: the sections a scene file of the task must have.
        optional: the sections it may have (all defaults when absent); any other is refused.
        unused: keys, by section, the task does not use: refused in a file, None in the scene.
        parallel: the ``--parallel`` modes it trains in (``"data"``: batches over the ranks,
            ``"mesh"``: a distributed mesh); empty: one process.
        trains: ``"cap"`` (a fixed K, K_eps or PRDP through capped layers) or ``"method"`` (its
            training method, SIP or HIG, against Adam with backpropagation).
        writes_fields: ``fempdl run --save-fields`` writes its validation predictions.
    """

    name: str
    pdes: tuple[str, ...]
    required: frozenset
    optional: frozenset
    unused: Mapping[str, frozenset] = dataclasses.field(default_factory=dict)
    parallel: tuple[str, ...] = ()
    trains: str = "cap"
    writes_fields: bool = False

    def __post_init__(self):
        unknown = sorted((set(self.required) | set(self.optional) | set(self.unused)) - set(SECTIONS))
        if unknown or self.trains not in ("cap", "method") or set(self.parallel) - set(PARALLEL_MODES):
            raise ValueError(f"task {self.name!r} declares unknown sections {unknown}, trains={self.trains!r} "
                             f"or parallel={self.parallel!r}")

    @property
    def sections(self) -> frozenset:
        return frozenset(self.required) | frozenset(self.optional)


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
    prdp: PRDPSettings | None = None
    network: NetworkConfig | None = None
    inverse: InverseConfig | None = None
    hybrid: HybridConfig | None = None
    sip: SipConfig | None = None
    hig: HigConfig | None = None
    baseline: BaselineConfig | None = None
    marker: MarkerConfig | None = None
    source: str = ""
    #: keys, by section, that the task and PDE do not use (None in the sections; left out of :meth:`as_dict`)
    unused: Mapping[str, frozenset] = dataclasses.field(default_factory=dict, compare=False, repr=False)

    def as_dict(self) -> dict:
        """Plain (JSON-able) values: one dict per section, holding the keys its task and PDE use."""
        out = {}
        for f in dataclasses.fields(self):
            if f.name == "unused":
                continue
            value = getattr(self, f.name)
            if dataclasses.is_dataclass(value):
                value = {key: list(v) if isinstance(v, tuple) else v
                         for key, v in dataclasses.asdict(value).items() if key not in self.unused.get(f.name, ())}
            out[f.name] = value
        return out
