"""What a run of a scene produced (:class:`RunResult`): the rows the reports read."""
from __future__ import annotations

import dataclasses

from fempdl.methods.newton_caps import ConvergedCaps

__all__ = ["RunResult"]


@dataclasses.dataclass
class RunResult:
    """What a run produced; ``rows`` are the per-epoch metrics of :class:`~fempdl.app.runs.training.Trainer`.

    ``mode`` is a run mode of :data:`~fempdl.app.runs.plan.MODES`, or the training method of a sip or
    hig scene (:mod:`fempdl.app.tasks.learned_inverse`), whose runs have no ``k_eps``.
    ``converged_caps``: on a Newton scene, what converged solves need (the measurement
    behind ``k_eps``; pass it to :func:`~fempdl.app.runs.runner.run` with ``k_eps_value``), else None."""

    scene: str
    mode: str
    k_eps: int | None
    rows: list
    out_dir: str | None
    converged_caps: ConvergedCaps | None = None

    @property
    def final_metric(self) -> float:
        return self.rows[-1]["val_metric"]

    @property
    def total_iterations(self) -> int:
        return self.rows[-1]["total_iterations"]

    @property
    def wall_time(self) -> float:
        return self.rows[-1]["wall_time"]

    @property
    def newton_steps(self) -> int | None:
        """Newton steps, forward and unrolled backward (None for a run without Newton layers)."""
        return self.rows[-1].get("newton_steps")

    @property
    def k_schedule(self) -> list[tuple[int, int]]:
        """(first epoch, K) for every K used."""
        out = []
        for row in self.rows:
            if not out or out[-1][1] != row["k"]:
                out.append((row["epoch"], row["k"]))
        return out
