"""Writing outputs completely or not at all, never over an input, one writer at a time.

Every output, a folder or a file, is written under a temporary name beside it and renamed into
place once complete. The temporary names carry their writer, ``.NAME.partial.HOST.PID.XXXX``
(and ``.NAME.old.HOST.PID.XXXX`` for the previous content while ``--force`` replaces it), so
the next writer of NAME removes those whose process is gone (a run killed by SIGKILL or SIGTERM)
and never those of a live run. While it works a writer holds an advisory lock on
``.NAME.lock`` (``fcntl.flock``, released by the kernel when the process dies): a second writer
of the same output gets an :class:`InputError` at once instead of silently replacing the first
one's result. Every failure to write (a read-only or full disk, a path through a file) is an
InputError naming the output.
"""
from __future__ import annotations

import contextlib
import errno
import io
import os
import re
import shutil
import socket
import tempfile
import time
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np
import pandas as pd

from ..errors import InputError, describe

try:
    import fcntl
except ImportError:  # not POSIX: outputs stay atomic, only the lock is missing
    fcntl = None

_HOST = re.sub(r"[^A-Za-z0-9-]", "-", socket.gethostname())[:40] or "host"
# errno values that only writing produces: an OSError carrying one is about the output
_WRITE_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EFBIG}


def _owner_tag() -> str:
    return f"{_HOST}.{os.getpid()}"


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _default_file_mode() -> int:
    # mkstemp/mkdtemp create owner-only entries; outputs get the usual umask-derived mode instead.
    return 0o666 & ~_umask()


@contextlib.contextmanager
def _output_errors(out: Path, doing: str) -> Iterator[None]:
    """OSErrors of the block become one InputError: 'cannot <doing> (<reason>)'."""
    try:
        yield
    except InputError:
        raise
    except OSError as exc:
        raise InputError(f"cannot {doing} ({exc.strerror or describe(exc)})", file=out) from None


# ---------------------------------------------------------------------------------------------
# Checks before any work
# ---------------------------------------------------------------------------------------------

def _same(a: Path, b: Path) -> bool:
    if a == b:
        return True
    with contextlib.suppress(OSError):
        return os.path.samefile(a, b)  # hard links, bind mounts
    return False


def _refuse_inputs(out: Path, inputs: Iterable, folder: bool) -> None:
    """An output must not be an input; an output folder must neither contain nor lie in one."""
    real_out = out.resolve()
    for given in inputs:
        if given is None:
            continue
        real_in = Path(given).resolve()
        if _same(real_out, real_in):
            raise InputError(f"--out is the input {given}: writing it would destroy the input; "
                             "choose another --out", file=out)
        if not folder:
            continue
        if real_out in real_in.parents:
            raise InputError(f"--out contains the input {given}: replacing the folder would delete "
                             "it; choose another --out", file=out)
        if real_in in real_out.parents:
            raise InputError(f"--out lies inside the input folder {given}; choose a folder outside "
                             "it", file=out)


def _has_content(folder: Path) -> bool:
    with os.scandir(folder) as it:
        return any(True for _ in it)


def _writable(folder: Path) -> bool:
    ids = {"effective_ids": True} if os.access in os.supports_effective_ids else {}
    return os.access(folder, os.W_OK | os.X_OK, **ids)


def _check_location(out: Path) -> None:
    """The nearest existing folder above ``out`` must be a writable folder."""
    above = out.parent
    while not above.exists() and above != above.parent:
        above = above.parent
    if not above.is_dir():
        raise InputError(f"{above} is a file, not a folder: the output cannot be created below it",
                         file=out)
    if not _writable(above):
        raise InputError(f"cannot write here: the folder {above} is not writable", file=out)


