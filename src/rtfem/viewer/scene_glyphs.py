"""What the scene viewer draws besides the bodies: the obstacles (a plane as a finite grid at the
plane, a mesh obstacle as its surface), the supports and attachments (points, and springs as line
segments between the nodes they join), and each tool as its shape: a probe as its sphere, capsule
or jaw (:class:`~rtfem.Tool`), a grasper as a shaft and two jaws whose gap follows its state (open
wide, or closed on what it holds), with its reach shown while it is open.

Every glyph is a viser scene node under ``/scene/...``; :meth:`Glyphs.update` moves them to the
scene's state of the frame. The viewer's state (:meth:`SceneViewer.state`) lists what is drawn.
"""

from __future__ import annotations

import numpy as np

__all__ = ["Glyphs", "tool_start", "quaternion"]

PLANE = (178, 186, 200)
OBSTACLE = (150, 156, 168)
SUPPORT = (150, 150, 150)
SPRING = (214, 90, 150)
BLADE, BLADE_OUT = (200, 30, 30), (190, 190, 200)  # a scalpel's blade in the tissue, and out of it
STEEL = (170, 176, 186)
JAW_OPEN = (240, 200, 60)
JAW_CLOSED = (235, 120, 30)
PROBE = (205, 208, 222)


def quaternion(R: np.ndarray) -> tuple[float, float, float, float]:
    """(w, x, y, z) of a rotation matrix whose columns are a frame's axes in the world."""
    R = np.asarray(R, dtype=float)
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = (0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s)
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(max(1.0 + R[i, i] - R[j, j] - R[k, k], 1e-30))
        v = np.zeros(3)
        v[i] = 0.25 * s
        v[j] = (R[j, i] + R[i, j]) / s
        v[k] = (R[k, i] + R[i, k]) / s
        q = ((R[k, j] - R[j, k]) / s, *v)
    q = np.asarray(q) / np.linalg.norm(q)
    return tuple(float(c) for c in q)


def _frame_z(axis: np.ndarray) -> np.ndarray:
    """A rotation whose third column is the unit ``axis`` (the other two any orthonormal pair)."""
    a = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    other = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(other, a)
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(a, x), a])


def tool_start(tool) -> np.ndarray | None:
    """Where a tool is at t = 0 before the scene has stepped: its scripted path's start (a
    :class:`~rtfem.ScriptedDevice`'s trajectory, read without touching the device), or None (a live
    hand: drawn once the scene has read it)."""
    trajectory = getattr(tool.device, "trajectory", None)
    if trajectory is None:
        return None
    try:
        return np.asarray(trajectory(0.0), dtype=float).reshape(3)
    except Exception:  # a user's trajectory that cannot say: drawn once the scene has read it
        return None


class _ProbeGlyph:
    """A probe's rigid shape (its :class:`~rtfem.Tool`: a point core swept by a radius is a sphere,
    a segment a capsule, a rectangle a jaw plate) at its proxy, and its virtual coupling to the hand
    (a line from the proxy to the device's position) when it has one."""

    def __init__(self, sc, name: str, tool) -> None:
        shape = tool.shape
        a, b, _ = shape.half_extents
        r = max(float(shape.radius), 1e-4)
        self.R = np.asarray(shape.orientation, dtype=float)
        if a == 0.0 and b == 0.0:
            self.parts = [sc.add_icosphere(f"{name}/sphere", radius=r, color=PROBE, visible=False)]
            self.kind = "sphere"
        elif b == 0.0:  # a capsule along the frame's first axis: a cylinder and two end spheres
            R = self.R[:, [1, 2, 0]]  # the cylinder's axis (local z) along the first axis
            self.parts = [sc.add_cylinder(f"{name}/shaft", radius=r, height=2 * a, color=PROBE, wxyz=quaternion(R),
                                          visible=False),
                          sc.add_icosphere(f"{name}/end0", radius=r, color=PROBE, visible=False),
                          sc.add_icosphere(f"{name}/end1", radius=r, color=PROBE, visible=False)]
            self.ends = (a * self.R[:, 0], -a * self.R[:, 0])
            self.kind = "capsule"
        else:  # a plate: the rectangle swept by the radius (its rounded rim drawn square)
            self.parts = [sc.add_box(f"{name}/plate", color=PROBE, dimensions=(2 * (a + r), 2 * (b + r), 2 * r),
                                     wxyz=quaternion(self.R), visible=False)]
            self.kind = "jaw"
        self.coupling = sc.add_line_segments(f"{name}/coupling", np.zeros((1, 2, 3), np.float32), (120, 120, 130),
                                             thickness=2.0, thickness_units="screen", visible=False)
        self.name = name

    def update(self, tool, at: np.ndarray | None) -> dict:
        shown = at is not None
        for k, part in enumerate(self.parts):
            if shown:
                offset = self.ends[k - 1] if self.kind == "capsule" and k > 0 else 0.0
                part.position = tuple(at + offset)
            part.visible = shown
        target = tool.target
        spring = shown and target is not None and float(np.linalg.norm(target - at)) > 1e-5
        if spring:
            self.coupling.points = np.array([[at, target]], dtype=np.float32)
        self.coupling.visible = spring
        return {"kind": tool.kind, "shape": self.kind, "visible": shown,
                "position": None if at is None else [float(v) for v in at]}


