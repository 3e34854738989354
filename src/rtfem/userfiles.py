"""The checks every file a user names passes before it is read (:func:`regular_file`,
:func:`read_text`, :func:`read_toml`: a regular file after its links, within a size cap, TOML nested
within a depth) and every name that becomes part of an output path (:func:`file_stem`,
:func:`inside`): a file or a name from someone else never makes rtfem hang, run out of memory or
write outside the folder the user named (issue 53)."""

from __future__ import annotations

import os
from pathlib import Path

from . import validate
from .errors import ModelError

__all__ = ["regular_file", "read_text", "read_toml", "file_stem", "inside", "text_limit", "TEXT_LIMIT_ENV",
           "TEXT_LIMIT", "TOML_DEPTH", "NAME_LENGTH"]


def _clean(exc: BaseException) -> str:
    return validate.one_line(str(exc), 160)


def _size(nbytes: int) -> str:
    for unit, k in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if nbytes >= k:
            return f"{nbytes / k:.3g} {unit}"
    return f"{nbytes} bytes"


# ---------------------------------------------------------------- files a user names
TEXT_LIMIT_ENV = "RTFEM_MAX_TEXT_MB"  # raises the size cap of scene files and batch plans
TEXT_LIMIT = 8 * 2**20  # bytes: a scene file or a plan is a few kB of TOML (a long scripted path: a few hundred)
TOML_DEPTH = 16  # tables and arrays inside each other: a scene file's deepest is 5 (a tool's path rows)


def regular_file(path, what: str, *, error: type = ModelError) -> Path:
    """``path`` once it is known to name a regular file after its links are followed: not a
    directory, and not a pipe, a device (``/dev/zero``) or a socket, which may never end. ``what``
    names it in the messages ("mesh file").

    Raises
    ------
    error
        A missing file, a directory, anything else that is not a regular file, a file that cannot
        be inspected; the message names the path.
    """
    p = Path(validate.path_like(path, "path", error=error))
    try:
        mode = os.stat(p).st_mode  # follows links: a link to /dev/zero is a device
    except FileNotFoundError:
        raise error(f"{what} {str(p)!r} does not exist") from None
    except (OSError, ValueError) as exc:
        raise error(f"cannot read the {what} {str(p)!r}: {getattr(exc, 'strerror', None) or _clean(exc)}") from None
    _check_mode(mode, p, what, error)
    return p


def _check_mode(mode: int, p: Path, what: str, error: type) -> None:
    import stat

    if stat.S_ISDIR(mode):
        raise error(f"{str(p)!r} is a directory, not a {what}")
    if not stat.S_ISREG(mode):
        raise error(f"{str(p)!r} is not a regular file (a pipe, a device or a socket, which may never end): give a "
                    f"{what} on disk")


def text_limit() -> int:
    """The size cap of a text file a user names (bytes): :data:`TEXT_LIMIT`, or ``$RTFEM_MAX_TEXT_MB`` MiB."""
    text = os.environ.get(TEXT_LIMIT_ENV)
    if not text:
        return TEXT_LIMIT
    try:
        mb = float(text)
    except ValueError:
        mb = -1.0
    if not 0 < mb < 2**20:
        raise ModelError(f"{TEXT_LIMIT_ENV}={validate.show(text)}: give a size in MiB, e.g. 64")
    return int(mb * 2**20)