def check_output(out: str | os.PathLike, *, force: bool = False, inputs: Iterable = (),
                 folder: bool = False) -> Path:
    """Refuse an output before any work is done; returns ``Path(out)``.

    Refused: an output equal to one of ``inputs`` (paths of the command's inputs), and for a
    ``folder`` one that contains or lies inside an input; a file where a folder is wanted or the
    other way round; an existing file (a non-empty folder) unless ``force``; a location that
    cannot be written. The atomic writers below check again when they start and when they finish.
    """
    out = Path(out)
    _refuse_inputs(out, inputs, folder)
    with _output_errors(out, "inspect the output"):
        if folder and out.exists() and not out.is_dir():
            raise InputError("--out exists and is not a folder", file=out)
        if not folder and out.is_dir():
            raise InputError("--out is a folder: expected a file name", file=out)
        if folder and out.is_dir() and _has_content(out):
            if not force:
                raise InputError("--out exists and is not empty (use --force to replace it)", file=out)
            if not _writable(out):
                raise InputError("--out cannot be replaced: the folder is not writable", file=out)
        if not folder and out.exists() and not force:
            raise InputError("output exists (use --force to replace it)", file=out)
        _check_location(out)
    return out


# ---------------------------------------------------------------------------------------------
# One writer per output, and the leftovers of dead ones
# ---------------------------------------------------------------------------------------------

def _lock_path(out: Path) -> Path:
    return out.parent / f".{out.name}.lock"


def _acquire(lock: Path, out: Path) -> int:
    """A descriptor holding an exclusive flock on ``lock``, or an InputError naming the holder."""
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, _default_file_mode())
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 200, 0).decode(errors="replace").strip() or "another process"
            os.close(fd)
            raise InputError(f"another run ({holder}) is writing this output now; wait for it or "
                             "choose another --out", file=out) from None
        try:
            if os.stat(lock).st_ino == os.fstat(fd).st_ino:
                break
        except FileNotFoundError:
            pass
        os.close(fd)  # the previous holder removed the file we locked: lock the new one
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"pid {os.getpid()} on host {_HOST}, since {time.strftime('%H:%M:%S')}".encode(), 0)
    return fd


@contextlib.contextmanager
def _writer_lock(out: Path) -> Iterator[None]:
    if fcntl is None:
        yield
        return
    lock = _lock_path(out)
    with _output_errors(out, "create the lock file beside the output"):
        fd = _acquire(lock, out)
    try:
        yield
    finally:
        with contextlib.suppress(OSError):
            os.unlink(lock)
        os.close(fd)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True  # exists, owned by someone else
    return True


def clean_leftovers(out: str | os.PathLike) -> list[Path]:
    """Remove ``.NAME.partial.*`` / ``.NAME.old.*`` beside ``out`` left by dead writers on this
    host; returns what was removed. Entries of live processes, of other hosts and of unknown
    naming are kept."""
    out = Path(out)
    removed, entries = [], []
    prefixes = (f".{out.name}.partial.", f".{out.name}.old.")
    with contextlib.suppress(OSError), os.scandir(out.parent) as it:
        entries = [e for e in it if e.name.startswith(prefixes)]
    for entry in entries:
        rest = entry.name[len(next(p for p in prefixes if entry.name.startswith(p))):]
        host, pid, *_ = rest.split(".", 2) + ["", ""]
        if host != _HOST or not pid.isdigit() or _alive(int(pid)):
            continue
        with contextlib.suppress(OSError):
            if entry.is_dir(follow_symlinks=False):
                shutil.rmtree(entry.path)
            else:
                os.unlink(entry.path)
            removed.append(Path(entry.path))
    return removed


def _written_error(exc: OSError, tmp: Path, out: Path) -> InputError | None:
    """The InputError for an OSError raised while writing into ``tmp``, if it is about the output."""
    inside = exc.filename is not None and str(exc.filename).startswith(str(tmp))
    if exc.errno in _WRITE_ERRNOS or (inside and exc.errno in (errno.EACCES, errno.EPERM)):
        return InputError(f"could not write the output ({exc.strerror or describe(exc)}); nothing "
                          "was written", file=out)
    return None


def _discard(tmp: Path) -> None:
    if tmp.is_dir() and not tmp.is_symlink():
        shutil.rmtree(tmp, ignore_errors=True)
    else:
        with contextlib.suppress(OSError):
            os.unlink(tmp)


