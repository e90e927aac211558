"""Regenerate the bundled .msh files in meshes/ (or another folder) with this machine's gmsh.

    python tools/regenerate_meshes.py [--out DIR] [--name NAME ...] [--h H]

Meshing runs on one thread with the user's gmsh configuration ignored, so the
files are reproducible for a given gmsh version (fempdl.core.meshgen).
"""
from __future__ import annotations

import argparse
from pathlib import Path

from fempdl.core import meshgen


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=meshgen.BUNDLED_DIR,
                        help="directory to write NAME.msh into (default: %(default)s)")
    parser.add_argument("--name", choices=meshgen.names(), action="append",
                        help="mesh to write (repeatable; default: all)")
    parser.add_argument("--h", type=float, default=None, help="mesh size (default: each mesh's bundled size)")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    for name in args.name or meshgen.names():
        print(f"wrote {meshgen.write_msh(name, args.out / f'{name}.msh', h=args.h)}")


if __name__ == "__main__":
    main()
