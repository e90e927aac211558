"""The task protocol the trainer runs, and what every task shares: its optimizer and its step."""
from __future__ import annotations

from typing import TYPE_CHECKING

import torch

from fempdl.layer.cap_target import CapTarget, as_target
from fempdl.layer.reference import counters_kept
from fempdl.solve.assembly import assemble_scipy

if TYPE_CHECKING:
    import scipy.sparse as sp

__all__ = ["Task", "make_optimizer", "optimisation_step", "operator_pattern", "cap_target", "uncounted"]


def optimisation_step(optimizer, loss: torch.Tensor) -> float:
    """One step of ``optimizer`` on ``loss``; returns the loss value."""
    optimizer.zero_grad()
    loss.backward()
    optimizer.step()
    return loss.item()


class Task:
    """What :class:`~fempdl.app.runs.training.Trainer` trains; subclasses define the physics.

    A task has ``model``, ``optimizer``, ``scheduler`` (or None), ``layers``
    (the capped layers whose iterations are counted), optionally ``caps``
    (what the cap K is set on when it is not each layer's ``max_it``: a
    :class:`~fempdl.methods.newton_caps.NewtonCaps` for Newton layers), ``train_size``,
    ``val_size``, and two functions of sample indices (a LongTensor):

    * ``loss(idx)``: the training loss of those samples, a mean over them (so a
      batch split into shards is the shard losses weighted by their sizes);
    * ``validation_errors(idx)``: one error per validation sample; the
      validation metric is their mean over all ``val_size`` samples.

    ``train_step(idx)`` is one step of ``optimizer`` on ``loss(idx)``; a task
    whose optimizer makes its own update (HIG, :mod:`fempdl.app.tasks.learned_inverse`)
    replaces it. A task may also define ``start_epoch(epoch)``, which the
    Trainer calls before every epoch (to draw new training data). State a
    task carries from step to step outside its model (a warm start's last
    solution) goes through ``state_dict()`` (this rank's) and
    ``load_state_dict(states)`` (every rank's, as saved: a resumed run's mesh
    may be partitioned differently), so that a resumed run continues.
    """

    val_size = 1
    #: A Newton task's caps rule (:class:`~fempdl.methods.newton_caps.NewtonCaps`); None: K is each layer's
    #: ``max_it``.
    caps = None

    def state_dict(self) -> dict:
        """This rank's state outside the model and optimizer (tensors and plain values); none by default."""
        return {}

    def load_state_dict(self, states: list) -> None:
        """Restore from the states every rank saved (one dict per rank)."""
        if any(states):
            raise ValueError(f"{type(self).__name__} keeps no state, got {[sorted(s) for s in states]}")

    def k_eps_rhs(self) -> dict:
        """The layer inputs (tensors, one row per sample) on which the converged cap K_eps is measured."""
        raise NotImplementedError(f"{type(self).__name__} measures no K_eps")

    def validation_fields(self, idx) -> tuple:
        """(space name or None, prediction, reference) of the validation samples ``idx``, (len(idx), n)
        each: what ``--save-fields`` writes (tasks whose spec says ``writes_fields``)."""
        raise NotImplementedError(f"{type(self).__name__} writes no fields")

    def close(self) -> None:
        """Free the PETSc objects the task holds (its layers'); the runner calls it when a run ends."""

    def train_step(self, idx) -> float:
        """One optimizer step on the samples ``idx``; returns the loss."""
        return optimisation_step(self.optimizer, self.loss(idx))

    def validate(self) -> float:
        """The validation metric: the mean error over every validation sample."""
        with torch.no_grad():
            return float(self.validation_errors(torch.arange(self.val_size)).double().mean())


#: Leave the solves run inside out of the layers' counters: a task's data drawn through its training
#: layers is not training (the wall clock still sees the time).
uncounted = counters_kept


def operator_pattern(problem) -> sp.csr_matrix:
    """The assembled operator without boundary conditions: its pattern is the DOF graph."""
    return assemble_scipy(problem.a_form)


def make_optimizer(params, kind: str, lr: float, decay: float):
    """Optimizer ``kind`` ("adam" or "sgd") at learning rate ``lr`` over ``params``, and its
    scheduler: the rate times ``decay`` every epoch (None when decay is 1)."""
    params = list(params)
    if kind == "adam":
        # The fused kernel updates all parameters in one call: the per-tensor loop of
        # the default implementation costs more than these small networks' arithmetic.
        optimizer = torch.optim.Adam(params, lr=lr, fused=True)
    else:
        optimizer = torch.optim.SGD(params, lr=lr)
    scheduler = None if decay == 1.0 else torch.optim.lr_scheduler.ExponentialLR(optimizer, decay)
    return optimizer, scheduler


def cap_target(task) -> CapTarget:
    """What the cap K of ``task`` moves (:mod:`fempdl.layer.cap_target`): its ``caps`` (a
    :class:`~fempdl.methods.newton_caps.NewtonCaps`, one number for a Newton layer's two
    caps) when it declares them, else its capped layers (each layer's ``max_it``)."""
    return as_target(task.layers if task.caps is None else task.caps)
