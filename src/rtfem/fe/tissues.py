"""Sourced tissue parameters (issue 58): the sets of ``rtfem/data/tissue.toml`` (a copy of the
project's sourced table: every number read in a source whose address, words and confidence it
keeps; nothing filled in from memory), as materials the models take.

A set becomes a material in its own law where the set gives that law's parameters: a linear set's
E (or its shear modulus G, E = 2 G (1 + nu)), a neo-Hookean set's C10 and bulk modulus, an Ogden
set's terms as printed. What is not in the set is said plainly in :attr:`TissueSet.derived`: a
Poisson's ratio assumed (the caller's, default 0.45), rtfem's default density, and a law made
from a set of another law (a neo-Hookean with the small-strain shear modulus and bulk modulus of a
linear set). A set that does not give its law's parameters (the brain's Mooney-Rivlin, whose
energy's normalisation was not read) is refused in that law; it can still be asked for as a
neo-Hookean of its shear modulus.

    >>> liver = rt.tissue("liver")          # the first set named liver; which=1 the next
    >>> print(liver)                         # the values, the citation, the confidence, what is derived
    >>> model = rt.SolidModel(mesh, liver.material)
    >>> rt.tissue("liver", law="neo-hookean").material   # derived from the linear set, and said so
"""

from __future__ import annotations

from dataclasses import dataclass, field
from importlib import resources

from .. import validate
from ..errors import ModelError

__all__ = ["TissueSet", "tissue", "tissues", "DEFAULT_NU"]

DEFAULT_NU = 0.45  # the Poisson's ratio assumed where a set gives none (soft tissue: 0.45 .. 0.49)
_LAWS = ("linear", "neo-hookean", "ogden")


@dataclass(frozen=True)
class TissueSet:
    """One sourced parameter set and the material made of it (what :func:`tissue` returns; frozen).

    Parameters
    ----------
    name, species : the tissue and the species, as the table gives them.
    law : the set's own law ("linear", "neo-hookean", "ogden", "mooney-rivlin").
    parameters : the set's values as the table gives them (SI).
    citation, source, quote : the publication, the address it was read at, the words read.
    confidence : "table", "abstract" or "secondary" (see the table's header).
    note, test : the table's note and the test the values come from.
    made_as : the law the material was made in.
    material : the rt.Material or law made of the set.
    derived : each thing that did not come from the set, said.

    Raises
    ------
    Nothing: it is built by :func:`tissue`, which checks.
    """

    name: str
    species: str
    law: str
    parameters: dict
    citation: str
    source: str
    quote: str
    confidence: str
    note: str
    test: str
    made_as: str
    material: object
    derived: list = field(default_factory=list)

    def __str__(self) -> str:
        values = ", ".join(f"{k} = {v}" for k, v in self.parameters.items())
        lines = [f"{self.name} ({self.species}), {self.law}: {values}",
                 f"  source: {self.citation}", f"  read at: {self.source} (confidence: {self.confidence})",
                 f"  as: {self.material!r}"]
        lines += [f"  derived: {d}" for d in self.derived]
        return "\n".join(lines)


def _table() -> list[dict]:
    import tomllib

    text = (resources.files("rtfem") / "data" / "tissue.toml").read_text(encoding="utf-8")
    return tomllib.loads(text)["tissue"]


def tissues(name: str | None = None) -> list[dict]:
    """The table's sets (dicts as written), or those whose name is ``name`` (case-insensitive)."""
    sets = _table()
    if name is None:
        return sets
    return [s for s in sets if s["name"].lower() == str(name).strip().lower()]


def tissue(name: str, *, law: str | None = None, nu: float | None = None, density: float = 1060.0,
           which: int = 0) -> TissueSet:
    """The sourced set ``name`` (the ``which``-th of that name in the table) as a material.

    Parameters
    ----------
    name : a tissue of the table: liver, liver capsule (Glisson's capsule), brain, gallbladder,
        stomach, skin, fat, muscle.
    law : the law to make ("linear", "neo-hookean", "ogden"); default the set's own. Another
        law is derived from the set's small-strain moduli, and said so.
    nu : the Poisson's ratio where the set gives none (default :data:`DEFAULT_NU`, said so); a
        set's own nu is kept (giving another is refused).
    density : kg/m^3 (no set gives one; rtfem's default 1060, said so).
    which : which set of that name (0 the first).

    Returns
    -------
    TissueSet

    Raises
    ------
    ModelError
        A name the table does not have (the names listed), ``which`` past its sets, a law the set
        cannot give, a nu other than the set's own.
    """
    found = tissues(name)
    if not found:
        names = sorted({s["name"] for s in _table()})
        raise ModelError(f"no sourced set for tissue {name!r}; the table has: {', '.join(names)}")
    which = validate.count(which, "which", 0, len(found) - 1)
    row = found[which]
    law = row["law"] if law is None else validate.choice(str(law).lower(), "law", _LAWS)
    if law not in _LAWS:
        raise ModelError(f"the {row['name']} set ({law}, {row['citation'][:60]}...) does not give its law's constants "
                         f"({row.get('note', '')[:160]}); ask for law='neo-hookean' (a neo-Hookean of its shear modulus)")
    derived = []
    own_nu = row.get("nu")
    if nu is not None and own_nu is not None and float(nu) != float(own_nu):
        raise ModelError(f"the {row['name']} set gives nu = {own_nu}; nu={nu} would not be the source's")
    assumed = own_nu is None  # said where it is used
    nu = float(own_nu) if own_nu is not None else DEFAULT_NU if nu is None else validate.number(nu, "nu", "a Poisson's ratio")
    derived.append(f"density = {density:g} kg/m^3: not in the set, rtfem's default" if density == 1060.0
                   else f"density = {density:g} kg/m^3: given, not in the set")
    material = _make(row, law, nu, assumed, density, derived)
    params = {k: v for k, v in row.items() if k not in ("name", "species", "law", "citation", "source", "quote",
                                                          "confidence", "note", "test", "in_vivo", "strain_range")}
    return TissueSet(row["name"], row.get("species", ""), row["law"], params, row["citation"], row["source"],
                     row["quote"], row["confidence"], row.get("note", ""), row.get("test", ""), law, material, derived)


