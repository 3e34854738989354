"""A scalpel in a scene (issue 57): an :class:`rtfem.Scalpel`'s blade on a device or a scripted path,
cutting one solid body of a :class:`~rtfem.Scene` as the scene steps it.

The scene steps the body (its weight, contacts, attachments and the tissue's share of the cutting
force together); the scalpel only places the blade, sweeps the cut surface against the body's
displacements after each step and has the body cut along it (:func:`rtfem.cut`, split mode, a piece cut
free falls away). A finished cut is swapped in at the start of the next step: the body's driver is the
one carried over to the cut model (its state node by node), its surface the cut mesh's (so the lips of
the cut touch the other bodies and tools), its attachments and graspers moved to the copies of the
nodes they held. By default each cut job is finished before the next step (``worker=False``: a scene run
is then the same from run to run); ``worker=True`` cuts in a worker process while the scene steps on.
"""

from __future__ import annotations

import copy

import numpy as np

from .. import validate
from ..errors import ModelError
from .scalpel import TOUGHNESS, Scalpel

__all__ = ["SceneScalpel", "CutJobFailed"]


class CutJobFailed(ModelError):
    """A scalpel's cut job failed with an error of its own (rt.cut's refusals are not this), raised by the
    scene's step after the step is taken: the scene can step on (see :meth:`SceneScalpel.raise_failure`)."""


