"""Saved files: versioned .npz (no pickle) with checked shapes, types and checksums, written
atomically (a temporary file beside the target, replaced in one step). The checks of a file a user
names are :mod:`rtfem.userfiles`."""

from __future__ import annotations

import contextlib
import errno
import json
import os
import re
import shutil
import tempfile
import zlib
from pathlib import Path
from typing import Iterator

import numpy as np

from .errors import ModelError
from .userfiles import _clean, _size, regular_file

__all__ = ["save_versioned", "load_versioned", "atomic_target", "atomic_stream", "sweep", "physical_memory"]


@contextlib.contextmanager
def atomic_target(path: str | os.PathLike, what: str = "file") -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it replaces ``path`` in one step.

    Whatever happens while the caller writes -- an exception, Ctrl-C (once or twice), a full
    disk, a crash -- ``path`` is either the old file or the new one, complete: the new
    content is written to ``.<name>.<random>.tmp<suffix>`` in the same directory, flushed to
    disk, and renamed over the target (an atomic operation on POSIX and Windows). The
    temporary file is removed when the write fails.
    """
    path = Path(path)
    if path.is_dir():
        raise ModelError(f"{str(path)!r} is a directory; give a file name for the {what}")
    parent = path.parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
        sweep(parent)
        fd, name = tempfile.mkstemp(prefix=f".{path.name}.{os.getpid()}.", suffix=f".tmp{path.suffix}", dir=parent)
    except OSError as exc:
        raise ModelError(f"cannot write the {what} {str(path)!r}: {exc.strerror or exc}") from None
    os.close(fd)
    tmp: Path | None = Path(name)
    try:
        try:
            mode = path.stat().st_mode & 0o777 if path.exists() else 0o666 & ~_umask()
            os.chmod(tmp, mode)
            yield tmp
            with open(tmp, "rb+") as fh:
                os.fsync(fh.fileno())
            os.replace(tmp, path)
            tmp = None
        except OSError as exc:
            raise ModelError(f"cannot write the {what} {str(path)!r}: {exc.strerror or exc}; "
                             "the previous file, if any, is unchanged") from None
    finally:
        if tmp is not None:
            with contextlib.suppress(OSError):
                tmp.unlink()


_TEMPORARY = re.compile(r"^\.(?P<name>.+)\.(?P<pid>[0-9]+)\.[^.]+\.tmp[^/]*$")


def sweep(folder: Path) -> None:
    """Remove the temporary files that saves killed before they finished left in ``folder``
    (``.<name>.<pid>.<random>.tmp<suffix>`` whose process is gone): at every save into the folder,
    whatever its name, so a killed save's file does not wait for the next save of the same name.
    Another running process's temporary files are left alone."""
    with contextlib.suppress(OSError):
        for old in folder.glob(".*.tmp*"):
            m = _TEMPORARY.match(old.name)
            if m and process_gone(m["pid"]):
                old.unlink(missing_ok=True)


@contextlib.contextmanager
def atomic_stream(path: Path, what: str = "file") -> Iterator:
    """An open binary file whose content replaces ``path`` in one step on success, like
    :func:`atomic_target`, but nameless while it is written where the system allows it (Linux's
    O_TMPFILE): a save killed at any moment (SIGKILL, a power cut) leaves no file behind. It is
    given its temporary name only once complete and flushed, for the rename; elsewhere it is
    :func:`atomic_target`'s named file."""
    if path.is_dir():
        raise ModelError(f"{str(path)!r} is a directory; give a file name for the {what}")
    parent = path.parent
    flag = getattr(os, "O_TMPFILE", 0)
    try:
        parent.mkdir(parents=True, exist_ok=True)
        sweep(parent)
        fd = os.open(parent, flag | os.O_RDWR, 0o666 & ~_umask()) if flag else -1
    except OSError as exc:
        if flag and exc.errno in (errno.EOPNOTSUPP, errno.EISDIR, errno.EINVAL, errno.ENOENT):
            fd = -1  # this file system has no anonymous files
        else:
            raise ModelError(f"cannot write the {what} {str(path)!r}: {exc.strerror or exc}") from None
    if fd < 0:
        with atomic_target(path, what) as tmp, open(tmp, "wb") as fh:
            yield fh
        return
    try:
        with os.fdopen(fd, "w+b") as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
            if path.exists():
                os.fchmod(fh.fileno(), path.stat().st_mode & 0o777)
            name = parent / f".{path.name}.{os.getpid()}.{os.urandom(4).hex()}.tmp{path.suffix}"
            if not _link(fh.fileno(), name):  # no linkat here: copy it into a named file
                fh.seek(0)
                with atomic_target(path, what) as tmp, open(tmp, "wb") as out:
                    shutil.copyfileobj(fh, out, 1 << 22)
                return
            try:
                os.replace(name, path)
            except BaseException:
                name.unlink(missing_ok=True)
                raise
    except OSError as exc:
        raise ModelError(f"cannot write the {what} {str(path)!r}: {exc.strerror or exc}; the previous file, if any, is "
                         "unchanged") from None


