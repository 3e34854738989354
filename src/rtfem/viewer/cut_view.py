"""The viewer's scalpel, its front end (issue 57): ctrl+left-drag on a solid organ draws a blade through
it along the line of sight, from :data:`CUT_ABOVE` in front of the point under the cursor to
:data:`CUT_DEPTH` behind it, and the session cuts where it sweeps (:mod:`rtfem.viewer.cutting`). The
mouse's blade is handed to the session by the frame thread, once a frame; the first stroke enters the
scalpel mode on a thread of its own (the organ is hung under gravity first: a static solve). Each cut
the session takes is sent as a new surface: the frames' encoder and the grabbable copy are rebuilt."""

from __future__ import annotations

import threading

import numpy as np

from ..errors import RtfemError
from .gltf import SurfaceGlb, surface_faces

__all__ = ["CutView", "CUT_DEPTH", "CUT_ABOVE"]

CUT_DEPTH = 0.02  # m: the blade reaches this far behind the point under the cursor, along the line of sight
CUT_ABOVE = 0.01  # m: and starts this far in front of it


def blade(point, camera) -> tuple[np.ndarray, np.ndarray]:
    """(tip, heel) of the blade through ``point`` (m) along the ray from ``camera`` (m) through it."""
    p, c = np.asarray(point, dtype=float), np.asarray(camera, dtype=float)
    d = p - c
    d = d / max(float(np.linalg.norm(d)), 1e-12)
    return p + CUT_DEPTH * d, p - CUT_ABOVE * d


class CutView:
    """The :class:`~rtfem.viewer.app.Viewer`'s side of cutting (see the module)."""

    _cut_blade = None  # the blade (tip, heel) the mouse asks for, "lift", or None: taken by the next frame
    _entering: threading.Thread | None = None
    _generation = 0  # the session's cut models drawn so far
    cuts_drawn = 0
    cut_drags = 0  # ctrl+drags the browser has begun on the organ (their "start" events)

    def _on_cut(self, event) -> None:
        if event.phase == "end":
            self._cut_blade = "lift"
            return
        if event.phase == "start":
            self.cut_drags += 1
            self.mode_index = None
            self._mode_dropdown.value = "off"
        self._cut_blade = blade(event.end_position, event.client.camera.position)

    def _apply_cut(self) -> None:
        """The frame thread's share: the mouse's blade to the session, a new surface when a cut came."""
        s = self.session
        pending, self._cut_blade = self._cut_blade, None
        entering = self._entering is not None and self._entering.is_alive()
        if isinstance(pending, str):
            if entering:
                self._cut_blade = pending  # (lifted once it has entered)
            else:
                s.lift()
        elif pending is not None:
            if s.scalpel is not None:
                s.cut(*pending)
            elif entering:
                self._cut_blade = pending
            else:
                s.cut_status = "entering scalpel mode: the organ on the full order, hung under gravity ..."
                self._entering = threading.Thread(target=self._enter, args=pending, daemon=True,
                                                  name="rtfem-viewer-scalpel")
                self._entering.start()
        if s.generation != self._generation:
            self._use_surface()
            self.cuts_drawn += 1

    def _enter(self, tip, heel) -> None:
        s = self.session
        try:
            s.cut(tip, heel)
        except RtfemError as exc:  # a shell, a device attached: said in the panel
            s.cut_status = ""
            s.error = str(exc)

    def _use_surface(self) -> None:
        """The session's surface (at the start, or a cut organ's): the frames' encoder and the grabbable
        copy (re)built on it (the same name: a new copy replaces the old one, whose drags go with it)."""
        s = self.session
        with s._lock:
            self._generation = s.generation
            self._faces = surface_faces(s)
            self._glb = SurfaceGlb(self._faces, s.drawn.size)
            self._pick_u = np.zeros((s.drawn.size, 3))
            self.pick = self._add_pick()
            self._drawn_sent = s.drawn  # the drawn vertices the encoder and the pick mesh are of