def read_text(path, what: str, *, limit: int | None = None, error: type = ModelError) -> str:
    """The UTF-8 text of a file a user names, after :func:`regular_file`'s checks and within a size
    cap (default :func:`text_limit`). The file is opened without blocking and checked again on the
    open descriptor, so one swapped for a pipe after the check is refused, not waited on; at most
    the cap (and one byte) is read, whatever the file claims.

    Raises
    ------
    error
        As :func:`regular_file`; a file over the cap (the message gives the cap and how to raise it);
        text that is not UTF-8.
    """
    p = regular_file(path, what, error=error)
    cap = text_limit() if limit is None else int(limit)
    try:
        fd = os.open(p, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
        with os.fdopen(fd, "rb") as fh:
            st = os.fstat(fh.fileno())
            _check_mode(st.st_mode, p, what, error)
            data = fh.read(cap + 1) if st.st_size <= cap else b""
    except OSError as exc:
        raise error(f"cannot read the {what} {str(p)!r}: {exc.strerror or _clean(exc)}") from None
    if st.st_size > cap or len(data) > cap:
        raise error(f"{str(p)!r} is {_size(max(st.st_size, len(data)))}, more than the {_size(cap)} a {what} may be "
                    f"(it is a few kB of text): is it the right file? If it is, raise the cap with {TEXT_LIMIT_ENV}="
                    f"<MiB> in the environment")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise error(f"{str(p)!r} is not a text (UTF-8) {what}: byte {exc.start} is {data[exc.start]:#04x}") from None


def read_toml(path, what: str, *, error: type = ModelError) -> dict:
    """A TOML file a user names (a scene file, a batch plan), read as :func:`read_text` reads it and
    parsed with the standard library's ``tomllib``; tables and arrays nested deeper than
    :data:`TOML_DEPTH` are refused.

    Raises
    ------
    error
        As :func:`read_text`; a TOML syntax error (its line and column), nesting too deep; one line
        that names the file.
    """
    import tomllib

    text = read_text(path, what, error=error)
    p = Path(path)
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{p}: not a TOML {what}: {_clean(exc)}") from None
    except RecursionError:
        raise error(f"{p}: tables or arrays nested deeper than the {TOML_DEPTH} levels a {what} may have") from None
    depth = _depth(doc)
    if depth > TOML_DEPTH:
        raise error(f"{p}: tables or arrays nested {depth} deep, more than the {TOML_DEPTH} levels a {what} may "
                    "have")
    return doc


def _depth(doc) -> int:
    """How deep dicts and lists nest in ``doc`` (walked without recursion)."""
    deepest, stack = 0, [(doc, 1)]
    while stack:
        value, d = stack.pop()
        deepest = max(deepest, d)
        if d > TOML_DEPTH:
            break
        children = value.values() if isinstance(value, dict) else value
        stack.extend((c, d + 1) for c in children if isinstance(c, (dict, list)))
    return deepest


#: characters that never belong in a name that becomes a file name: path separators and NUL
_SEPARATORS = frozenset("/\\\0")
NAME_LENGTH = 100  # characters of a name used in file names


def file_stem(name, what: str, *, error: type = ModelError) -> str:
    """``name`` when it may be part of a file name in an output folder: a non-empty string of at most
    :data:`NAME_LENGTH` characters, not ``.`` or ``..``, with no path separator and no control,
    formatting (bidirectional overrides, zero-width characters) or line-separator character, and no
    space at either end. ``what`` names it in the message ("[[body]] 2's name").

    Raises
    ------
    error
        The name is not such a string; the message shows it escaped and says what to change.
    """
    import unicodedata

    if not isinstance(name, str) or not name:
        raise error(f"{what} {validate.show(name)}: give a non-empty text (it names files)")
    shown = ascii(name) if len(name) <= 60 else ascii(name[:57]) + "..."
    if len(name) > NAME_LENGTH:
        raise error(f"{what} {shown} is {len(name)} characters long: it names files, give at most {NAME_LENGTH}")
    if name in (".", ".."):
        raise error(f"{what} {shown} names a folder, not a file: give a name of letters, digits, '-' or '_'")
    bad = [c for c in name if c in _SEPARATORS or unicodedata.category(c) in ("Cc", "Cf", "Cs", "Co", "Cn", "Zl", "Zp")]
    if bad:
        kinds = sorted({"a path separator" if c in _SEPARATORS else f"U+{ord(c):04X}" for c in bad})
        raise error(f"{what} {shown} holds {', '.join(kinds)}: it names files in the output folder, so it takes no "
                    "path separators and no control or bidirectional-text characters; give letters, digits, '-' or '_'")
    if name != name.strip():
        raise error(f"{what} {shown} begins or ends with a space: give the name without it (it names files)")
    return name


def inside(folder, path, what: str = "output", *, error: type = ModelError) -> Path:
    """``path`` resolved (links followed), refused unless it lies inside ``folder`` resolved: what a
    command writes stays in the folder its user named.

    Raises
    ------
    error
        The path resolves outside the folder (through ``..`` or a link); the message names both.
    """
    root = Path(folder).resolve()
    target = Path(path).resolve()
    if target != root and root not in target.parents:
        raise error(f"the {what} {str(path)!r} resolves to {str(target)!r}, outside the output folder {str(root)!r} "
                    "(through '..' or a link): rtfem writes only inside the folder it is given")
    return target
