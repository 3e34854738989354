"""``rtfem cache``: where the precomputed artefacts are kept (tet meshes, modal bases, reduced
nonlinear models with their cubature; :mod:`rtfem.cache`), how large they are, and clearing them."""

from __future__ import annotations

import argparse
import os

from ..cache import KINDS, cache_dir, clear, entries


def size_text(nbytes: int) -> str:
    for unit, k in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if nbytes >= k:
            return f"{nbytes / k:.3g} {unit}"
    return f"{nbytes} bytes"


def _age(seconds: float) -> str:
    for unit, k in (("d", 86400), ("h", 3600), ("min", 60)):
        if seconds >= k:
            return f"{seconds / k:.0f} {unit}"
    return f"{seconds:.0f} s"


def summary() -> str:
    """One line: the cache's folder, its files and their size (what `rtfem view` and `simulate` print)."""
    found = entries()
    return (f"{cache_dir()} ({len(found)} file{'s' if len(found) != 1 else ''}, {size_text(sum(e.size for e in found))};"
            " rtfem cache lists and clears it)")


def cmd_cache(args: argparse.Namespace) -> int:
    if args.clear:
        n, size = clear(args.kind)
        what = KINDS[args.kind] if args.kind else "file"
        print(f"cache       removed {n} {what}{'' if n == 1 else 's'} ({size_text(size)}) from {cache_dir()}")
        return 0
    found = [e for e in entries() if args.kind is None or e.kind == args.kind]
    moved = "from $RTFEM_CACHE" if os.environ.get("RTFEM_CACHE") else "set $RTFEM_CACHE to move it"
    print(f"cache       {cache_dir()} ({moved})")
    print(f"size        {size_text(sum(e.size for e in found))} in {len(found)} file{'s' if len(found) != 1 else ''}")
    for e in found:
        print(f"  {e.kind:8s} {size_text(e.size):>9s}  {_age(e.age):>7s} old  {e.path.name}  ({KINDS[e.kind]})")
    return 0


def add_cache_command(sub) -> None:
    p = sub.add_parser("cache", help="list (or --clear) the precomputed tet meshes, modes and reduced models kept here",
                       description="rtfem keeps what it precomputes (tet meshes, modal bases, reduced nonlinear models "
                       "with their cubature) in one folder, named by everything each was computed from, so that a "
                       "second launch of the same organ loads them in seconds. Lists that folder, or clears it.")
    p.add_argument("--clear", action="store_true", help="remove the files (of --kind, or all)")
    p.add_argument("--kind", choices=sorted(KINDS), help="only this kind of file")
    p.set_defaults(func=cmd_cache)


def report(**artefacts) -> str:
    """The line `rtfem view` and `simulate` print after the precompute: which artefacts (name=object,
    each with the ``info`` the cache stamps) came from the cache, and where the cache is."""
    artefacts = {k: (a.local["parent"] if getattr(a, "local", None) else a) for k, a in artefacts.items()}  # a patch's
    hits = [name.replace("_", " ") for name, a in artefacts.items() if a is not None and
            getattr(a, "info", {}).get("cache_hit")]
    return f"cache       {'loaded ' + ' and '.join(hits) + ' from' if hits else 'kept in'} {summary()}"