class SceneScalpel:
    """A blade cutting body ``body`` of a scene, following ``device`` (see the module).

    Parameters
    ----------
    name : its name in the contact records.
    body : the :class:`~rtfem.interaction.scene.Body` it cuts: a full-order solid
        (``rt.DirectSimulator`` on an ``rt.SolidModel``, tet4 or tet10).
    device : an :class:`~rtfem.Device` (position(t), set_force(t, f)): the blade's tip, in metres in the
        scene's frame; the hand is given the cutting resistance.
    blade : (3,) m, from the tip to the heel (default (0, 0, 0.03): a 3 cm blade held upright).
    toughness : J/m^2, the energy a cut takes per unit area opened (default liver's, 164).
    advance : m, how far the blade moves before its strip joins the cut (default half an element edge).
    button : cut only while the device's first button is held (a scripted path's ``closed`` times; a
        live hand's button); False (default): the blade is in the tissue all along its path.
    worker : cut in a worker process while the scene steps on (True), or finish each cut before the next
        step (False, the default: the same run every time).

    Raises
    ------
    ModelError
        What :class:`rtfem.Scalpel` refuses (a body that is not a full-order solid, a blade of no length,
        a negative toughness), a device without position and set_force.
    """

    def __init__(self, name: str, body, device, *, gravity=(0.0, 0.0, -9.81), blade=(0.0, 0.0, 0.03),
                 toughness: float = TOUGHNESS, advance=None, button: bool = False, worker: bool = False) -> None:
        if not isinstance(name, str) or not name:
            raise ModelError(f"a scalpel's name must be a non-empty string, got {validate.show(name)}")
        if not (callable(getattr(device, "position", None)) and callable(getattr(device, "set_force", None))):
            raise ModelError(f"scalpel {name}: the device must have position(t) and set_force(t, force) (an rt.Device)")
        self.name, self.body, self.device = name, body.name, device
        self.button = validate.flag(button, f"scalpel {name}: button")
        self.wait = not validate.flag(worker, f"scalpel {name}: worker")
        try:
            self.cutter = Scalpel(body.driver, blade=blade, gravity=gravity, toughness=toughness, advance=advance,
                                  thread=False, worker=not self.wait)
        except ModelError as exc:
            raise ModelError(f"scalpel {name} on body {body.name}: {exc}") from None
        self.cutter.lift()
        self.force = np.zeros(3)  # on the hand, the last step's (the tissue took its opposite)
        self.applied = np.zeros(3)  # on the body, this step's: the opposite, where the tissue took it
        self.tip = None  # where the device put the blade's tip in the last step
        self.failure = None  # a cut job's error, raised at the end of the step (raise_failure)

    def __repr__(self) -> str:
        return f"SceneScalpel({self.name!r}, body={self.body!r})"

    @property
    def model(self):
        """The body's model as cut so far."""
        return self.cutter.model

    @property
    def cuts(self) -> int:
        return self.cutter.cuts

    def in_tissue(self) -> bool:
        """The blade in the tissue: always, or (``button``) while the device's first button is held."""
        return not self.button or bool(int(getattr(self.device, "buttons", 0) or 0) & 1)

    def begin(self, t: float) -> bool:
        """The step ending at ``t``: a finished cut swapped in (True: the body's model changed; the scene
        then rebuilds the body), and the blade placed at the device (or lifted out of the tissue)."""
        self._take_failure()  # (not raised by the blade's tick below, which would stop the scalpel for good)
        changed = self.cutter.take_cut()
        x = validate.vector(self.device.position(t), f"scalpel {self.name}: the device's position", 3)
        self.tip = np.asarray(x, dtype=float)
        if self.in_tissue():
            self.force = np.asarray(self.cutter.update(self.tip, t=t), dtype=float).copy()
        else:
            if not self.cutter.lifted:
                self.cutter.lift()
            self.force = np.zeros(3)
        return changed

    def loads(self) -> np.ndarray:
        """(n, 3) N on the body this step: the opposite of the hand's force, at the nodes the blade cuts
        (``applied``: their sum, what the scene records; none in a step that swapped a cut in)."""
        F = self.cutter.tissue_loads()
        self.applied = F.sum(axis=0)
        return F

    def end(self, t: float, U: np.ndarray, held: np.ndarray) -> None:
        """After the body's step to displacements ``U``: the strip swept, a cut started (and finished,
        unless in a worker; a piece with a node of ``held``, the body's nodes on springs or in a grasp, is
        kept as a fixed one is), the hand given its force."""
        self.cutter.held = held
        self.cutter.follow(U)
        if self.wait:
            self.cutter.join()
        if self._take_failure():
            self.force = np.zeros(3)
        self.device.set_force(t, self.force)

    def _take_failure(self) -> bool:
        """A cut job's failure (an error of its own: rt.cut's refusals are ``cutter.refused``) taken from the
        cutter, to be raised by :meth:`raise_failure` at the end of the step. True while one waits there."""
        err, self.cutter.error = self.cutter.error, None
        if err is not None and self.failure is None:
            self.failure = err
        return self.failure is not None

    def raise_failure(self) -> None:
        """Raise the failure of a cut job (the scene does at the end of a step, the step taken: the body stepped
        uncut there, the hand given zero force); the next step goes on, and the next strip's job takes the
        strips of the one that failed with its own. A job in a worker that failed meanwhile is raised at the
        end of a later step."""
        err, self.failure = self.failure, None
        if err is not None:
            raise CutJobFailed(f"scalpel {self.name}: a cut job failed ({type(err).__name__}: {err}); body {self.body} "
                             "stepped on uncut there, the hand was given zero force, and the next strip's cut job tries "
                             "those strips again (step on to go on)") from err

    def remap(self, nodes) -> tuple[np.ndarray, np.ndarray]:
        """The last cut's nodes that are entries of ``nodes`` (of the model before it; repeats allowed) or
        copies of them: (those nodes, the index in ``nodes`` of the entry each is). A node the cut moved
        onto its surface is still itself; one it added on a split edge is none of them."""
        info = self.model.cut_info
        parent, n0 = np.asarray(info["parent"]), int(info["uncut"])
        nodes = np.asarray(nodes, dtype=np.int64).ravel()
        new = np.flatnonzero(parent < n0)
        order = np.argsort(nodes, kind="stable")
        lo = np.searchsorted(nodes[order], parent[new], "left")
        count = np.searchsorted(nodes[order], parent[new], "right") - lo
        first = np.repeat(lo - np.cumsum(count) + count, count)  # each new node once per entry of its parent
        return np.repeat(new, count), order[first + np.arange(first.size)]

    def state(self) -> dict:
        """What :meth:`set_state` puts back (a scene viewer's kept state): the model and driver as cut so
        far, the surface swept, the stroke, the forces (the cut job in progress finished first)."""
        c = self.cutter
        c.join()
        out = {k: getattr(c, k) for k in _STATE}
        out.update(latencies=list(c.latencies), _added=list(c._added), scene=(self.force.copy(), self.tip))
        return out

    def set_state(self, state: dict) -> None:
        """Back to a :meth:`state`: the cuts made since are undone (the body is the scene's to put back)."""
        c = self.cutter
        c.join()
        for k in (*_STATE, "latencies", "_added"):
            setattr(c, k, list(state[k]) if k in ("latencies", "_added") else state[k])
        self.force, self.tip = state["scene"][0].copy(), state["scene"][1]
        self.failure = c.error = None  # (a failure of a cut since undone)

    def close(self) -> None:
        """Stop its cut worker process, if any."""
        self.cutter.close()


