"""The ``rtfem`` command.

Commands so far: ``rtfem info [MESH]`` (mesh check and repair report) and ``rtfem demo``.
Exit codes: 0 ok, 2 bad input (one-line message, no traceback).
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from .errors import RtfemError


def _load(path: str | None, scale: float):
    from . import meshes
    from .meshfile import load_mesh

    return meshes.liver() if path is None else load_mesh(path, scale=scale)


def cmd_info(args: argparse.Namespace) -> int:
    mesh = _load(args.mesh, args.scale)
    lo, hi = mesh.bounds()
    print(f"mesh        {args.mesh or 'embedded default liver'}")
    print(f"size        {mesh.n_vertices} vertices, {mesh.n_triangles} triangles, {mesh.edges().shape[0]} edges")
    print(f"extent      {np.array2string(hi - lo, precision=4)} (x, y, z), surface area {mesh.areas().sum():.4g}")
    if mesh.is_closed():
        print(f"volume      {mesh.volume():.4g}")
    print("check       " + str(mesh.report).replace("\n", "\n            "))
    if mesh.groups:
        print("groups      " + ", ".join(f"{k} ({len(v)} vertices)" for k, v in sorted(mesh.groups.items())))
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from .demo import main as demo_main

    return demo_main(["--out", args.out])


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="rtfem", description="Real-time simulation of deformable shell finite-element models.")
    sub = ap.add_subparsers(dest="command", required=True)
    p = sub.add_parser("info", help="check a mesh file (or the embedded liver) and report repairs")
    p.add_argument("mesh", nargs="?", help="mesh file (OBJ, STL, PLY, OFF, VTK, VTU, MSH, ...); default: the embedded liver")
    p.add_argument("--scale", type=float, default=1.0, help="coordinate scale factor (1e-3 turns mm into m)")
    p.set_defaults(func=cmd_info)
    p = sub.add_parser("demo", help="static poke, modal push-hold-release and a 1 kHz haptic session on the liver")
    p.add_argument("--out", default="out/demo", help="output folder (default: out/demo)")
    p.set_defaults(func=cmd_demo)
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args))
    except RtfemError as exc:
        print(f"rtfem: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"rtfem: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
