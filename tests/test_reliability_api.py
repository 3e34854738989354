"""Every public entry point, every argument, hostile values (issue 10).

For each argument of each public call, a list of values that make no sense for it (NaN, a
string where a number belongs, a float or a bool where a node index belongs, a negative
count, a 2x2 array where a point belongs, ...). Each one must be refused with an
:class:`rt.RtfemError` that says what was wrong -- never a bare numpy/builtin exception -- and a
refused call on a stateful object (a model, a simulator, a probe, a grasp, a session) must
leave every piece of its state as it was.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest

import rtfem as rt
from rtfem.io import write_pvd, write_vtu
from rtfem.viewer.session import Session, Settings

NAN, INF = float("nan"), float("inf")
OBJ = object()
M22 = np.ones((2, 2))

POSITIVE = [None, "abc", NAN, INF, -INF, -1.0, 0.0, True, [], {}, OBJ, M22]
NONNEG = [None, "abc", NAN, INF, -1.0, True, [], OBJ, M22]
OPTIONAL_POSITIVE = ["abc", NAN, INF, -1.0, 0.0, True, [], OBJ, M22]
COUNT = [None, "abc", NAN, INF, -1, 0, 2.5, True, [], OBJ]
CHOICE = ["nonsense", None, 3, OBJ, ""]
FLAG = ["yes", "no", 2, NAN, OBJ]
POINT = [None, "abc", [1.0, 2.0], [NAN, 0.0, 0.0], [INF, 0.0, 0.0], OBJ, M22, 5.0, ["a", "b", "c"]]
TIMES = [[], [NAN], [-1.0], [0.2, 0.1], "abc", OBJ, [[0.1, 0.2]], [INF], None]
PATHS = [None, 5, "", OBJ]


def nodes_bad(n: int) -> list:
    return [-1, n, 10**9, 2.5, True, "3", None, NAN, [], OBJ, np.float64(3.0)]


def forces_bad(n: int, node: int) -> list:
    f = (0.1, 0.0, 0.0)
    return [{node: (NAN, 0.0, 0.0)}, {node: ("a", 0.0, 0.0)}, {node: (1.0, 2.0)}, {2.5: f}, {True: f}, {-1: f},
            {10**9: f}, {"3": f}, {node: None}, {node: f, -1: f}, {node: f, 10**9: f}, np.ones((3, 3)),
            np.full((n, 3), NAN), "abc", 5, OBJ, {np.float64(3.0): f}]


@functools.lru_cache(maxsize=None)
def world() -> dict:
    mesh = rt.meshes.liver(2)
    model = rt.ShellModel(mesh, rt.Material())
    model.fix("attachment")
    modes = rt.modal_analysis(model, 8)
    node = int(model.mesh.groups["probe"][0])
    damping = rt.Damping(alpha=8.0)
    imap = rt.ImpedanceMap.build(model, damping, nodes=[node], modes=modes)
    other = rt.TriMesh(np.asarray(mesh.vertices) * 2.0, mesh.triangles, groups=mesh.groups)  # same size, another organ
    return dict(mesh=mesh, model=model, modes=modes, node=node, n=mesh.n_vertices, damping=damping, imap=imap,
                other=other, far=np.asarray(mesh.vertices)[node] + 0.05 * mesh.vertex_normals()[node])


def _sim():
    w = world()
    return rt.ModalSimulator(w["modes"], 1e-3, w["damping"], static_correction=True)


def _direct():
    w = world()
    return rt.DirectSimulator(w["model"], 1e-3, w["damping"])


def _sim_state(sim) -> list:
    return [sim.get_state(), sim.displacements(), sim.time]


def _direct_state(sim) -> list:
    return [sim.displacements(), sim.time, sim.steps]


def _square() -> tuple[np.ndarray, np.ndarray]:
    return np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float), np.array([[0, 1, 2], [0, 2, 3]])


class Entry:
    """A public call: ``call(obj, **kwargs)``; ``make()`` gives a fresh object (or None)."""

    def __init__(self, name, call, base, bad, make=None, snapshot=None):
        self.name, self.call, self.base, self.bad = name, call, base, bad
        self.make, self.snapshot = make, snapshot


def _entries() -> list[Entry]:
    w = world()
    n, node = w["n"], w["node"]
    mesh, model, modes, imap = w["mesh"], w["model"], w["modes"], w["imap"]
    V, T = _square()
    sim_shared = _sim()
    direct_shared = _direct()
    sim_shared.step({node: (0.0, 0.0, -0.05)})
    direct_shared.step({node: (0.0, 0.0, -0.05)})
    sldm = rt.SLDM(model, w["damping"])
    f = {node: (0.0, 0.0, -0.1)}
    E = []
    add = lambda *a, **k: E.append(Entry(*a, **k))  # noqa: E731

    add("Material", lambda o, **k: rt.Material(**k), dict(E=3e4, nu=0.45, thickness=4e-3, density=1060.0),
        dict(E=POSITIVE, thickness=POSITIVE, density=POSITIVE,
             nu=[None, "abc", NAN, INF, 0.5, -1.0, 0.7, True, [], OBJ]))
    add("Damping", lambda o, **k: rt.Damping(**k), dict(alpha=8.0),
        dict(alpha=NONNEG, beta=NONNEG, zeta=["x", NAN, -0.1, [NAN], [-1.0], OBJ, {}, M22, True]))
    add("TriMesh", lambda o, **k: rt.TriMesh(**k), dict(vertices=V, triangles=T),
        dict(vertices=[None, "abc", [], np.full((4, 3), NAN), np.ones((4, 4)), np.ones(5), OBJ, [[0, 0, "a"]] * 4],
             triangles=[None, "abc", [], [[0, 1, 9]], [[0, 1]], [[0, 1, 2.5]], [[-1, 1, 2]], OBJ, np.ones((1, 3, 1))],
             merge_tol=[NAN, -1.0, INF, "abc", OBJ], repair=FLAG,
             groups=["abc", 5, {"g": [99]}, {"g": "x"}, {"g": [0.5]}, {5: [0]}, {"g": [True]}]))
    add("load_mesh", lambda o, **k: rt.load_mesh(**k), dict(path="TINY_OBJ", scale=1.0),
        dict(path=PATHS + ["/no/such/file.obj", "TMPDIR"], scale=POSITIVE, repair=FLAG, merge_tol=[NAN, -1.0, "abc"]))
    add("meshes.plate", lambda o, **k: rt.meshes.plate(**k), dict(a=1.0, nx=2),
        dict(a=POSITIVE, b=[NAN, -1.0, 0.0, "abc", OBJ, True], nx=COUNT + [10**9], ny=[0, 2.5, "abc", 10**9],
             pattern=CHOICE))
    add("meshes.cylinder", lambda o, **k: rt.meshes.cylinder(**k), dict(radius=0.05, length=0.2, n_around=8, n_along=2),
        dict(radius=POSITIVE, length=POSITIVE, n_around=[2, 2.5, "abc", None, 10**9], n_along=[0, 2.5, "abc", 10**9]))
    add("meshes.hemisphere", lambda o, **k: rt.meshes.hemisphere(**k), dict(radius=0.05, n_rings=3),
        dict(radius=POSITIVE, n_rings=[0, 2.5, "abc", None, 10**9]))
    add("meshes.icosphere", lambda o, **k: rt.meshes.icosphere(**k), dict(radius=1.0, level=1),
        dict(radius=POSITIVE, level=[-1, 2.5, "abc", None, NAN, True, 99]))
    add("meshes.liver", lambda o, **k: rt.meshes.liver(**k), dict(level=1),
        dict(level=[0, -1, 2.5, "abc", None, NAN, True, 99]))
    add("ShellModel", lambda o, **k: rt.ShellModel(**k), dict(mesh=mesh, material=rt.Material()),
        dict(mesh=[None, "abc", 5, OBJ], material=[None, "abc", 5, OBJ], membrane=CHOICE, constraints=CHOICE,
             penalty=[None, "abc", NAN, INF, 0.5, 1.0, -5.0, OBJ, True], rotary_inertia=FLAG))

    def fresh_model():
        return rt.ShellModel(mesh, rt.Material())

    add("ShellModel.fix", lambda o, **k: o.fix(**k), dict(nodes=[0], dofs="all"),
        dict(nodes=[-1, 10**9, 2.5, "nogroup", [], None, NAN, True, OBJ, [0, 10**9], np.zeros(5, bool)],
             dofs=["q", 7, None, "", OBJ, [7], "xyzw"]),
        make=fresh_model, snapshot=lambda o: [o.fixed.copy()])
    add("ShellModel.release", lambda o, **k: o.release(**k), dict(nodes=[0]),
        dict(nodes=[-1, 10**9, 2.5, "nogroup", NAN, True, OBJ], dofs=["q", 7, "", OBJ]),
        make=lambda: fresh_model().fix("attachment"), snapshot=lambda o: [o.fixed.copy()])
    add("ShellModel.solve_static", lambda o, **k: model.solve_static(**k), dict(forces=f),
        dict(forces=forces_bad(n, node)))
    add("ShellModel.surface_compliance", lambda o, **k: model.surface_compliance(**k), dict(nodes=[node]),
        dict(nodes=[-1, 10**9, 2.5, NAN, True, OBJ, "abc"], method=CHOICE, memory=POSITIVE, allow_large=FLAG))
    add("ShellModel.pressure_forces", lambda o, **k: model.pressure_forces(**k), dict(pressure=10.0),
        dict(pressure=[None, "abc", NAN, INF, [], OBJ, True]))
    add("ShellModel.nearest_free_node", lambda o, **k: model.nearest_free_node(**k), dict(point=[0.0, 0.0, 0.0]),
        dict(point=POINT, displacements=[np.full((n, 3), NAN), np.ones((2, 3)), "abc", OBJ]))
    add("modal_analysis", lambda o, **k: rt.modal_analysis(**k), dict(model=model, n_modes=5),
        dict(model=[None, "abc", 5, OBJ, mesh], n_modes=COUNT + [10**9, "some"], sigma=[NAN, INF, "abc", OBJ, True],
             tol=[NAN, -1.0, INF, "abc", OBJ, 1.5], progress=["abc", 5, OBJ]))
    add("ModalBasis", lambda o, **k: rt.ModalBasis(**k),
        dict(omega=modes.omega, shapes=modes.shapes, fingerprint=modes.fingerprint),
        dict(omega=[None, "abc", np.full(8, NAN), -np.ones(8), modes.omega[::-1].copy(), np.ones(7), OBJ],
             shapes=[None, "abc", np.full((n, 3, 8), NAN), np.ones((n, 2, 8)), np.ones((n, 3, 7)), OBJ],
             fingerprint=[None, 5, OBJ]))
    add("ModalBasis.truncated", lambda o, **k: modes.truncated(**k), dict(n_modes=4),
        dict(n_modes=COUNT + [9, 10**9]))
    add("ModalSimulator", lambda o, **k: rt.ModalSimulator(**k),
        dict(modes=modes, dt=1e-3, damping=w["damping"], static_correction=True),
        dict(modes=[None, "abc", model, OBJ], dt=POSITIVE + [1e-300, 1e300], damping=["abc", 5, OBJ],
             integrator=CHOICE, static_correction=FLAG))
    sim_snap = _sim_state
    add("ModalSimulator.step", lambda o, **k: sim_shared.step(**k), dict(forces=f), dict(forces=forces_bad(n, node)),
        make=lambda: sim_shared, snapshot=sim_snap)
    add("ModalSimulator.run", lambda o, **k: sim_shared.run(**k), dict(forces=f, n_steps=2),
        dict(forces=forces_bad(n, node), n_steps=[-1, 2.5, "abc", None, NAN, True, OBJ]),
        make=lambda: sim_shared, snapshot=sim_snap)
    for meth in ("displacement", "predict", "step_compliance"):
        add(f"ModalSimulator.{meth}", lambda o, meth=meth, **k: getattr(sim_shared, meth)(**k), dict(node=node),
            dict(node=nodes_bad(n)), make=lambda: sim_shared, snapshot=sim_snap)
    add("ModalSimulator.prepare", lambda o, **k: sim_shared.prepare(**k), dict(nodes=[node]),
        dict(nodes=[-1, 10**9, 2.5, "abc", OBJ, [node, 10**9], True]), make=lambda: sim_shared, snapshot=sim_snap)
    z8 = np.zeros(8)
    add("ModalSimulator.set_state", lambda o, **k: sim_shared.set_state(**k), dict(state=sim_shared.get_state()),
        dict(state=[{}, {"q": np.full(8, NAN)}, "abc", {"q": [1, 2]}, None, 5, {"q": z8, "qdot": "x"},
                    {"q": z8, "steps": -1}, {"q": z8, "f_old": np.full(8, NAN)}, {"q": z8, "steps": 2.5}]),
        make=lambda: sim_shared, snapshot=sim_snap)
    add("DirectSimulator", lambda o, **k: rt.DirectSimulator(**k), dict(model=model, dt=1e-3, damping=w["damping"]),
        dict(model=[None, "abc", OBJ, mesh], dt=POSITIVE + [1e-300, 1e300], damping=["abc", 5], method=CHOICE))
    add("DirectSimulator.step", lambda o, **k: direct_shared.step(**k), dict(forces=f), dict(forces=forces_bad(n, node)),
        make=lambda: direct_shared, snapshot=_direct_state)
    for meth in ("displacement", "predict", "step_compliance"):
        add(f"DirectSimulator.{meth}", lambda o, meth=meth, **k: getattr(direct_shared, meth)(**k), dict(node=node),
            dict(node=nodes_bad(n)), make=lambda: direct_shared, snapshot=_direct_state)
    add("ModalSimulator.displacements_at", lambda o, **k: sim_shared.displacements_at(**k), dict(nodes=[node]),
        dict(nodes=[[-1], [10**9], [2.5], "abc", OBJ, True, None]), make=lambda: sim_shared, snapshot=sim_snap)
    add("DirectSimulator.set_state", lambda o, **k: direct_shared.set_state(**k), dict(state=direct_shared.get_state()),
        dict(state=[{}, "abc", None, 5, {**direct_shared.get_state(), "u": "x"},
                    {**direct_shared.get_state(), "u": np.full(3, NAN)}, {**direct_shared.get_state(), "steps": -1},
                    {**direct_shared.get_state(), "bogus": 1}]),
        make=lambda: direct_shared, snapshot=_direct_state)
    map_driver = imap.as_driver()

    def map_driver_snap(d):
        return [d.get_state(), d.displacements(), d.time]

    add("ImpedanceDriver.step", lambda o, **k: map_driver.step(**k), dict(forces=f),
        dict(forces=forces_bad(n, node) + [{0: (0.1, 0.0, 0.0)}]), make=lambda: map_driver, snapshot=map_driver_snap)
    add("ImpedanceDriver.set_state", lambda o, **k: map_driver.set_state(**k), dict(state=map_driver.get_state()),
        dict(state=[{}, "abc", {"loads": {0: (1.0, 0.0, 0.0)}, "steps": 0}, {"loads": {node: (NAN, 0, 0)}, "steps": 0},
                    {"loads": {}, "steps": 2.5}]), make=lambda: map_driver, snapshot=map_driver_snap)
    add("ImpedanceMap.as_driver", lambda o, **k: imap.as_driver(**k), dict(dt=1e-3), dict(dt=POSITIVE))
    add("SLDM", lambda o, **k: rt.SLDM(**k), dict(model=model, damping=w["damping"]),
        dict(model=[None, "abc", OBJ], damping=["abc", 5], tol=[NAN, 0.0, 1.0, -1.0, "abc", None],
             m=[0, -1, 2.5, "abc", NAN, True],
             m_max=[0, -1, 2.5, "abc", NAN], reorth=CHOICE))
    add("SLDM.step_response", lambda o, **k: sldm.step_response(**k), dict(forces=f, times=[1e-3, 2e-3], m=20),
        dict(forces=forces_bad(n, node), times=TIMES, tol=[NAN, 0.0, 2.0, "abc"], m=[0, 2.5, "abc", NAN]))
    add("SLDM.frequency_response", lambda o, **k: sldm.frequency_response(**k), dict(forces=f, frequencies=[1.0], m=20),
        dict(forces=forces_bad(n, node), frequencies=[[], [NAN], [-1.0], "abc", OBJ, [[1.0]], None]))
    add("SLDM.response", lambda o, **k: sldm.response(**k), dict(forces_of_time=[(0.0, f)], times=[1e-3, 2e-3]),
        dict(forces_of_time=[[], "abc", [(NAN, f)], [(0.1, f), (0.05, f)], [(0.0, {node: (NAN, 0.0, 0.0)})], [(0.0,)], 5, OBJ,
                             [("a", f)]],
             times=[t for t in TIMES if t != [-1.0]]))
    add("ImpedanceMap.build", lambda o, **k: rt.ImpedanceMap.build(**k),
        dict(model=model, damping=w["damping"], nodes=[node], modes=modes),
        dict(model=[None, "abc", OBJ], damping=["abc"], nodes=[-1, 10**9, 2.5, "nogroup", [], OBJ, [True]],
             radius=[NAN, -1.0, 0.0, "abc", OBJ], metric=CHOICE, threshold=[NAN, -0.1, 1.0, 2.0, "abc", OBJ],
             times=TIMES, method=CHOICE, static=CHOICE, n_modes=COUNT, tol=[NAN, 0.0, 1.0, "abc"],
             memory_limit=[NAN, -1.0, 0.0, "abc", OBJ, None], progress=["abc", 5], workers=[0, -1, 2.5, "abc", NAN, True],
             modes=["abc", 5, rt.modal_analysis(rt.ShellModel(w["other"], rt.Material()).fix("attachment"), 3)]))
    add("ImpedanceMap.displacements", lambda o, **k: imap.displacements(**k), dict(loads=[(node, (0.0, 0.0, -0.1), 0.0)], t=0.01),
        dict(loads=[[(node, (NAN, 0.0, 0.0), 0.0)], [(node, ("a", 0.0, 0.0))], [(10**9, (1.0, 0.0, 0.0))],
                    [(2.5, (1.0, 0.0, 0.0))],
                    [(True, (1.0, 0.0, 0.0))], "abc", 5, [(node,)], [(node, (1.0, 0.0, 0.0), NAN)], OBJ],
             t=[NAN, "abc", None, OBJ]))
    add("ImpedanceMap.compliance_at", lambda o, **k: imap.compliance_at(**k), dict(loaded=node, nodes=[0, 1]),
        dict(loaded=nodes_bad(n), nodes=[[-1], [10**9], "abc", [2.5], OBJ], t=[NAN, "abc", OBJ]))
    add("ImpedanceMap.point_compliance", lambda o, **k: imap.point_compliance(**k), dict(node=node),
        dict(node=nodes_bad(n), t=[NAN, "abc", OBJ]))

    def probe_snap(p):
        return [p.force.copy(), p.contact_node, _sim_state(p.driver)]

    add("Probe", lambda o, **k: rt.Probe(**k), dict(mesh=mesh, driver=_sim()),
        dict(mesh=[None, "abc", w["other"], rt.meshes.liver(1)], driver=[None, "abc", 5, model], radius=NONNEG,
             coupling=CHOICE, stiffness=POSITIVE, candidates=COUNT))
    probe = rt.Probe(mesh, _sim())
    add("Probe.prepare", lambda o, **k: probe.prepare(**k), dict(nodes=[node]),
        dict(nodes=[-1, 10**9, 2.5, "abc", OBJ, True]), make=lambda: probe, snapshot=probe_snap)
    add("Probe.prepare(around)", lambda o, **k: probe.prepare(**k), dict(around=w["far"], radius=0.01),
        dict(around=POINT[1:], radius=[NAN, -1.0, "abc", OBJ]), make=lambda: probe, snapshot=probe_snap)
    add("Probe.update", lambda o, **k: probe.update(**k), dict(position=w["far"]), dict(position=POINT),
        make=lambda: probe, snapshot=probe_snap)
    add("Grasp", lambda o, **k: rt.Grasp(**k), dict(mesh=mesh, driver=_sim()),
        dict(mesh=[None, "abc", w["other"]], driver=[None, "abc", 5], stiffness=POSITIVE,
             max_force=OPTIONAL_POSITIVE))
    grasp = rt.Grasp(mesh, _sim())
    grasp.grab(node)

    def grasp_snap(g):
        return [g.node, g.force.copy(), _sim_state(g.driver)]

    add("Grasp.grab", lambda o, **k: grasp.grab(**k), dict(node=node), dict(node=nodes_bad(n)),
        make=lambda: grasp, snapshot=grasp_snap)
    add("Grasp.update", lambda o, **k: grasp.update(**k), dict(target=w["far"]), dict(target=POINT[1:]),
        make=lambda: grasp, snapshot=grasp_snap)
    device = rt.ScriptedDevice(lambda t: w["far"])
    add("HapticLoop", lambda o, **k: rt.HapticLoop(**k), dict(probe=rt.Probe(mesh, _sim()), device=device, rate=1000.0),
        dict(probe=[None, "abc", _sim()], device=[None, "abc", 5], rate=POSITIVE + [1e9], spin=[NAN, -1.0, "abc", OBJ]))
    add("HapticLoop.run", lambda o, **k: rt.HapticLoop(rt.Probe(mesh, _sim()), device).run(**k), dict(seconds=0.01),
        dict(seconds=POSITIVE))
    add("ScriptedDevice", lambda o, **k: rt.ScriptedDevice(**k), dict(trajectory=lambda t: np.zeros(3)),
        dict(trajectory=["abc", None, 5, OBJ]))
    add("CallbackDevice", lambda o, **k: rt.CallbackDevice(**k),
        dict(get_position=lambda: np.zeros(3), set_force=lambda f: None),
        dict(get_position=["abc", None, 5], set_force=["abc", None, 5]))
    add("write_vtu", lambda o, **k: write_vtu(**k), dict(path="TMP/x.vtu", mesh=mesh, displacements=np.zeros((n, 3))),
        dict(path=PATHS + ["TMPDIR"], mesh=[None, "abc"], displacements=[np.ones((2, 3)), np.full((n, 3), NAN), "abc", OBJ]))
    add("write_pvd", lambda o, **k: write_pvd(**k), dict(path="TMP/x.pvd", frames=[(0.0, "TMP/x.vtu")]),
        dict(path=PATHS + ["TMPDIR"], frames=["abc", 5, [(NAN, "x.vtu")], [("a", "x.vtu")], OBJ, [(0.0,)]]))
    add("save_mesh", lambda o, **k: rt.save_mesh(**k), dict(mesh=mesh, path="TMP/x.obj"),
        dict(mesh=[None, "abc"], path=PATHS + ["TMP/x.nosuchformat", "TMPDIR"]))
    add("Session", lambda o, **k: Session(**k),
        dict(mesh=mesh, material=rt.Material(), fixed="attachment", settings=Settings(n_modes=8)),
        dict(mesh=["abc", 5, OBJ], material=["abc", 5], fixed=["nogroup", [10**9], 2.5, OBJ], settings=["abc", 5]))
    session = Session(mesh, rt.Material(), "attachment", Settings(n_modes=8))

    def session_snap(s):
        return [s.settings, s.node, None if s.target is None else s.target.copy(), s.displacements()]

    add("Session.configure", lambda o, **k: session.configure(**k), dict(alpha=8.0),
        dict(method=CHOICE, n_modes=[0, -1, 2.5, "abc", NAN, 10**6, True], dt=[NAN, 0.0, -1.0, "abc", 1.0],
             alpha=[NAN, -1.0, "abc"], E=[NAN, 0.0, -1.0, "abc"], grasp_stiffness=[NAN, 0.0, "abc"],
             max_force=[NAN, 0.0, -1.0, "abc"], bogus=[1]),
        make=lambda: session, snapshot=session_snap)
    add("Session.grab", lambda o, **k: session.grab(**k), dict(point=w["far"]),
        dict(point=POINT, displacements=["abc", np.ones((2, 3))]),
        make=lambda: session, snapshot=session_snap)
    add("Session.drag", lambda o, **k: session.drag(**k), dict(target=w["far"]), dict(target=POINT),
        make=lambda: session, snapshot=session_snap)
    return E


@functools.lru_cache(maxsize=None)
def entries() -> dict[str, Entry]:
    return {e.name: e for e in _entries()}


def _params() -> list:
    return [pytest.param(name, arg, i, id=f"{name}-{arg}-{i}")
            for name, e in entries().items() for arg, bad in e.bad.items() for i in range(len(bad))]


def _resolve(value, tmp_path):
    if isinstance(value, str) and value == "TINY_OBJ":
        p = tmp_path / "tiny.obj"
        p.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3\nf 1 3 4\n")
        return str(p)
    if isinstance(value, str) and value.startswith("TMP"):
        if value == "TMPDIR":
            return str(tmp_path)
        return str(tmp_path / value.split("/", 1)[1])
    if isinstance(value, list) and value and isinstance(value[0], tuple) and len(value[0]) == 2 and isinstance(value[0][1], str) \
            and value[0][1].startswith("TMP"):
        return [(value[0][0], str(tmp_path / value[0][1].split("/", 1)[1]))]
    return value


def _same(a, b) -> bool:
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return isinstance(b, (list, tuple)) and len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return np.array_equal(np.asarray(a), np.asarray(b), equal_nan=True)
    return a == b


@pytest.mark.parametrize("name", list(entries()))
def test_baseline_call_succeeds(name, tmp_path):
    e = entries()[name]
    obj = e.make() if e.make else None
    e.call(obj, **{k: _resolve(v, tmp_path) for k, v in e.base.items()})


@pytest.mark.parametrize("name, arg, i", _params())
def test_hostile_argument_is_refused_and_state_kept(name, arg, i, tmp_path):
    e = entries()[name]
    value = e.bad[arg][i]
    obj = e.make() if e.make else None
    before = e.snapshot(obj) if e.snapshot else None
    kwargs = {k: _resolve(v, tmp_path) for k, v in e.base.items()}
    kwargs[arg] = _resolve(value, tmp_path)
    with pytest.raises(rt.RtfemError) as info:
        e.call(obj, **kwargs)
    msg = str(info.value)
    assert len(msg) > 10 and "\n" not in msg.strip(), msg
    if e.snapshot:
        assert _same(before, e.snapshot(obj)), f"{name}({arg}={value!r}) was refused but changed the state"