class _GrasperGlyph:
    """A grasper: a shaft and two jaws at its tip, closing along a direction across the shaft; the
    gap is wide while it is open and shut while it is closed (on what it holds, or on nothing);
    its reach (the radius within which closing takes the surface) is a faint sphere while open.
    The shaft points away from the nearest body's centre at the tool's first drawn position."""

    def __init__(self, sc, name: str, tool, centres: list[np.ndarray]) -> None:
        r = float(tool.radius)
        self.r, self.name, self.centres, self.sc = r, name, centres, sc
        self.length, self.width, self.thick = 1.6 * r, 0.7 * r, 0.3 * r
        self.shaft = sc.add_cylinder(f"{name}/shaft", radius=0.22 * r, height=8 * r, color=STEEL, visible=False)
        self.jaws = [sc.add_box(f"{name}/jaw{k}", color=JAW_OPEN, dimensions=(self.width, self.thick, self.length),
                                visible=False) for k in range(2)]
        self.reach = sc.add_icosphere(f"{name}/reach", radius=r, color=JAW_OPEN, opacity=0.15, visible=False)
        self.hold = sc.add_line_segments(f"{name}/hold", np.zeros((1, 2, 3), np.float32), JAW_CLOSED, thickness=2.0,
                                         thickness_units="screen", visible=False)
        self.frame: np.ndarray | None = None  # columns: across the jaws' width, the closing direction, the shaft
        self.closed_colour = None

    def _orient(self, at: np.ndarray) -> np.ndarray:
        c = min(self.centres, key=lambda c: float(np.linalg.norm(c - at))) if self.centres else at - [0, 0, 1.0]
        axis = at - c
        if np.linalg.norm(axis) < 1e-9:
            axis = np.array([0.0, 0.0, 1.0])
        axis = axis / np.linalg.norm(axis)
        close = np.cross(axis, [0.0, 0.0, 1.0])
        if np.linalg.norm(close) < 1e-6:
            close = np.cross(axis, [1.0, 0.0, 0.0])
        close /= np.linalg.norm(close)
        return np.column_stack([np.cross(close, axis), close, axis])

    def update(self, tool, at: np.ndarray | None, held_at: np.ndarray | None = None) -> dict:
        """``held_at``: where the nodes it holds are (k, 3), drawn tied to the jaws' springs' anchors."""
        shown = at is not None
        closed = bool(tool.closed) if shown else False
        if shown:
            if self.frame is None:
                self.frame = self._orient(at)
            R = self.frame
            wxyz = quaternion(R)
            gap = 0.15 * self.r if closed else 1.6 * self.r
            for k, jaw in enumerate(self.jaws):
                side = 1.0 if k == 0 else -1.0
                jaw.position = tuple(at + 0.5 * self.length * R[:, 2] + side * 0.5 * (gap + self.thick) * R[:, 1])
                jaw.wxyz = wxyz
                colour = JAW_CLOSED if closed else JAW_OPEN
                if jaw.color != colour:
                    jaw.color = colour
            self.shaft.position = tuple(at + (self.length + 4 * self.r) * R[:, 2])
            self.shaft.wxyz = wxyz
            self.reach.position = tuple(at)
        for part in (*self.jaws, self.shaft):
            part.visible = shown
        self.reach.visible = shown and not closed
        held = tool.held
        tied = shown and held is not None and held_at is not None
        if tied:
            self.hold.points = np.stack([held_at, held.anchor], axis=1).astype(np.float32)
        self.hold.visible = tied
        return {"kind": tool.kind, "shape": "grasper", "visible": shown, "closed": closed,
                "holds": None if held is None else held.a.name, "held_nodes": 0 if held is None else int(held.nodes_a.size),
                "position": None if at is None else [float(v) for v in at]}


