"""The impedance map at run time (paper 4.1): :class:`ImpedanceDriver` superposes a map's unit-load
responses under the forces applied, quasi-static or following the force history."""

from __future__ import annotations

import math
from typing import Mapping

import numpy as np

from .. import validate
from ..errors import ModelError
from ..fe.material import Damping
from ..fe.protocol import check_model
from ..reduction.modal import mesh_fingerprint

from .impedance import ImpedanceMap

__all__ = ["ImpedanceDriver"]


class ImpedanceDriver:
    """Impedance maps as a Driver (paper 4.1): the organ answers a contact force with the
    precomputed responses of its loaded nodes; nothing is solved at run time.

    ``step(forces)`` makes ``forces`` the current loads (on loaded nodes of the maps). The
    contact (``predict``, ``step_compliance``) is quasi-static, as in the paper: with no load
    the organ is at rest (``predict`` is zero) and W is the exact static point compliance G_pp.
    The drawn field depends on ``dynamic``:

    * ``dynamic=False``: the static columns of the current loads, superposed.
    * ``dynamic=True``: Duhamel superposition of the force history. Each change of a node's
      load is a step load switched on when it happens; changes within ``resolution`` seconds
      (default the map's first sample time) are merged into one, and loads older than the
      last sample have settled into one static load, so the history stays short (at most
      ``times[-1] / resolution`` live entries per node). The field is the map's sampled step
      responses, linear in time between samples.

    Maps: one :class:`ImpedanceMap` or several of the same mesh; :meth:`on_demand` builds a
    node's map the first time it is prepared (:meth:`prepare`, called by Grasp and Probe
    when a vertex is first touched, outside the force loop).

    Parameters
    ----------
    maps : an :class:`~rtfem.ImpedanceMap` or a list of maps of the same mesh.
    dt : time step (s).
    dynamic : the drawn field by Duhamel superposition of the force history (True) or the
        static columns of the current loads (False).
    resolution : with ``dynamic``, changes of a node's load closer than this (s) are merged
        (default: the maps' first sample time).

    Raises
    ------
    ModelError
        No maps, maps of different meshes, a bad dt or resolution; at run time, a load on a
        node no map has (prepare it, or build its map).
    """

    def __init__(self, maps, dt: float = 1e-3, *, dynamic: bool = False, resolution: float | None = None) -> None:
        maps = [maps] if isinstance(maps, ImpedanceMap) else maps
        if isinstance(maps, (str, bytes)) or not hasattr(maps, "__iter__"):
            raise ModelError(f"maps={validate.show(maps)} must be an ImpedanceMap or a list of them")
        maps = list(maps)
        if not maps or not all(isinstance(m, ImpedanceMap) for m in maps):
            raise ModelError("maps must hold at least one ImpedanceMap (ImpedanceDriver.on_demand builds them as needed)")
        self._init(maps[0].n_nodes, maps[0].fingerprint, dt, dynamic, resolution, None)
        for m in maps:
            self.add(m)

    @classmethod
    def on_demand(cls, model, damping: Damping | None = None, dt: float = 1e-3, *, dynamic: bool = True,
                  resolution: float | None = None, **build_options) -> "ImpedanceDriver":
        """A driver with no map yet: :meth:`prepare` builds one per newly touched node with
        ``ImpedanceMap.build(model, damping, nodes=[node], **build_options)``."""
        check_model(model)
        if damping is not None and not isinstance(damping, Damping):
            raise ModelError(f"damping={validate.show(damping)} must be an rt.Damping (or None)")

        def build(nodes):
            return ImpedanceMap.build(model, damping, nodes=nodes, **build_options)

        self = cls.__new__(cls)
        self._init(model.n_nodes, mesh_fingerprint(model.mesh), dt, dynamic, resolution, build)
        return self

    def _init(self, n_nodes, fingerprint, dt, dynamic, resolution, builder) -> None:
        self.dt = validate.time_step(dt)
        self.dynamic = validate.flag(dynamic, "dynamic")
        self.resolution = None if resolution is None else validate.positive(resolution, "resolution",
                                                                             "a time in s")
        self.n_nodes = n_nodes
        self.fingerprint = fingerprint
        self.maps: list[ImpedanceMap] = []
        self._owner: dict[int, ImpedanceMap] = {}
        self._builder = builder
        self.time = 0.0
        self.steps = 0
        self._loads: dict[int, np.ndarray] = {}
        self._history: list[tuple[int, np.ndarray, float]] = []  # (node, force change, onset); -inf: settled
        self._live = None  # while a compiled HapticLoop ticks this driver: the loads it applies now

    # ---------------------------------------------------------------- maps
    def add(self, imap: ImpedanceMap) -> None:
        """Use ``imap`` for its loaded nodes too (it must belong to the same mesh)."""
        if not isinstance(imap, ImpedanceMap):
            raise ModelError(f"imap={validate.show(imap)} must be an ImpedanceMap")
        if imap.n_nodes != self.n_nodes or imap.fingerprint != self.fingerprint:
            raise ModelError("this impedance map belongs to another mesh than the driver's")
        self.maps.append(imap)
        for node in imap.loaded.tolist():
            self._owner.setdefault(node, imap)

    def _map(self, node: int) -> ImpedanceMap:
        m = self._owner.get(node)
        if m is None:
            raise ModelError(f"node {node} is not a loaded node of this driver's impedance maps"
                             + ("; prepare([node]) builds its map" if self._builder else "; build a map with it"))
        return m

    def prepare(self, nodes) -> None:
        """Make sure every node has a map (built now when the driver builds on demand)."""
        nodes = validate.nodes(nodes, self.n_nodes)
        missing = [n for n in nodes.tolist() if n not in self._owner]
        if missing and self._builder is not None:
            self.add(self._builder(missing))
        for n in missing:
            self._map(n)

    @property
    def _settle(self) -> float:
        return max(m.times[-1] for m in self.maps) if self.maps else 0.0

    # ---------------------------------------------------------------- stepping
    def _parse(self, forces) -> dict[int, np.ndarray]:
        loads: dict[int, np.ndarray] = {}
        if forces is None:
            return loads
        if type(forces) is dict and len(forces) == 1:  # the haptic loop's one contact: checked inline
            ((node, f),) = forces.items()
            if type(node) is int and node in self._owner and type(f) is tuple and len(f) == 3 \
                    and all(type(v) is float and math.isfinite(v) for v in f):
                return {node: np.array(f)} if any(f) else loads
        if isinstance(forces, Mapping):
            for node, f in forces.items():
                i = validate.node(node, self.n_nodes, "force key")
                v = validate.vector(f, f"force on node {i}", 3)
                self._map(i)
                loads[i] = loads.get(i, 0.0) + v
        else:
            F = validate.forces(forces, self.n_nodes)
            for i in np.flatnonzero(np.any(F != 0, axis=1)).tolist():
                self._map(i)
                loads[i] = F[i]
        return {i: f for i, f in loads.items() if np.any(f)}

    def step(self, forces=None) -> None:
        """Make ``forces`` the current loads and advance ``dt`` (checked whole first)."""
        loads = self._parse(forces)
        if self.dynamic:
            self._record(loads)
        self._loads = loads
        self.steps += 1
        self.time = self.steps * self.dt

    def _record(self, loads: dict[int, np.ndarray]) -> None:
        """The load changes of this step into the history (merged per node within the resolution)."""
        t = self.time
        res = self.resolution if self.resolution is not None else min((m.times[0] for m in self.maps), default=self.dt)
        for node in set(loads) | set(self._loads):
            df = loads.get(node, 0.0) - self._loads.get(node, 0.0)
            if not np.any(df):
                continue
            last = next((k for k in range(len(self._history) - 1, -1, -1) if self._history[k][0] == node), None)
            if last is not None and t - self._history[last][2] < res:
                n_, f_, onset = self._history[last]
                self._history[last] = (n_, f_ + df, onset)
            else:
                self._history.append((node, np.array(df, dtype=float), t))
        # settled loads: one static entry per node
        settle, now = self._settle, t + self.dt
        if any(now - onset > settle for _, _, onset in self._history if onset > -np.inf):
            settled: dict[int, np.ndarray] = {}
            live = []
            for node, df, onset in self._history:
                if now - onset > settle:
                    settled[node] = settled.get(node, 0.0) + df
                else:
                    live.append((node, df, onset))
            self._history = [(n, f, -np.inf) for n, f in settled.items() if np.any(f)] + live

    # ---------------------------------------------------------------- contact (quasi-static)
    def predict(self, node) -> np.ndarray:
        if type(node) is not int or not 0 <= node < self.n_nodes:
            validate.node(node, self.n_nodes)
        return np.zeros(3)

    def step_compliance(self, node) -> np.ndarray:
        i = validate.node(node, self.n_nodes)
        return self._map(i).point_compliance(i)

    def predict_at(self, nodes) -> np.ndarray:
        return np.zeros((validate.nodes(nodes, self.n_nodes).size, 3))

    def step_compliances(self, nodes, loaded=None) -> np.ndarray:
        """The static cross compliances (3k, 3l) G_ab = [K^-1]_ab of a contact set, from the maps of
        the loaded nodes (zero beyond a map's kept neighbourhood; the diagonal blocks exact)."""
        nodes = validate.nodes(nodes, self.n_nodes)
        loaded = nodes if loaded is None else validate.nodes(loaded, self.n_nodes)
        W = np.zeros((3 * nodes.size, 3 * loaded.size))
        for b, j in enumerate(loaded.tolist()):
            W[:, 3 * b:3 * b + 3] = self._map(j)._columns(j, nodes, None).reshape(-1, 3)
            same = np.flatnonzero(nodes == j)
            for a in same.tolist():
                W[3 * a:3 * a + 3, 3 * b:3 * b + 3] = self._map(j).point_compliance(j)
        return W

    # ---------------------------------------------------------------- the field
    def _entries(self):
        """(node, force, delay since its onset; inf for a static or settled load) of what is
        superposed now."""
        if not self.dynamic:
            live = self._live
            return [(p, f, np.inf) for p, f in (self._loads if live is None else live()).items()]
        return [(p, f, self.time - onset) for p, f, onset in self._history]  # onset -inf: settled

    def displacements_at(self, nodes) -> np.ndarray:
        if not (type(nodes) is np.ndarray and nodes.dtype == np.int64 and nodes.ndim == 1 and nodes.size
                and 0 <= nodes.min() and nodes.max() < self.n_nodes):
            nodes = validate.nodes(nodes, self.n_nodes)
        u = np.zeros((nodes.size, 3))
        for p, f, delay in self._entries():
            u += self._owner[p]._columns(p, nodes, delay) @ f
        return u

    def displacement(self, node) -> np.ndarray:
        return self.displacements_at([validate.node(node, self.n_nodes)])[0]

    def displacements(self) -> np.ndarray:
        u = np.zeros((self.n_nodes, 3))
        for p, f, delay in self._entries():
            self._owner[p]._superpose(u, p, f, delay)
        return u

    # ---------------------------------------------------------------- state
    def reset(self) -> None:
        self._loads = {}
        self._history = []
        self.time = 0.0
        self.steps = 0

    def get_state(self) -> dict:
        return {"loads": {p: f.copy() for p, f in self._loads.items()},
                "history": [(p, f.copy(), onset) for p, f, onset in self._history], "steps": self.steps}

    def set_state(self, state) -> None:
        if not isinstance(state, Mapping) or not {"loads", "steps"} <= set(state) <= {"loads", "history", "steps"} \
                or not isinstance(state["loads"], Mapping):
            raise ModelError("state must be a mapping with 'loads' ({node: force}), 'steps' and optionally 'history', "
                             "as get_state() returns")
        loads = {}
        for node, f in state["loads"].items():
            i = validate.node(node, self.n_nodes, "load node")
            self._map(i)
            loads[i] = validate.vector(f, f"load on node {i}", 3)
        history = []
        for h in validate.entries(state.get("history", []), "state['history']", "history entry", 3,
                                  "(node, force change, onset)"):
            i = validate.node(h[0], self.n_nodes, "history node")
            self._map(i)
            onset = validate.instant(h[2], "onset")  # -inf: a settled load
            history.append((i, validate.vector(h[1], f"force change on node {i}", 3), onset))
        steps = validate.count(state["steps"], "state['steps']", 0)
        self._loads, self._history, self.steps, self.time = loads, history, steps, steps * self.dt


ImpedanceMap._driver = ImpedanceDriver