def _make(row: dict, law: str, nu: float, assumed: bool, density: float, derived: list):
    """The material of ``row`` in ``law`` (``assumed``: nu is not the set's), each derivation appended
    to ``derived``."""
    from .hyperelastic import NeoHookean, Ogden
    from .material import Material

    own = row["law"]
    mu = _shear_modulus(row, nu)
    if assumed and (law == "linear" or "E" in row or (law == "neo-hookean" and "kappa" not in row)):
        derived.insert(0, f"nu = {nu:g}: not in the set, assumed")
    if law == "linear":
        if "G" in row:
            derived.append(f"E = 2 G (1 + nu) = {2 * mu * (1 + nu):.6g} Pa from the set's shear modulus G = {row['G']:g} Pa")
        if own != "linear":
            derived.append(f"linear: E and nu of the {own} set's moduli at rest (mu = {mu:.6g} Pa), not a linear "
                           "set of the source")
        return Material(E=2 * mu * (1 + nu), nu=nu, density=density)
    if law == "neo-hookean":
        kappa = row.get("kappa")
        if own != "neo-hookean":
            derived.append(f"neo-Hookean derived from the {own} set: mu = its small-strain shear modulus ({mu:.6g} Pa)"
                           + ("" if kappa is not None else f", kappa = 2 mu (1 + nu) / (3 (1 - 2 nu)) with nu {nu:g}")
                           + "; the source fitted no neo-Hookean")
        if kappa is None:
            kappa = 2 * mu * (1 + nu) / (3 * (1 - 2 * nu))
        return NeoHookean(mu=mu, kappa=float(kappa), density=density)
    if own != "ogden":
        raise ModelError(f"the {row['name']} set is {own}: an Ogden law cannot be made of it (take its own law or "
                         "law='neo-hookean')")
    derived.append("Ogden's constants as printed; whether the source's mu is FEBio's c1 (2 mu_1 here) was not checked")
    return Ogden(mu=list(row["mu"]), alpha=list(row["alpha"]), kappa=float(row["kappa"]), density=density)


def _shear_modulus(row: dict, nu: float) -> float:
    """The set's small-strain shear modulus (Pa)."""
    if "G" in row:
        return float(row["G"])
    if "E" in row:
        return float(row["E"]) / (2 * (1 + nu))
    if "c10" in row:
        return 2 * float(row["c10"])
    if "mu" in row:
        return float(sum(row["mu"])) if isinstance(row["mu"], list) else float(row["mu"])
    if "shear_modulus" in row:
        return float(row["shear_modulus"])
    raise ModelError(f"the {row['name']} set gives no modulus rtfem can use")


def tissue_from_text(text: str, material, *, nu_given: bool = False) -> TissueSet | None:
    """The set a command line's ``--material TISSUE`` or ``TISSUE#N`` (the N-th of that name, from 1)
    names, with ``material``'s nu where the set has none and its density; None when ``text`` names
    no tissue of the table. ``nu_given``: ``material``'s nu was asked for (a scene file's ``nu``),
    so a set with a nu of its own refuses another."""
    name, hash_, number = str(text).strip().partition("#")
    found = tissues(name)
    if not found:
        return None
    try:
        if hash_ and not number.strip():
            raise ValueError
        which = int(number) - 1 if number else 0
    except ValueError:
        raise ModelError(f"--material {text!r}: after '#' give which {name} set, 1 .. {len(found)}") from None
    if not 0 <= which < len(found):
        raise ModelError(f"--material {text!r}: the table has {len(found)} {name} set(s); give #1 .. #{len(found)}")
    nu = None if found[which].get("nu") is not None and not nu_given else material.nu
    return tissue(name, which=which, nu=nu, density=material.density)
