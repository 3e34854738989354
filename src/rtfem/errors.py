"""Exceptions and warnings a user can cause.

Every error that bad input can trigger is a subclass of :class:`RtfemError` and carries a
message that says what was wrong and what to do about it.
"""

from __future__ import annotations


class RtfemError(Exception):
    """Base class of every error rtfem raises for bad input or an unsolvable request."""


class MeshError(RtfemError, ValueError):
    """A mesh that cannot be used: unreadable file, non-manifold edge, bad coordinates..."""


class ModelError(RtfemError, ValueError):
    """A model that cannot be solved as asked: rigid-body freedom, bad loads, bad fixes..."""


class SolverError(RtfemError, RuntimeError):
    """A numerical solver failed (factorization, eigen-solver, Lanczos)."""


class DeviceError(RtfemError, RuntimeError):
    """A haptic device or its service that cannot be used: its library or service not found, an
    error it reported (named as its SDK names it), a disconnection."""


class RtfemWarning(UserWarning):
    """Something was done that the user should know about (a repair, a dropped load)."""