def _link(fd: int, name: Path) -> bool:
    """Give the anonymous file ``fd`` the name ``name``: linkat(2) of /proc/self/fd/N with
    AT_SYMLINK_FOLLOW, as open(2) documents for O_TMPFILE (Python's os.link links the /proc entry
    itself, which fails across file systems). False where that call is not available."""
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        at_fdcwd, at_symlink_follow = -100, 0x400
        done = libc.linkat(at_fdcwd, f"/proc/self/fd/{fd}".encode(), at_fdcwd, os.fsencode(name), at_symlink_follow)
    except (OSError, AttributeError):
        return False
    if done != 0:
        err = ctypes.get_errno()
        if err in (errno.ENOSYS, errno.ENOENT, errno.EXDEV, errno.EPERM, errno.EOPNOTSUPP):
            return False
        raise OSError(err, os.strerror(err))
    return True


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _json_default(v):
    if isinstance(v, np.bool_):
        return bool(v)
    if isinstance(v, np.integer):
        return int(v)
    if isinstance(v, np.floating):
        return float(v)
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, (tuple, set)):
        return list(v)
    return str(v)


def save_versioned(path: str | os.PathLike, kind: str, version: int, arrays: dict[str, np.ndarray], info: dict) -> Path:
    """Save arrays as an ``.npz`` tagged with a format name and version (no pickle), atomically.

    ``info`` is kept as JSON (numbers, strings, booleans and lists keep their types). The file
    is written beside the target and renamed over it (:func:`atomic_target`), so an
    interrupted save never damages an existing file. Arrays are stored uncompressed: mode
    shapes and responses barely compress, and writing is then limited by the disk alone.
    """
    path = Path(path)
    if path.is_dir():
        raise ModelError(f"{str(path)!r} is a directory; give a file name (e.g. {str(path / 'out.npz')!r})")
    if path.suffix != ".npz":
        path = path.with_name(path.name + ".npz")
    text = json.dumps(dict(info), default=_json_default)
    arrays = {k: np.asarray(v) for k, v in arrays.items()}
    sums = json.dumps({k: _checksum(v) for k, v in arrays.items()})
    with atomic_stream(path, kind.split(".")[-1]) as fh:
        np.savez(fh, format=np.array(kind), version=np.array(version), info_json=np.array(text),
                 checksums=np.array(sums), **arrays)
    return path


def process_gone(pid) -> bool:
    """Whether ``pid`` (an int, or its text) names no running process: what a temporary file or
    folder named after its writer's pid is kept for (a killed process cannot remove its own)."""
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return True
    except (ValueError, TypeError, OverflowError, PermissionError, OSError):
        return False  # not a pid, or another user's process: leave it
    return False


MAX_INFLATION = 20  # rtfem stores its arrays uncompressed; a member inflating more is not its own


def _checksum(a: np.ndarray) -> int:
    """CRC-32 of an array's dtype, shape and bytes (catches a field altered after saving)."""
    a = np.ascontiguousarray(a)
    crc = zlib.crc32(f"{a.dtype.str}{a.shape}".encode())
    flat = a.reshape(-1).view(np.uint8) if a.size else np.zeros(0, np.uint8)
    step = 1 << 26
    for i in range(0, flat.size, step):
        crc = zlib.crc32(flat[i:i + step], crc)
    return crc


def physical_memory() -> int:
    """This machine's physical memory in bytes (what a load or a precompute may at most take)."""
    try:
        return int(os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):  # pragma: no cover - not POSIX
        return 2**40