#: what a scalpel's state holds of its rt.Scalpel (all replaced, never changed in place, as it cuts)
_STATE = ("driver", "solid", "shown", "transfer", "last_transfer", "vertices", "triangles", "_applied", "_tried",
          "cuts", "removed_mass", "refused", "_last", "_anchor", "_velocity", "_mid", "_t_tick", "resistance", "_push",
          "lifted", "_blade", "force", "_ready", "_restroke")


#: the scene's caches of a body's nodes and compliances, stale once a body is cut
_CACHES = ("_spring_nodes_kept", "_springs_kept", "_held_cache", "_pair_cache", "_compliance_cache")


def recut(scene, scalpel: SceneScalpel) -> None:
    """Body ``scalpel.body`` of ``scene`` rebuilt on the cut model the scalpel just swapped in: its driver
    and surface the cut's, its held loads shared among each node's copies, the springs on its nodes
    (attachments and grasps) moved to their copies, each copy held as the node was (a node the cut moved
    onto its surface takes its anchor along: no spring is stretched by the cut), the scene's caches of it
    dropped. The scene's lists of bodies and attachments are replaced, not changed (new Body and
    Attachment objects): a reader holding the old ones (a frame being drawn, a kept state) sees them whole."""
    k = next(i for i, b in enumerate(scene.bodies) if b.name == scalpel.body)
    old = scene.bodies[k]
    new = type(old)(old.name, scalpel.cutter.driver, scalpel.model.mesh, _masses(old, scalpel))
    if hasattr(old, "model"):
        new.model = scalpel.model
    copies, of = scalpel.remap(np.arange(old.driver.n_nodes))
    share = np.bincount(of, minlength=old.driver.n_nodes)[of]
    new.loads[copies] = old.loads[of] / share[:, None]

    def moved(nodes):  # the springs' nodes on the cut body, where each entry went, and how far the cut moved it
        to, pick = scalpel.remap(nodes)
        return to, pick, new.X[to] - old.X[np.asarray(nodes)[pick]]
    attachments = []
    for att in scene.attachments:
        if att.a is old or att.b is old:
            att = copy.copy(att)
        if att.a is old:
            att.nodes_a, pick, d = moved(att.nodes_a)
            att.a = new
            if att.b is None:
                att.anchor = att.anchor[pick] + d
            else:
                att.nodes_b, att.rest = att.nodes_b[pick], att.rest[pick] - d
        elif att.b is old:
            att.nodes_b, pick, d = moved(att.nodes_b)
            att.b, att.nodes_a, att.rest = new, att.nodes_a[pick], att.rest[pick] + d
        attachments.append(att)
    for tool in scene.tools:
        held = tool.held
        if held is not None and held.a is old:
            held = copy.copy(held)
            held.nodes_a, pick, d = moved(held.nodes_a)
            held.a, held.anchor = new, held.anchor[pick] + d
            tool.held, tool.offsets = held, tool.offsets[pick] + d
    drop_caches(scene)
    scene.attachments = attachments
    scene.bodies = [new if b is old else b for b in scene.bodies]


def _masses(old, scalpel):
    """The cut body's nodal masses: its model's (None) where the body had its model's; else those, each
    node's share of its model's mass carried over (a weightless body stays weightless)."""
    before = np.asarray(old.driver.model.mass_diagonal, dtype=float).reshape(old.driver.n_nodes, -1)[:, 0]
    if np.array_equal(old.masses, before):
        return None
    share = np.divide(old.masses, before, out=np.zeros_like(before), where=before > 0)
    after = np.asarray(scalpel.model.mass_diagonal, dtype=float).reshape(scalpel.model.n_nodes, -1)[:, 0]
    return after * (scalpel.cutter.last_transfer @ share)


def drop_caches(scene) -> None:
    """Forget the scene's caches of its bodies' nodes and compliances (a body was cut, or put back)."""
    for name in _CACHES:
        scene.__dict__.pop(name, None)