@contextlib.contextmanager
def _claimed(out: Path, *, force: bool, inputs: Iterable, folder: bool, make) -> Iterator[Path]:
    """Checked, locked and cleaned: yields the temporary made by ``make(out)``; discards it when
    the block fails (an OSError about the output becomes an InputError)."""
    inputs = list(inputs)
    check_output(out, force=force, inputs=inputs, folder=folder)
    with _output_errors(out, "create the folder of the output"):
        out.parent.mkdir(parents=True, exist_ok=True)
    with _writer_lock(out):
        clean_leftovers(out)
        check_output(out, force=force, inputs=inputs, folder=folder)
        with _output_errors(out, "create a temporary output beside it"):
            tmp = make(out)
        try:
            yield tmp
        except OSError as exc:
            _discard(tmp)
            err = _written_error(exc, tmp, out)
            if err is None:
                raise
            raise err from None
        except BaseException:
            _discard(tmp)
            raise


# ---------------------------------------------------------------------------------------------
# Output folders
# ---------------------------------------------------------------------------------------------

def _partial_dir(out: Path) -> Path:
    tmp = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}.partial.{_owner_tag()}."))
    os.chmod(tmp, 0o777 & ~_umask())
    return tmp


def _commit_dir(tmp: Path, out: Path, force: bool) -> None:
    """Move the finished ``tmp`` to ``out``; the old content goes only once the new one is there."""
    if out.is_dir() and _has_content(out):
        if not force:
            raise InputError("--out was filled by another program meanwhile; nothing written "
                             "(use --force to replace it)", file=out)
        _swap_in(tmp, out)
    else:
        os.replace(tmp, out)


def _swap_in(tmp: Path, out: Path) -> None:
    """Replace the folder ``out`` by ``tmp``; on failure ``out`` keeps its old content."""
    trash = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}.old.{_owner_tag()}."))
    try:
        os.replace(out, trash / "old")
    except OSError:
        os.rmdir(trash)
        raise
    try:
        os.replace(tmp, out)
    except OSError:
        os.replace(trash / "old", out)
        os.rmdir(trash)
        raise
    shutil.rmtree(trash, ignore_errors=True)


@contextlib.contextmanager
def atomic_output_dir(out: str | os.PathLike, *, force: bool = False,
                      inputs: Iterable[str | os.PathLike] = ()) -> Iterator[Path]:
    """Yield a temporary folder that becomes ``out`` only if the block finishes without error.

    An existing non-empty ``out`` is refused unless ``force``; with ``force`` it is replaced only
    after the new content is complete, so a failure leaves the old content untouched. ``out``
    must neither be, contain nor lie inside one of ``inputs``. One writer per ``out`` at a time;
    leftovers of dead writers are removed first (see the module's docstring).
    """
    out = Path(out)
    with _claimed(out, force=force, inputs=inputs, folder=True, make=_partial_dir) as tmp:
        yield tmp
        with _output_errors(out, "move the finished output into place"):
            _commit_dir(tmp, out, force)


# ---------------------------------------------------------------------------------------------
# Output files
# ---------------------------------------------------------------------------------------------

def _partial_file(out: Path) -> Path:
    # the suffix stays last: writers such as numpy.savez choose the format by it
    fd, tmp = tempfile.mkstemp(dir=out.parent, prefix=f".{out.name}.partial.{_owner_tag()}.",
                               suffix=out.suffix)
    os.close(fd)
    return Path(tmp)


def _commit_file(tmp: Path, out: Path, force: bool) -> None:
    os.chmod(tmp, _default_file_mode())
    if force:
        os.replace(tmp, out)
        return
    try:
        os.link(tmp, out)  # atomic: fails if anything appeared at ``out`` meanwhile
    except FileExistsError:
        raise InputError("output was created by another program meanwhile; nothing written "
                         "(use --force to replace it)", file=out) from None
    except OSError:
        os.replace(tmp, out)  # a file system without hard links; the lock still excludes mmgp writers
        return
    os.unlink(tmp)


