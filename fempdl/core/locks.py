"""File-system facts the locks of run directories and output files rely on."""
from __future__ import annotations

import os

__all__ = ["same_file"]


def same_file(fd: int, path) -> bool:
    """Whether ``path`` itself (not a link's target) still names the open file ``fd``: a lock taken on
    a file that its last holder has since unlinked (and that another process may have recreated), or
    that another entry replaced, locks nothing."""
    try:
        here = os.lstat(path)
    except OSError:
        return False
    mine = os.fstat(fd)
    return (here.st_dev, here.st_ino) == (mine.st_dev, mine.st_ino)