class Glyphs:
    """The scene's obstacles, supports, attachments and tools as viser nodes (see the module)."""

    def __init__(self, server, scene, centre: np.ndarray, size: float, skip=()) -> None:
        sc = server.scene
        self.scene, self.size = scene, size
        self.planes, self.meshes = [], []
        for i, obstacle in enumerate(scene.obstacles):
            if hasattr(obstacle, "normal"):
                self.planes.append((obstacle, self._plane(sc, f"/scene/planes/{i}", obstacle, centre, size)))
            else:
                m = obstacle.mesh
                self.meshes.append((obstacle, sc.add_mesh_simple(
                    f"/scene/obstacles/{i}", np.asarray(m.vertices, np.float32), np.asarray(m.triangles, np.uint32),
                    color=OBSTACLE, side="double")))
        self.supports = []
        for k, body in enumerate(scene.bodies):
            held = getattr(getattr(body, "model", None), "held_nodes", None)
            nodes = np.flatnonzero(held) if held is not None else np.zeros(0, dtype=np.int64)
            nodes = nodes[np.isin(nodes, body.surface)]
            if nodes.size:
                self.supports.append((body, sc.add_point_cloud(f"/scene/supports/{k}", body.X[nodes], colors=SUPPORT,
                                                               point_size=0.006 * size, point_shape="circle")))
        self.springs = None
        if scene.attachments:
            self.springs = sc.add_line_segments("/scene/attachments", self._spring_points(), SPRING, thickness=2.0,
                                                thickness_units="screen")
        centres = [b.centre for b in scene.bodies]
        self.tools = []
        for i, tool in enumerate(scene.tools):
            if tool in skip:
                continue
            name = f"/scene/tools/{i}"
            glyph = _GrasperGlyph(sc, name, tool, centres) if tool.kind == "grasper" else _ProbeGlyph(sc, name, tool)
            self.tools.append((tool, glyph, tool_start(tool)))
        self.blades = []
        for i, scalpel in enumerate(getattr(scene, "scalpels", ())):
            points, shown = self._blade(scalpel)
            line = sc.add_line_segments(f"/scene/scalpels/{i}", points, BLADE_OUT, thickness=4.0, thickness_units="screen")
            line.visible = shown
            self.blades.append((scalpel, line))
        self.drawn: dict = {}
        self.hidden: set[str] = set()

    @staticmethod
    def _blade(scalpel) -> tuple[np.ndarray, bool]:
        """((1, 2, 3): a scalpel's blade from its tip to its heel, whether it is shown): where the scene last
        put it, or before the first step at its scripted path's start (:func:`tool_start`: the device is not
        read here, on the frame thread); a live hand's blade is hidden until the scene has read it."""
        tip = scalpel.tip if scalpel.tip is not None else tool_start(scalpel)
        shown = tip is not None
        tip = tip if shown else np.zeros(3)
        return np.stack([tip, tip + scalpel.cutter.blade])[None].astype(np.float32), shown

    @staticmethod
    def _plane(sc, name: str, plane, centre: np.ndarray, size: float):
        """A finite grid on the plane, 1.6 times the bodies' size, centred at their centre's foot on it."""
        n = plane.normal
        at = centre - float((centre - plane.point) @ n) * n
        R = np.column_stack([plane.frame[:, 1], plane.frame[:, 2], n])
        w = 1.6 * size
        return sc.add_grid(name, width=w, height=w, plane="xy", cell_size=w / 20, section_size=w / 4,
                           cell_color=(150, 156, 170), section_color=(110, 116, 130), plane_color=PLANE,
                           plane_opacity=0.45, shadow_opacity=0.0, wxyz=quaternion(R), position=tuple(at))

    def _spring_points(self, us=None, bodies=None) -> np.ndarray:
        """(k, 2, 3): each attachment spring from its node of a to its anchor or its node of b, at the
        bodies' displacements ``us`` (each body's surface field, of ``bodies``; None: at rest). An
        attachment of a body that is not among ``bodies`` (cut since they were read) waits a frame."""
        bodies = self.scene.bodies if bodies is None else bodies
        index = {id(b): k for k, b in enumerate(bodies)}
        segments = []
        for att in list(self.scene.attachments):
            a, b = att.a, att.b
            if id(a) not in index or (b is not None and id(b) not in index):
                continue
            xa = a.X[att.nodes_a] + (0.0 if us is None else _at(us[index[id(a)]], a, att.nodes_a))
            if b is None:
                xb = att.anchor
            else:
                xb = b.X[att.nodes_b] + (0.0 if us is None else _at(us[index[id(b)]], b, att.nodes_b))
            segments.append(np.stack([xa, xb], axis=1))
        return np.concatenate(segments).astype(np.float32) if segments else np.zeros((0, 2, 3), np.float32)

    def update(self, us, bodies=None) -> None:
        """Move every glyph to the scene as it is (``us``: each body's surface displacements, of
        ``bodies``, default the scene's)."""
        bodies = self.scene.bodies if bodies is None else bodies
        if self.springs is not None:
            self.springs.points = self._spring_points(us, bodies)
        for scalpel, line in self.blades:
            points, line.visible = self._blade(scalpel)
            line.points = points
            line.colors = np.tile(np.array(BLADE if scalpel.in_tissue() else BLADE_OUT, np.uint8), (1, 2, 1))
        tools = {}
        index = {id(b): k for k, b in enumerate(bodies)}
        for tool, glyph, start in self.tools:
            at = tool.proxy if tool.proxy is not None else start
            if "tools" in self.hidden:
                at = None
            at = None if at is None else np.asarray(at, dtype=float)
            if tool.kind == "grasper":
                held = tool.held
                held_at = None if held is None or id(held.a) not in index else \
                    held.a.X[held.nodes_a] + _at(us[index[id(held.a)]], held.a, held.nodes_a)
                tools[tool.name] = glyph.update(tool, at, held_at)
            else:
                tools[tool.name] = glyph.update(tool, at)
        self.drawn = {"planes": [p.name for p, _ in self.planes], "obstacles": [m.name for m, _ in self.meshes],
                      "supports": [b.name for b, _ in self.supports],
                      "attachments": [a.name for a in self.scene.attachments] if self.springs is not None else [],
                      "tools": tools}

    def set_visible(self, what: str, visible: bool) -> None:
        """Show or hide one kind of glyph ("planes" or "tools"; the browser test compares the pictures)."""
        if what == "planes":
            for _, node in self.planes:
                node.visible = visible
        elif what == "tools":
            (self.hidden.discard if visible else self.hidden.add)("tools")
        else:
            raise ValueError(f"what={what!r}: 'planes' or 'tools'")


def _at(u_surface: np.ndarray, body, nodes: np.ndarray) -> np.ndarray:
    """The displacements of ``nodes`` of ``body`` from its surface field (0 for nodes off the surface)."""
    local = body.local[nodes]
    out = np.zeros((nodes.size, 3))
    on = local >= 0
    out[on] = u_surface[local[on]]
    return out
