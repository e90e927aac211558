"""How a run trains and where it writes: :class:`RunSettings`, one frozen value handed from the command
(or a script) through the runner to the training loop.

The scene says what is trained (task, PDE, data, optimizer, solver); the run's mode and cap say how
the solver is capped; everything else about a run is here, checked once when it is built.
"""
from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path

from mpi4py import MPI

from fempdl.app.schema import PARALLEL_MODES, SEED_MAX
from fempdl.core.checks import is_int, is_real, python_number

__all__ = ["RunSettings", "PARALLEL_MODES", "CHECKPOINT_EVERY"]

# Seconds of a run between writes of its files: a checkpoint costs milliseconds (a network's and
# its optimizer's state), which after every epoch of a fast scene would be a share of the run.
CHECKPOINT_EVERY = 1.0


@dataclasses.dataclass(frozen=True)
class RunSettings:
    """How one run trains and where it writes.

    Attributes:
        out_dir: where metrics, checkpoints and fields go (``None``: nowhere).
        resume: continue the run ``out_dir`` holds (the same settings; only the epochs may grow).
        overwrite: a fresh run replaces the files of a run already in ``out_dir``, or writes into a
            directory holding other files (fempdl's names replaced, nothing deleted); without it
            both are refused (:func:`~fempdl.app.runs.rundir.check_output_directory`). Not with
            ``resume``.
        epochs: the loop's length (``None``: the scene's ``[optimizer] epochs``).
        seed: the network initialisation and the minibatch order (``None``: the scene's data seed;
            the data are the scene's either way).
        progress: show a tqdm bar with epoch, loss, metric and K.
        stop_after: stop, as if interrupted, after this many epochs of this call.
        stop_at_time: end training once its steps took this many seconds (a comparison at equal
            training time; > 0).
        tensorboard: also write every metric row as TensorBoard scalars into ``out_dir``/tensorboard
            (rank 0; needs the ``tensorboard`` package).
        checkpoint_every: write the files after an epoch that ends at least this many seconds of the
            run's clock after they were last written (and after the last epoch); 0: every epoch.
        save: write the validation fields after training (tasks that write fields; into ``out_dir``).
        parallel: ``None`` (serial), ``"data"`` or ``"mesh"`` (:mod:`fempdl.core.parallel`).
        comm: the ranks that train together in a parallel mode; every rank returns the same result.
    """

    out_dir: Path | None = None
    resume: bool = False
    overwrite: bool = False
    epochs: int | None = None
    seed: int | None = None
    progress: bool = False
    stop_after: int | None = None
    stop_at_time: float | None = None
    tensorboard: bool = False
    checkpoint_every: float = CHECKPOINT_EVERY
    save: bool = False
    parallel: str | None = None
    comm: MPI.Comm = dataclasses.field(default_factory=lambda: MPI.COMM_WORLD)

    def __post_init__(self):
        if self.out_dir is not None:
            # An empty string is Path("."): a run would write into the working directory unasked.
            if not isinstance(self.out_dir, (str, os.PathLike)) or (isinstance(self.out_dir, str)
                                                                     and not self.out_dir.strip()):
                raise ValueError(f"out_dir must be a directory's path (str or Path) or None, got {self.out_dir!r}; "
                                 "for the working directory give '.'")
            object.__setattr__(self, "out_dir", Path(self.out_dir))
        for name in ("resume", "overwrite", "progress", "tensorboard", "save"):
            if not isinstance(getattr(self, name), bool):     # resume="no" is truthy: it resumed
                raise ValueError(f"{name} must be True or False, got {getattr(self, name)!r}")
        if self.resume and self.overwrite:
            raise ValueError("resume=True and overwrite=True contradict each other: resume continues the run in "
                             "out_dir, overwrite starts it afresh; give one")
        if self.stop_at_time is not None and not (is_real(self.stop_at_time) and 0 < self.stop_at_time < math.inf):
            raise ValueError(f"stop_at_time must be a finite number of seconds > 0 or None, got "
                             f"{self.stop_at_time!r}")
        if self.parallel not in (None, *PARALLEL_MODES):
            raise ValueError(f"parallel must be None or one of {list(PARALLEL_MODES)}, got {self.parallel!r}")
        if self.seed is not None and not (is_int(self.seed) and 0 <= self.seed <= SEED_MAX):
            raise ValueError(f"seed must be an int in [0, 2^63 - 1] (what torch's and numpy's generators take), "
                             f"got {self.seed!r}")
        for name in ("epochs", "stop_after"):
            value = getattr(self, name)
            if value is not None and (not is_int(value) or value < 1):
                raise ValueError(f"{name} must be a positive int or None, got {value!r}")
        if not (is_real(self.checkpoint_every) and 0 <= self.checkpoint_every < math.inf):
            raise ValueError(f"checkpoint_every must be a finite number of seconds >= 0, got "
                             f"{self.checkpoint_every!r}")
        # Numpy scalars are stored as python numbers: the settings are compared with a resumed run's.
        for name in ("seed", "epochs", "stop_after", "stop_at_time", "checkpoint_every"):
            object.__setattr__(self, name, python_number(getattr(self, name)))

    def check_outputs(self) -> None:
        """Raise ValueError for outputs that need an ``out_dir`` it does not have (checked when a run
        starts, not when the settings are built: a command's common settings get their ``out_dir``
        per run)."""
        if self.tensorboard and self.out_dir is None:
            raise ValueError("tensorboard=True writes into out_dir/tensorboard: give out_dir")
        if self.resume and self.out_dir is None:
            raise ValueError("resume=True continues the run in out_dir: give out_dir")

    @property
    def board_dir(self) -> Path | None:
        """Where the TensorBoard event files go (``None``: none are written)."""
        return self.out_dir / "tensorboard" if self.tensorboard else None

    @property
    def ranks(self) -> MPI.Comm:
        """The ranks that train together: ``comm`` in a parallel mode, else this process alone."""
        return MPI.COMM_SELF if self.parallel is None else self.comm
