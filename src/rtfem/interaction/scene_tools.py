"""Tools in scenes: rigid probes pressing any body, graspers holding them, each on its own device.

A :class:`SceneTool` follows a :class:`~rtfem.interaction.devices.Device` (its position at the end
of each step, metres in the scene's frame; what the hand feels goes back by ``set_force``).

- A **probe** is a rigid :class:`~rtfem.Tool` (a sphere by default). Each body's surface vertices
  within the scene's margin of it (after the trial steps) are contact points of the scene's one
  frictional problem, with the tool's push direction as normal and their slip relative to the
  tool's move over the step; so a probe pressing an organ against another organ, a plane or an
  attachment is solved with those contacts together. It sits at the device (``stiffness=None``), or
  is held to it by a virtual spring of ``stiffness`` N/m: the proxy is at x_d - (sum f) / k, which
  adds 1/k between every two points of the tool in A (w = b + A r) and shifts their gaps by last
  step's force (the gaps are evaluated with the proxy where last step's force leaves it).
- A **grasper** closes while the device's first button is held: on closing it takes the surface
  nodes of the nearest body within ``radius`` of its tip, and holds each, by its offset then, with
  a spring of ``stiffness / n`` N/m to the tip's position at the end of the step. The springs are
  the scene's implicit attachments with a moving anchor, so the hold is stable at any stiffness.
  Opening lets go.

What the hand feels is minus the tool's total force on the bodies; the scene records each body's
share as ``contacts[(body, tool)]``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import validate
from ..errors import ModelError
from ..drivers.base import displacements_at
from .contact import Tool

__all__ = ["SceneTool", "Keyframes"]

KINDS = ("probe", "grasper")
REACH = 1e3  # m: a scripted hand farther than this from the origin is a unit mistake (or overflows the contacts)
MAX_TIME = 1e6  # s


def _frames(normals: np.ndarray) -> np.ndarray:
    """(k, 3, 3): for each normal (k, 3), columns the unit normal and two unit tangents."""
    n = normals / np.linalg.norm(normals, axis=1)[:, None]
    x, y, z = n[:, 0], n[:, 1], n[:, 2]
    use_x = np.abs(x) < 0.9  # n x e_x = (0, z, -y); else n x e_y = (-z, 0, x)
    t1 = np.where(use_x[:, None], np.column_stack([0 * x, z, -y]), np.column_stack([-z, 0 * x, x]))
    t1 /= np.linalg.norm(t1, axis=1)[:, None]
    t2 = np.column_stack([y * t1[:, 2] - z * t1[:, 1], z * t1[:, 0] - x * t1[:, 2], x * t1[:, 1] - y * t1[:, 0]])
    return np.stack([n, t1, t2], axis=2)


def _frame(normal: np.ndarray) -> np.ndarray:
    """(3, 3) columns: the unit normal and two unit tangents."""
    return _frames(np.asarray(normal, dtype=float)[None])[0]


@dataclass
class _Springs:
    """A set of springs from nodes of body ``a`` to anchors in the world (the attachments' shape)."""

    name: str
    a: object
    nodes_a: np.ndarray
    anchor: np.ndarray
    stiffness: float
    b: object = None
    nodes_b: None = None


class SceneTool:
    """A probe or a grasper in a :class:`~rtfem.Scene`, following a device (see the module's docstring).

    Parameters
    ----------
    name : its name in the contact records.
    device : a :class:`~rtfem.Device` (position(t) in metres in the scene's frame, set_force(t, f);
        a grasper closes while ``buttons & 1``).
    kind : "probe" or "grasper".
    radius : the probe sphere's radius, or the grasper's reach from its tip (m).
    shape : a probe's :class:`~rtfem.Tool` instead of the sphere (a capsule, a jaw).
    stiffness : a probe's virtual coupling (N/m; None: the tool sits at the device); a grasper's
        total holding stiffness (N/m, shared by the nodes it holds; default 300).
    friction : a probe's Coulomb coefficient against the bodies.

    Raises
    ------
    ModelError
        A kind not listed, a device without position and set_force, a non-positive radius or
        stiffness, a negative friction, a shape that is not a Tool.
    """

    def __init__(self, name: str, device, *, kind: str = "probe", radius: float = 0.005, shape=None,
                 stiffness: float | None = None, friction: float = 0.0) -> None:
        if not isinstance(name, str) or not name:
            raise ModelError(f"a tool's name must be a non-empty string, got {validate.show(name)}")
        if kind not in KINDS:
            raise ModelError(f"tool {name}: kind={validate.show(kind)}; give one of {', '.join(map(repr, KINDS))}")
        if not (callable(getattr(device, "position", None)) and callable(getattr(device, "set_force", None))):
            raise ModelError(f"tool {name}: the device must have position(t) and set_force(t, force) (an rt.Device)")
        self.name, self.device, self.kind = name, device, kind
        self.radius = validate.positive(radius, f"tool {name}: radius", "a length in m")
        if shape is not None and not isinstance(shape, Tool):
            raise ModelError(f"tool {name}: shape must be an rt.Tool (sphere, capsule, jaw), got {validate.show(shape)}")
        if shape is not None and kind == "grasper":
            raise ModelError(f"tool {name}: a grasper holds what is within its radius; a shape is for probes")
        self.shape = shape if shape is not None else Tool.sphere(self.radius)
        if stiffness is None and kind == "grasper":
            stiffness = 300.0
        self.stiffness = None if stiffness is None else validate.positive(stiffness, f"tool {name}: stiffness", "N/m")
        self.friction = validate.in_range(friction, f"tool {name}: friction", 0.0, 10.0, what="Coulomb's coefficient")
        self.target = None  # the device's position at the end of the step
        self.proxy = None  # where the tool is (the device, or the coupled proxy)
        self.force = np.zeros(3)  # the tool's total force on the bodies in the last step
        self.held: _Springs | None = None

    def __repr__(self) -> str:
        return f"SceneTool({self.name!r}, kind={self.kind!r}, radius={self.radius:g})"

    @property
    def closed(self) -> bool:
        return bool(int(getattr(self.device, "buttons", 0) or 0) & 1)

    def begin(self, t: float, bodies) -> None:
        """Read the device for the step ending at ``t``; a grasper grabs or lets go."""
        x = validate.vector(self.device.position(t), f"tool {self.name}: the device's position", 3)
        self.target = np.asarray(x, dtype=float)
        if self.proxy is None:
            self.proxy = self.target.copy()
        if self.kind != "grasper":
            return
        if not self.closed:
            self.held = None
        elif self.held is None:
            self.held = self._grab(bodies)
        if self.held is not None:
            self.held.anchor = self.target + self.offsets

    def _grab(self, bodies) -> _Springs | None:
        best = None
        for body in bodies:
            x = body.X[body.surface] + displacements_at(body.driver, body.surface)
            d = np.linalg.norm(x - self.proxy, axis=1)
            near = np.flatnonzero(d <= self.radius)
            if near.size and (best is None or d[near].min() < best[0]):
                best = (d[near].min(), body, body.surface[near], x[near])
        if best is None:
            return None
        _, body, nodes, x = best
        self.offsets = x - self.proxy
        return _Springs(self.name, body, nodes, x.copy(), self.stiffness / nodes.size)

    def end(self, t: float, force: np.ndarray) -> None:
        """The tool's total force on the bodies this step: the proxy moves, the hand feels its opposite."""
        self.force = np.asarray(force, dtype=float)
        if self.kind == "probe" and self.stiffness is not None:
            self.proxy = self.target - self.force / self.stiffness
        else:
            self.proxy = self.target.copy()
        self.device.set_force(t, -self.force)

    def expected(self) -> np.ndarray:
        """Where a probe is taken to be for its gaps: the proxy that last step's force leaves."""
        if self.stiffness is None:
            return self.target
        return self.target - self.force / self.stiffness


class Keyframes:
    """A scripted hand: positions at times (linear between them, held before the first and after the
    last), and the first button held during ``closed`` intervals. ``Keyframes(...).device()`` is a
    :class:`~rtfem.ScriptedDevice` with those buttons (scene files' ``path`` and ``closed``).

    Parameters
    ----------
    path : (k, 4) rows t, x, y, z (s, m), times increasing.
    closed : (j, 2) rows t_on, t_off (s): the first button is held for t_on <= t < t_off.

    Raises
    ------
    ModelError
        Rows of the wrong shape, times not increasing, non-finite values, a position farther than
        :data:`REACH` from the origin.
    """

    def __init__(self, path, closed=()) -> None:
        p = validate.real_array(path, "path", 2)
        if p.ndim != 2 or p.shape[1] != 4 or p.shape[0] < 1:
            raise ModelError(f"path must be rows [t, x, y, z] (s, m), got shape {p.shape}")
        if np.any(np.diff(p[:, 0]) <= 0):
            raise ModelError("path: the times must increase from row to row")
        far = np.flatnonzero(np.abs(p[:, 1:]).max(axis=1) > REACH)
        if far.size:
            raise ModelError(f"path: row {far[0] + 1} puts the hand at {p[far[0], 1:].tolist()} m, more than {REACH:g} m "
                             "from the origin: give positions in metres (a mesh in millimetres wants scale = 1e-3)")
        if np.abs(p[:, 0]).max() > MAX_TIME:
            raise ModelError(f"path: times beyond {MAX_TIME:g} s: give them in seconds")
        c = np.zeros((0, 2)) if len(closed) == 0 else validate.real_array(closed, "closed", 2)
        if c.ndim != 2 or c.shape[1] != 2 or np.any(c[:, 1] <= c[:, 0]):
            raise ModelError("closed must be rows [t_on, t_off] (s) with t_off > t_on")
        self.path, self.closed = p, c

    def __call__(self, t: float) -> np.ndarray:
        p = self.path  # linear between the rows about t, held outside them (np.interp's rule)
        i = int(np.searchsorted(p[:, 0], t, side="right"))
        if i == 0 or i == p.shape[0]:
            return p[max(i - 1, 0), 1:].copy()
        s = (t - p[i - 1, 0]) / (p[i, 0] - p[i - 1, 0])
        return (1.0 - s) * p[i - 1, 1:] + s * p[i, 1:]

    def buttons(self, t: float) -> int:
        return int(any(on <= t < off for on, off in self.closed.tolist()))

    def device(self):
        """A :class:`~rtfem.ScriptedDevice` on this path, its first button held while closed."""
        from .devices.base import ScriptedDevice

        return ScriptedDevice(self, buttons=self.buttons)