@contextlib.contextmanager
def atomic_output_file(path: str | os.PathLike, *, force: bool = False,
                       inputs: Iterable[str | os.PathLike] = ()) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` (same suffix) that becomes ``path`` only if the
    block finishes without error. An existing ``path`` is refused unless ``force``; ``path``
    must not be one of ``inputs``. One writer per ``path`` at a time."""
    path = Path(path)
    with _claimed(path, force=force, inputs=inputs, folder=False, make=_partial_file) as tmp:
        yield tmp
        with _output_errors(path, "move the finished output into place"):
            _commit_file(tmp, path, force)


def write_table(path: str | os.PathLike, df: pd.DataFrame, metadata: dict | None = None, *,
                force: bool = True, inputs: Iterable[str | os.PathLike] = ()) -> None:
    """Write a DataFrame to Parquet (with string metadata) or CSV, completely or not at all.

    ``force`` defaults to True (replace an existing file), as every caller did before it
    existed; a command passes its ``--force`` and its ``inputs``."""
    with atomic_output_file(path, force=force, inputs=inputs) as tmp:
        if tmp.suffix.lower() == ".csv":
            df.to_csv(tmp, index=False)
            return
        import pyarrow as pa
        import pyarrow.parquet as pq

        table = pa.Table.from_pandas(df, preserve_index=False)
        if metadata:
            merged = dict(table.schema.metadata or {})
            merged.update({k.encode(): str(v).encode() for k, v in metadata.items()})
            table = table.replace_schema_metadata(merged)
        pq.write_table(table, tmp)


def atomic_write_bytes(path: str | os.PathLike, data: bytes, *, force: bool = True,
                       inputs: Iterable[str | os.PathLike] = ()) -> None:
    """Write a file completely or not at all (``force``/``inputs`` as in :func:`write_table`)."""
    with atomic_output_file(path, force=force, inputs=inputs) as tmp:
        tmp.write_bytes(data)


def atomic_write_text(path: str | os.PathLike, text: str, *, force: bool = True,
                      inputs: Iterable[str | os.PathLike] = ()) -> None:
    """:func:`atomic_write_bytes` of ``text`` in UTF-8."""
    atomic_write_bytes(path, text.encode("utf-8"), force=force, inputs=inputs)


def write_figure(path: str | os.PathLike, fig, *, force: bool = True, **savefig) -> None:
    """A matplotlib figure saved completely or not at all, in the format of ``path``'s suffix
    (``savefig``: e.g. ``dpi``); the figure is rendered in memory first, then written."""
    buf = io.BytesIO()
    fig.savefig(buf, format=Path(path).suffix.lstrip(".").lower() or "png", **savefig)
    atomic_write_bytes(path, buf.getvalue(), force=force)


@contextlib.contextmanager
def atomic_output_files(out: str | os.PathLike, *,
                        inputs: Iterable[str | os.PathLike] = ()) -> Iterator[Path]:
    """Yield a temporary folder beside ``out`` whose entries are moved into the folder ``out``
    (created when missing) only if the block finishes without error: a failure leaves ``out``
    as it was. Unlike :func:`atomic_output_dir`, the rest of ``out`` stays; an entry of the same
    name is replaced (as ``MultimodalGP.save`` replaces its files). For a library call that
    writes several files into a folder it is given; a command writes its folder whole."""
    out = Path(out)
    with _claimed(out, force=True, inputs=inputs, folder=True, make=_partial_dir) as tmp:
        yield tmp
        with _output_errors(out, "move the finished files into the folder"):
            out.mkdir(exist_ok=True)
            for entry in sorted(tmp.iterdir()):
                os.replace(entry, out / entry.name)
            os.rmdir(tmp)


def jsonable(x):
    """Plain-JSON copy of nested dicts/lists/arrays/numpy scalars; non-finite floats become None
    (JSON has no NaN)."""
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return jsonable(x.tolist())
    if isinstance(x, np.bool_):
        return bool(x)
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, (float, np.floating)):
        x = float(x)
        return x if np.isfinite(x) else None
    return x
