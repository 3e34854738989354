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

    _entering: threading.Thread | None = None
    _generation = 0  # the session's cut models drawn so far
    cuts_drawn = 0
    cut_drags = 0  # ctrl+drags the browser has begun on the organ (their "start" events)

    def _init_cut(self) -> None:
        self._cut_lock = threading.Lock()
        # the mouse's blades (tip, heel) and "lift"s (a stroke's end) not yet taken by a frame, in order: a lift
        # is never lost to the next blade (it was one slot, read and cleared in two steps: a stroke's end written
        # between them was cleared unseen, the blade left in the tissue) and two strokes never join into one
        self._cut_events: list = []

    def _on_cut(self, event) -> None:
        if event.phase == "start":
            self.cut_drags += 1
            self.mode_index = None
            self._mode_dropdown.value = "off"
        item = "lift" if event.phase == "end" else blade(event.end_position, event.client.camera.position)
        with self._cut_lock:
            events = self._cut_events
            if events and not isinstance(item, str) and not isinstance(events[-1], str):
                events[-1] = item  # the blade moved again before a frame took it: the newest place is the one
            else:
                events.append(item)

    def _apply_cut(self) -> None:
        """The frame thread's share: the mouse's blades and lifts to the session, in order (held while scalpel
        mode is being entered; the first blade enters it), a new surface when a cut came."""
        s = self.session
        entering = self._entering is not None and self._entering.is_alive()
        with self._cut_lock:
            events, self._cut_events = ([], self._cut_events) if entering else (self._cut_events, [])
        for i, item in enumerate(events):
            if isinstance(item, str):
                s.lift()
            elif s.scalpel is not None:
                s.cut(*item)
            else:
                with self._cut_lock:  # the rest of the stroke waits for scalpel mode
                    self._cut_events[:0] = events[i + 1:]
                s.cut_status = "entering scalpel mode: the organ on the full order, hung under gravity ..."
                self._entering = threading.Thread(target=self._enter, args=item, daemon=True,
                                                  name="rtfem-viewer-scalpel")
                self._entering.start()
                break
        if s.generation != self._generation:
            self._use_surface()
            self.cuts_drawn += 1

    def _enter(self, tip, heel) -> None:
        s = self.session
        try:
            s.cut(tip, heel)
        except RtfemError as exc:  # a shell, a device attached: said in the panel; the stroke is dropped
            with self._cut_lock:
                self._cut_events.clear()
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
