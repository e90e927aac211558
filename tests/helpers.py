"""What the tests share: the solver x form configurations, problem builders, control batches, and tiny scenes.

Test files import from here (``from helpers import build, tiny_scene``); conftest.py holds only fixtures.
tests/mpi/*.py, run as scripts under mpirun, put this directory on sys.path first.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import gc
import json

from mpi4py import MPI
import dolfinx.fem
import numpy as np
import torch

from fempdl import forms
from fempdl.app import cli as _cli
from fempdl.ksp_adjoint import KSPOptions

# Converged solvers: gradients must be exact (gradcheck, Taylor test).
CONVERGED = {
    "lu": KSPOptions.preset("lu"),
    "cg": KSPOptions.preset("cg", rtol=1e-13),
}
# Capped solvers: exact iteration counts; implicit gradients exact for Jacobi (RHS
# controls), approximate for Krylov methods.
CAPPED = {
    "jacobi": lambda k: KSPOptions(ksp_type="richardson", pc_type="jacobi", max_it=k),
    "gmres": lambda k: KSPOptions.preset("gmres", max_it=k, gmres_restart=5),
    "cg": lambda k: KSPOptions.preset("cg", max_it=k),
}
# Every control of every form module, and the variants that change which
# controls enter the matrix or the right-hand side (theta < 1 puts kappa into L;
# theta = 0 makes kappa an affine RHS control on its own DG0 space) or the
# sizes of the spaces (P2 solution, DG0 coefficient).
FORM_CONTROLS = {
    "poisson": ("f", "kappa"),
    "poisson-p2-dg0": ("f", "kappa"),
    "heat": ("u0", "f", "kappa"),
    "heat-cn": ("u0", "f", "kappa"),
    "heat-explicit-dg0": ("u0", "f", "kappa"),
}
FORM_VARIANTS = {
    "poisson": {},
    "poisson-p2-dg0": {"degree": 2, "kappa_space": "DG0"},
    "heat": {},
    "heat-cn": {"theta": 0.5},
    "heat-explicit-dg0": {"theta": 0.0, "kappa_space": "DG0"},
}
FORM_CONTROL_PAIRS = [(form, c) for form, cs in FORM_CONTROLS.items() for c in cs]


def smooth(x):
    return 1.0 + 0.5 * np.sin(np.pi * x[0]) * np.cos(np.pi * x[1])


def build(form: str, msh, controls=None, **kw):
    """A problem of the named form variant with every control (or the given ones)."""
    controls = FORM_CONTROLS[form] if controls is None else controls
    kw = {**FORM_VARIANTS[form], **kw}
    if form.startswith("poisson"):
        return forms.poisson.problem(msh, controls=controls, kappa=smooth, **kw)
    return forms.heat.problem(msh, controls=controls, dt=0.05, kappa=smooth,
                              u0=lambda x: np.sin(np.pi * x[0]), **kw)


def control_values(prob, name: str, batch: int, seed: int = 0) -> torch.Tensor:
    """A positive, smooth-plus-noise control batch (kappa stays well away from 0)."""
    gen = torch.Generator().manual_seed(seed)
    n = prob.control_size(name)
    base = torch.as_tensor(prob.interpolate(smooth, name))
    noise = 0.2 * torch.rand(batch, n, generator=gen, dtype=torch.float64)
    return (base + noise) if name == "kappa" else (base - 1.0 + noise)


def integral(form, comm) -> float:
    """A compiled functional assembled and summed over ``comm``."""
    return comm.allreduce(dolfinx.fem.assemble_scalar(form), op=MPI.SUM)


# ------------------------------------------------------------------ tiny scenes
# One small scene per task, section by section; tiny_scene() edits a copy and writes it as TOML.
TINY_SCENES = {
    # The heat emulator on the L-shape: 16 samples, 30 short epochs, a quick PRDP schedule.
    "emulator": {
        "scene": {"name": "tiny-heat", "task": "emulator"},
        "mesh": {"name": "lshape", "h": 0.2},
        "pde": {"type": "heat", "dt": 0.002},
        "data": {"train": 16, "validation": 4, "modes": 3},
        "network": {"hidden": 16},
        "optimizer": {"lr": 1e-2, "epochs": 30, "batch": 8},
        "prdp": {"k0": 1, "dk": 2, "tau_step": 0.95, "delta": 2, "ema_window": 2},
    },
    # Two Poisson conductivities fitted by SGD.
    "inverse": {
        "scene": {"name": "tiny-inverse", "task": "inverse"},
        "mesh": {"name": "lshape", "h": 0.25},
        "pde": {"type": "poisson"},
        "inverse": {"theta_ref": [0.6, 1.9], "theta_init": [3.0, 3.0]},
        "optimizer": {"type": "sgd", "lr": 1.0, "epochs": 15},
    },
    # Poisson source inference through the exact inverse, with a linear network.
    "sip": {
        "scene": {"name": "tiny-sip", "task": "sip"},
        "mesh": {"name": "lshape", "h": 0.3},
        "pde": {"type": "poisson"},
        "data": {"train": 16, "validation": 8},
        "network": {"layers": 0},
        "sip": {"inverse": "exact"},
        "optimizer": {"lr": 3e-2, "epochs": 10, "batch": 16},
    },
    "hig": {
        "scene": {"name": "tiny-hig", "task": "hig"},
        "mesh": {"name": "lshape", "h": 0.3},
        "pde": {"type": "poisson"},
        "data": {"train": 4, "validation": 4},
        "network": {"hidden": 8, "layers": 1},
        "hig": {"lr": 0.5},
        "optimizer": {"epochs": 10, "batch": 4},
    },
    # Oseen around the obstacle, corrected by a network against a finer mesh.
    "hybrid": {
        "scene": {"name": "tiny-hybrid", "task": "hybrid"},
        "mesh": {"name": "obstacle", "h": 0.15},
        "pde": {"type": "oseen", "nu": 1e-3, "dt": 0.02, "inflow": 1.5},
        "hybrid": {"fine_h": 0.08, "steps": 2, "spinup": 2},
        "data": {"train": 6, "validation": 3, "modes": 2, "rollout": 3},
        "network": {"hidden": 16},
        "optimizer": {"lr": 1e-3, "epochs": 8, "batch": 3},
        "solver": {"preset": "schur"},
        "prdp": {"k0": 2, "dk": 2, "delta": 2, "ema_window": 2},
    },
}

# The CLI tests' emulator (an edit for tiny_scene("emulator", CLI_TINY)): every [prdp] key, Adam with
# decay, Jacobi; test_cli and test_mpi_logs count its iterations from [data] train = 16.
CLI_TINY = {
    "scene": {"name": "tiny-emulator", "description": "tiny heat emulator for the CLI tests"},
    "pde": {"kappa": 1.0},
    "data": {"modes": 2, "seed": 0},
    "network": {"type": "mlp", "layers": 2},
    "optimizer": {"type": "adam", "lr": 1e-3, "decay": 0.98, "epochs": 6, "batch": 8},
    "solver": {"preset": "jacobi"},
    "prdp": {"tau_stop": 0.9, "delta": 3, "ema_window": 4},
}


def tiny_scene(task: str = "emulator", *edits: dict, name: str | None = None, description: str | None = None,
               **sections: dict | None) -> str:
    """The TOML text of ``task``'s tiny scene after ``edits``, then ``sections`` (and ``name``,
    ``description`` in [scene]), each a {section: {key: value}} mapping applied in order: keys are set,
    a value of None removes the key, a section of None removes the section.

    ``tiny_scene(name="t", optimizer={"epochs": 2}, prdp=None)``: the emulator as "t", 2 epochs, no [prdp].
    """
    scene = {section: dict(keys) for section, keys in TINY_SCENES[task].items()}
    named = {key: value for key, value in (("name", name), ("description", description)) if value is not None}
    for edit in (*edits, sections, {"scene": named}):
        for section, keys in edit.items():
            if keys is None:
                scene.pop(section, None)
                continue
            target = scene.setdefault(section, {})
            for key, value in keys.items():
                if value is None:
                    target.pop(key, None)
                else:
                    target[key] = value
    return to_toml(scene)


def to_toml(scene: dict) -> str:
    """``{section: {key: value}}`` as TOML text (values: str, bool, int, float, or lists of them)."""
    return "".join(f"[{section}]\n" + "".join(f"{key} = {_toml_value(value)}\n" for key, value in keys.items())
                   for section, keys in scene.items())


def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)          # repr of a float keeps its point or exponent (1.0, 0.001, 1e-06, inf)
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False)    # a TOML basic string: JSON's escapes are TOML's
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise TypeError(f"no TOML form for {value!r} ({type(value).__name__})")


# ------------------------------------------------------------------ memory
_libc_name = ctypes.util.find_library("c")
_libc = ctypes.CDLL(_libc_name) if _libc_name else None


def rss() -> int:
    """Resident set size of this process in bytes."""
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    raise RuntimeError("no VmRSS line in /proc/self/status")


def settled_rss() -> int:
    """VmRSS after a garbage collection and malloc_trim (free pages returned to the system)."""
    gc.collect()
    if _libc is not None and hasattr(_libc, "malloc_trim"):
        _libc.malloc_trim(0)
    return rss()


def one_line_error(argv, capsys) -> str:
    """The command's last stderr line, checked to be its one-line error with exit code 2."""
    code = _cli.main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert code == 2, err
    lines = [line for line in err.splitlines() if line.strip()]
    # Log lines of the run may come first (stderr is no terminal here); the error is the last line.
    assert "Traceback" not in err and all(line.startswith("fempdl: ") for line in lines), err
    return lines[-1]


def finished_run(root, scene_text: str):
    """(scene file, output directory): ``scene_text`` written under ``root`` and one finished run of it by
    ``fempdl run --k 4 --no-baseline`` in ``root / "out"`` (its run folder ``out/k4``)."""
    from fempdl.app import cli

    path = root / "tiny.toml"
    path.write_text(scene_text)
    argv = ["run", path, "--k", 4, "--out", root / "out", "--no-progress", "--no-baseline"]
    assert cli.main([str(a) for a in argv]) == 0
    return path, root / "out"
