"""The default run: a network trained through a capped heat-step layer.

The PRDP paper's mixed chain on the bundled L-shape: a residual MLP emulates
one heat step u0 -> u1 on DOF vectors, a capped implicit-Euler heat layer
(Richardson + Jacobi, K iterations) advances u1 -> u2, and the loss is the
normalised MSE (PRDP paper, eq. 56)

    nMSE = mean_i ||u2_i - u2_ref_i||^2 / ||u2_ref_i||^2

against two converged heat steps. The run reports the inner iterations the
capped layer used, the iterations a converged Jacobi solve would have needed
for the same solves, and the validation error measured with converged physics.
"""
from __future__ import annotations

import dataclasses
import time

import numpy as np
import torch
from mpi4py import MPI
from tqdm import tqdm

from fempdl import forms, mesh
from fempdl.bridge_torch import SolveLayer
from fempdl.ksp_adjoint import KSPOptions


@dataclasses.dataclass(frozen=True)
class HeatDemoConfig:
    """Settings of the default run (all small enough for a laptop CPU)."""

    k: int | None = 16            # None: train with the converged solver (the baseline)
    epochs: int = 30
    train_samples: int = 64
    val_samples: int = 16
    batch: int = 16
    hidden: int = 128
    lr: float = 1e-3
    dt: float = 0.002
    modes: int = 4
    seed: int = 0
    converged_rtol: float = 1e-10


@dataclasses.dataclass(frozen=True)
class HeatDemoResult:
    k: int | None
    val_nmse: float                # network + converged physics, after training
    val_nmse_untrained: float
    forward_iterations: int
    backward_iterations: int
    converged_iterations_per_solve: float
    solve_time: float
    wall_time: float


def nmse(u: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """Mean over samples of ||u - ref||^2 / ||ref||^2 (PRDP paper, eq. 56)."""
    return (((u - ref) ** 2).sum(-1) / (ref ** 2).sum(-1)).mean()


def random_initial_states(prob, count: int, modes: int, gen: np.random.Generator) -> torch.Tensor:
    """Smooth random fields: sums of sine modes with decaying random amplitudes."""
    xy = prob.dof_coordinates()
    x, y = (xy[:, 0] + 1.0) / 2.0, (xy[:, 1] + 1.0) / 2.0
    out = np.zeros((count, len(xy)))
    for i in range(1, modes + 1):
        for j in range(1, modes + 1):
            amp = gen.standard_normal(count) / (i * i + j * j)
            out += amp[:, None] * np.sin(i * np.pi * x)[None] * np.sin(j * np.pi * y)[None]
    return torch.as_tensor(out)


class ResidualMLP(torch.nn.Module):
    """u1 = u0 + MLP(u0): the network only has to learn the change of one step."""

    def __init__(self, n: int, hidden: int):
        super().__init__()
        self.net = torch.nn.Sequential(
            torch.nn.Linear(n, hidden), torch.nn.GELU(),
            torch.nn.Linear(hidden, hidden), torch.nn.GELU(),
            torch.nn.Linear(hidden, n))

    def forward(self, u0: torch.Tensor) -> torch.Tensor:
        return u0 + self.net(u0)


def run(config: HeatDemoConfig = HeatDemoConfig(), *, progress: bool = True) -> HeatDemoResult:
    """Train the emulator through the capped heat layer and evaluate it."""
    t_start = time.perf_counter()
    torch.manual_seed(config.seed)
    gen = np.random.default_rng(config.seed)
    msh = mesh.load("lshape", MPI.COMM_WORLD)
    prob = forms.heat.problem(msh, controls=("u0",), dt=config.dt)
    converged = SolveLayer(prob, KSPOptions.preset("jacobi", rtol=config.converged_rtol))
    capped = SolveLayer(prob, converged.options if config.k is None else KSPOptions(max_it=config.k))

    u0_all = random_initial_states(prob, config.train_samples + config.val_samples, config.modes, gen)
    with torch.no_grad():
        ref_all = converged(u0=converged(u0=u0_all))
    converged_per_solve = converged.stats.forward_iterations / converged.stats.forward_solves
    n_train = config.train_samples
    train_u0, train_ref = u0_all[:n_train].float(), ref_all[:n_train].float()
    val_u0, val_ref = u0_all[n_train:].float(), ref_all[n_train:].float()

    model = ResidualMLP(prob.output_size, config.hidden)
    optimizer = torch.optim.Adam(model.parameters(), lr=config.lr)

    def validate() -> float:
        with torch.no_grad():
            return float(nmse(converged(u0=model(val_u0)), val_ref))

    untrained = validate()
    bar = tqdm(range(config.epochs), desc=f"heat emulator K={config.k or 'converged'}", disable=not progress)
    for epoch in bar:
        order = torch.randperm(n_train)
        for start in range(0, n_train, config.batch):
            idx = order[start:start + config.batch]
            loss = nmse(capped(u0=model(train_u0[idx])), train_ref[idx])
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
        bar.set_postfix(loss=f"{loss.item():.2e}", val=f"{validate():.2e}")
    s = capped.stats
    result = HeatDemoResult(
        k=config.k, val_nmse=validate(), val_nmse_untrained=untrained,
        forward_iterations=s.forward_iterations, backward_iterations=s.backward_iterations,
        converged_iterations_per_solve=converged_per_solve, solve_time=s.solve_time,
        wall_time=time.perf_counter() - t_start)
    capped.close()
    converged.close()
    return result


def report(results: list[HeatDemoResult]) -> str:
    """A table of runs: iterations used, the saving against converged training, error, time.

    The saving is relative to the run trained with the converged solver when it
    is among ``results``, else to converged Jacobi estimated per solve.
    """
    def used(r):
        return r.forward_iterations + r.backward_iterations

    baseline = next((r for r in results if r.k is None), None)
    header = f"{'K':>10} {'inner iterations':>17} {'saved':>7} {'val nMSE':>10} {'wall s':>7}"
    lines = ["heat emulator on the L-shape: MLP step u0 -> u1, heat layer u1 -> u2 (Richardson+Jacobi).",
             "val nMSE: validation error with converged physics; saved: inner iterations saved against",
             "training with converged Jacobi (rtol 1e-10, "
             f"{results[0].converged_iterations_per_solve:.0f} iterations per forward solve).",
             header, "-" * len(header)]
    for r in results:
        if baseline is not None:
            reference = used(baseline)
        else:
            reference = used(r) / r.k * r.converged_iterations_per_solve
        label = "converged" if r.k is None else str(r.k)
        saved = "" if r is baseline else f"{100 * (1 - used(r) / reference):.0f}%"
        lines.append(f"{label:>10} {used(r):>17,d} {saved:>7} {r.val_nmse:>10.2e} {r.wall_time:>7.1f}")
    lines.append(f"{'untrained':>10} {'':>17} {'':>7} {results[0].val_nmse_untrained:>10.2e}")
    return "\n".join(lines)
