"""TensorBoard logging of a run (optional: the ``tensorboard`` extra)."""
from __future__ import annotations

from pathlib import Path

__all__ = ["tensorboard_writer"]


def tensorboard_writer(directory: Path):
    """A TensorBoard SummaryWriter on ``directory``, or an ImportError that says how to install it."""
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError as err:
        raise ImportError(f"TensorBoard logging needs the tensorboard package ({err}); install it with "
                          "pip install 'fempdl[tensorboard]', or train without it") from None
    return SummaryWriter(log_dir=str(directory))