def _read_npz(path: Path, what: str, max_bytes: int | None) -> dict[str, np.ndarray]:
    """Every array of an .npz, with each .npy header checked before its data is read."""
    import zipfile

    where = repr(str(path))
    limit = physical_memory() if max_bytes is None else int(max_bytes)
    try:
        zf = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError, ValueError) as exc:
        raise ModelError(f"could not read {what} {where}: not an rtfem file ({_clean(exc)}); was it saved by rtfem?") from None
    out: dict[str, np.ndarray] = {}
    with zf:
        members = [m for m in zf.infolist() if m.filename.endswith(".npy")]
        declared = {}
        for m in members:
            field = m.filename[:-4]
            try:
                with zf.open(m) as fh:
                    major, _ = np.lib.format.read_magic(fh)
                    reader = np.lib.format.read_array_header_1_0 if major == 1 else np.lib.format.read_array_header_2_0
                    shape, _, dtype = reader(fh)
                    header = fh.tell()
            except Exception as exc:
                raise ModelError(f"{where}: field {field!r} is damaged ({_clean(exc)})") from None
            if dtype.hasobject:
                raise ModelError(f"{where}: field {field!r} holds Python objects (pickled data), which rtfem files "
                                 "never do; the file was altered or not written by rtfem, and is not opened")
            nbytes = int(np.prod(shape, dtype=object)) * dtype.itemsize
            if m.file_size > MAX_INFLATION * max(m.compress_size, 1024):
                raise ModelError(f"{where}: field {field!r} inflates from {_size(m.compress_size)} to {_size(m.file_size)}: "
                                 "rtfem saves its arrays uncompressed, so this file was not written by rtfem (or was "
                                 "altered), and is not opened")
            if nbytes > m.file_size - header:
                raise ModelError(f"{where}: field {field!r} declares shape {tuple(shape)} ({_size(nbytes)}) but holds "
                                 f"{_size(max(m.file_size - header, 0))}: the file is damaged or altered")
            declared[field] = nbytes
        total = sum(declared.values())
        if total > limit:
            big = max(declared, key=declared.get)
            raise ModelError(f"{where} holds {_size(total)} of arrays (field {big!r}: {_size(declared[big])}), more "
                             f"than the {_size(limit)} allowed here; free memory or pass a larger max_bytes")
        for m in members:
            field = m.filename[:-4]
            try:
                with zf.open(m) as fh:
                    out[field] = np.lib.format.read_array(fh, allow_pickle=False)
            except Exception as exc:
                raise ModelError(f"{where}: field {field!r} could not be read ({_clean(exc)}); the file is damaged") from None
    return out


def _old_info(keys, values) -> dict:
    """``info`` of format-1 files written before JSON: strings, turned back into numbers and booleans."""
    out = {}
    for k, v in zip(keys.tolist(), values.tolist()):
        if v in ("True", "False"):
            out[k] = v == "True"
            continue
        for conv in (int, float):
            try:
                out[k] = conv(v)
                break
            except ValueError:
                continue
        else:
            out[k] = v
    return out


def load_versioned(path: str | os.PathLike, kind: str, version: int, names: list[str],
                   what: str, *, max_bytes: int | None = None) -> tuple[dict[str, np.ndarray], dict]:
    """Load what :func:`save_versioned` wrote, checking the format name, the version and the arrays.

    Each array's header is read first: Python objects (pickles) and arrays larger than the
    file holds or than ``max_bytes`` (default: the physical memory) are refused before any
    data is read. ``what`` names the content in error messages ("modal basis").
    """
    path = regular_file(path, f"{what} file")
    z = _read_npz(path, what, max_bytes)
    fmt = z.get("format")
    if fmt is None or fmt.dtype.kind != "U" or str(fmt) != kind:
        raise ModelError(f"{str(path)!r} is not an rtfem {what} file")
    try:
        v = int(z["version"])
    except (KeyError, TypeError, ValueError):
        raise ModelError(f"{str(path)!r}: field 'version' is missing or damaged") from None
    if v > version:
        raise ModelError(f"{str(path)!r} has format version {v}; this rtfem reads up to {version}: upgrade rtfem")
    if v < 1:
        raise ModelError(f"{str(path)!r} has format version {v}, which no rtfem writes: the file is damaged or altered")
    missing = [n for n in names if n not in z]
    if missing:
        raise ModelError(f"{str(path)!r} lacks {', '.join(missing)}: the file is damaged")
    try:  # every field's checksum, as every save writes them
        sums = json.loads(str(z["checksums"]))
        if not isinstance(sums, dict):
            raise ValueError("not a mapping")
    except KeyError:
        raise ModelError(f"{str(path)!r} has no checksums: it was altered, or saved by an rtfem before they were kept; "
                         "compute it again") from None
    except ValueError:
        raise ModelError(f"{str(path)!r}: field 'checksums' is damaged or altered") from None
    for n in names:
        if n not in sums:
            raise ModelError(f"{str(path)!r}: field {n!r} has no checksum: the file was altered; compute it again")
        if sums[n] != _checksum(z[n]):
            raise ModelError(f"{str(path)!r}: field {n!r} does not match the checksum saved with it: the file was "
                             "altered or damaged after saving; restore it or compute it again")
    try:
        if "info_json" in z:
            info = json.loads(str(z["info_json"]))
            if not isinstance(info, dict):
                raise ValueError("not a mapping")
        else:
            info = _old_info(z["info_keys"], z["info_values"])
    except (KeyError, ValueError, TypeError) as exc:
        raise ModelError(f"{str(path)!r}: field 'info' is damaged ({_clean(exc)})") from None
    return {n: z[n] for n in names}, info
