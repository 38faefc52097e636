"""Atomic output folders.

A run writes into a fresh staging folder beside the destination; only when the
whole run has completed is the staging folder swapped into place. A run that
fails leaves the destination exactly as it was before (absent, or holding the
previous complete result) and removes its staging folder.

fabflow only ever replaces a folder it wrote itself (it carries the marker file
:data:`MARKER`) or an empty one: pointing ``-o`` at a project folder or a home
directory is refused, never wiped.

Beside an output folder ``OUT`` a run keeps, only while it runs:

* ``.OUT.lock``: the lock that one run at a time holds on ``OUT`` (a second run
  for the same folder stops at once with exit code 2);
* ``.OUT.staging-PID-XXXX``: the staging folder of the run with process id PID;
* ``.OUT.previous-PID-XXXX``: the previous output while it is replaced, on a
  platform without an atomic exchange of two folders.

A run stopped by SIGTERM or SIGINT (Ctrl-C) removes its staging folder. One that
could not clean up (SIGKILL, a power cut) leaves these names behind; the next
run for ``OUT`` removes them, restores a previous output that was moved aside
with no new one in its place, and says so in one line.
"""

from __future__ import annotations

import _thread
import contextlib
import ctypes
import ctypes.util
import errno
import os
import secrets
import shutil
import signal
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from fabflow.errors import InputError
from fabflow.json_format import json_text

try:
    import fcntl
except ImportError:  # pragma: no cover - Windows: no advisory locks
    fcntl = None  # type: ignore[assignment]

MARKER = ".fabflow-output"
"""File in every output folder fabflow writes; only such folders are replaced."""

_AT_FDCWD = -100
_RENAME_EXCHANGE = 2
_UNSUPPORTED = {errno.ENOSYS, errno.EINVAL, errno.ENOTSUP, errno.EOPNOTSUPP}
"""renameat2 errors meaning "this kernel or file system cannot exchange": fall back."""
_HANDLED_SIGNALS = ("SIGTERM", "SIGINT")


def _reached(point: str) -> None:
    """Mark a named point of a run (a no-op; the kill test replaces it to stop runs there).

    Points: ``staging-created``, ``before-replace``, ``moved-aside`` (only
    without an atomic exchange: the previous output moved aside, the new one not
    yet in place) and ``replaced`` (the new output in place, the previous one not
    yet removed).
    """


def _target(out: Path) -> Path:
    """The folder to replace: ``out`` itself, or where ``out`` points if it is a symbolic link.

    A symbolic link given as ``-o`` is kept: the folder it points to is replaced
    (staged beside that folder, on its file system), so the link goes on
    pointing at the new output.
    """
    if not out.is_symlink():
        return out
    target = Path(os.path.realpath(out))
    if target.is_symlink():
        raise InputError("output path is a symbolic link that points to itself (a loop)", out)
    return target


def _check_name(out: Path, shown: Path) -> None:
    real = Path(os.path.realpath(out))
    if shown.name in ("", ".", "..") or real == Path(real.anchor):
        raise InputError("choose a named output folder, not the current or root folder", shown)


def _check_destination(out: Path, shown: Path) -> None:
    if out.exists() and not out.is_dir():
        raise InputError("output path exists and is not a folder", shown)
    if out.is_dir() and any(out.iterdir()) and not (out / MARKER).exists():
        raise InputError(
            "output folder exists, is not empty and was not written by fabflow; "
            "choose another folder or remove it first (fabflow only replaces its own outputs)",
            shown,
        )


class _Signals:
    """SIGTERM and SIGINT raise into the run (so its cleanup runs), except while held.

    SIGTERM raises :class:`SystemExit` with code 143 (128 + 15, what a shell
    reports for a process ended by SIGTERM), SIGINT :class:`KeyboardInterrupt`.
    While :meth:`held` (moving folders, removing the staging folder) a signal is
    noted and raised when the step is done, so a step is never cut in half.
    Handlers are only installed in the main thread (Python delivers signals
    there), never over a signal the caller ignores (``nohup``, a background
    job), and are restored on exit.

    A handler that runs inside a weakref callback or a ``__del__`` (the garbage
    collector runs them between any two steps) raises where Python ignores
    exceptions: it prints "Exception ignored" and goes on, and the signal would
    be lost. :meth:`_unraisable`, installed as :data:`sys.unraisablehook` for
    the run, takes that exception and has the signal raised again in the main
    thread a millisecond later.
    """

    def __init__(self) -> None:
        self.holding = False
        self.pending: int | None = None
        self.raised: int | None = None
        self.owed: int | None = None
        self.timer: threading.Timer | None = None
        self.previous: dict[int, Any] = {}
        self.previous_hook: Any = None

    def _handle(self, signum: int, frame: object) -> None:
        if self.holding:
            self.pending = signum
            return
        self.raised, self.owed = signum, None
        self._raise(signum)

    def _unraisable(self, unraisable: Any) -> None:
        """:data:`sys.unraisablehook`: a signal's exception lost in a callback is raised again."""
        signum = self.raised
        if signum is not None and isinstance(unraisable.exc_value, SystemExit | KeyboardInterrupt):
            # not from here: the hook runs inside the callback, where it would be lost again;
            # a run that ends first raises it on restoring (restore)
            self.raised, self.owed = None, signum
            self.timer = threading.Timer(0.001, _thread.interrupt_main, (signum,))
            self.timer.start()
            return
        (self.previous_hook or sys.__unraisablehook__)(unraisable)

    @staticmethod
    def _raise(signum: int) -> None:
        if signum == signal.SIGINT:
            raise KeyboardInterrupt
        raise SystemExit(128 + signum)

    def install(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return
        for name in _HANDLED_SIGNALS:
            signum = getattr(signal, name, None)
            if signum is None:  # pragma: no cover - not on this platform
                continue
            current = signal.getsignal(signum)
            if current is signal.SIG_IGN:
                continue
            self.previous[signum] = current
            signal.signal(signum, self._handle)
        if self.previous:
            self.previous_hook, sys.unraisablehook = sys.unraisablehook, self._unraisable

    def restore(self) -> None:
        if self.timer is not None:
            self.timer.cancel()
        for signum, handler in self.previous.items():
            signal.signal(signum, handler if handler is not None else signal.SIG_DFL)
        if self.previous:
            sys.unraisablehook = self.previous_hook
        self.previous.clear()
        owed, self.owed = self.owed, None
        if owed is not None:  # lost in a callback and not raised again before the end
            self._raise(owed)

    @contextlib.contextmanager
    def held(self) -> Iterator[None]:
        self.holding = True
        try:
            yield
        finally:
            self.holding = False
            signum, self.pending = self.pending, None
            if signum is not None:
                self._raise(signum)


@contextlib.contextmanager
def _output_lock(out: Path, shown: Path, signals: _Signals) -> Iterator[None]:
    """Hold the exclusive lock of output folder ``out`` (``.OUT.lock`` beside it).

    The lock is an ``flock`` on a file beside the folder, so the kernel drops it
    when its holder dies, however it dies. A second run does not wait: a build
    takes seconds to minutes, so it stops at once with an :class:`InputError`.
    The file is removed by its holder; a run that locked a file another run had
    just removed checks the name still points to it and locks again. Signals
    wait while the file is removed, so a stopped run leaves no lock file.
    """
    if fcntl is None:  # pragma: no cover - no advisory locks on this platform
        yield
        return
    path = out.parent / f".{out.name}.lock"
    fd: int | None = None
    try:
        with signals.held():
            fd = _acquire(path, shown)
        yield
    finally:
        if fd is not None:
            with signals.held():
                with contextlib.suppress(OSError):
                    path.unlink()
                os.close(fd)


def _acquire(path: Path, shown: Path) -> int:
    """Open and lock the lock file ``path``; return its descriptor (see :func:`_output_lock`)."""
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise InputError(
                f"cannot create the output folder's lock file {path.name}: {exc.strerror or exc}",
                shown,
            ) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            holder = os.pread(fd, 32, 0).decode("ascii", "replace").strip()
            os.close(fd)
            if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise InputError(f"cannot lock the output folder: {exc.strerror}", shown) from None
            who = f" (process {holder})" if holder.isdigit() else ""
            raise InputError(
                f"another fabflow run{who} is writing this output folder; "
                "wait for it to finish or choose another folder",
                shown,
            ) from None
        try:
            same = os.path.samestat(os.fstat(fd), os.stat(path))
        except FileNotFoundError:
            same = False
        if same:
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
            return fd
        os.close(fd)  # the holder removed the file between our open and our lock


def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return False  # this process holds the lock and has not staged yet: a leftover
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _owner(name: str, prefix: str) -> int | None:
    """The process id in a leftover's name ``PREFIX PID-XXXX`` (``None`` if it has none)."""
    head = name[len(prefix) :].split("-", 1)[0]
    return int(head) if head.isdigit() else None


def _size(path: Path) -> int:
    total = 0
    for root, _dirs, files in os.walk(path):
        for f in files:
            with contextlib.suppress(OSError):
                total += os.lstat(os.path.join(root, f)).st_size
    return total


def _recover(out: Path) -> str | None:
    """Clean up after runs for ``out`` that were killed; return what was done (or ``None``).

    Called with the lock of ``out`` held, so no other run is writing it: a
    staging folder whose process is gone is a leftover and is removed; a
    previous output moved aside is put back when ``out`` is missing (the run
    was killed between moving it aside and moving its own output in), else
    removed. A staging folder named after a live process other than this one is
    left alone.
    """
    staging_prefix = f".{out.name}.staging-"
    previous_prefix = f".{out.name}.previous-"
    staged: list[Path] = []
    previous: list[Path] = []
    for p in out.parent.iterdir():
        if p.name.startswith(staging_prefix) and p.is_dir() and not p.is_symlink():
            pid = _owner(p.name, staging_prefix)
            if pid is None or not _pid_alive(pid):
                staged.append(p)
        elif p.name.startswith(previous_prefix) and p.is_dir() and not p.is_symlink():
            previous.append(p)
    done = []
    if previous and not out.exists() and not out.is_symlink():
        previous.sort(key=lambda p: p.stat().st_mtime)
        newest = previous.pop()
        if (newest / MARKER).exists():
            newest.rename(out)
            done.append("restored the previous output that an interrupted run had moved aside")
        else:
            previous.append(newest)
    leftovers = staged + previous
    if leftovers:
        size = sum(_size(p) for p in leftovers)
        for p in leftovers:
            shutil.rmtree(p, ignore_errors=True)
        done.append(
            f"removed {len(leftovers)} folder(s) left by interrupted runs ({size / 1e6:.1f} MB)"
        )
    return "; ".join(done) or None


def _libc_renameat2() -> Any:
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)
        fn = libc.renameat2
    except (OSError, AttributeError):
        return None
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    fn.restype = ctypes.c_int
    return fn


_renameat2 = _libc_renameat2()


def _exchange(a: Path, b: Path) -> bool:
    """Swap folders ``a`` and ``b`` in one atomic step; ``False`` if the platform cannot.

    Linux's ``renameat2(RENAME_EXCHANGE)`` (kernel 3.15, glibc 2.28; ext4, xfs,
    btrfs, tmpfs, ...) swaps the two names at once: there is no moment at which
    neither exists. Elsewhere, or when the kernel or the file system does not
    support it (``ENOSYS``, ``EINVAL``, ``ENOTSUP``), the caller falls back to
    two renames.

    Raises
    ------
    OSError
        Any other failure of the exchange.
    """
    if _renameat2 is None:
        return False
    if _renameat2(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in _UNSUPPORTED:
        return False
    raise OSError(err, os.strerror(err), str(b))


def _replace(staging: Path, out: Path) -> Path | None:
    """Put ``staging`` in place of ``out``; return the folder now holding the old output.

    With an atomic exchange the old output ends up under the staging folder's
    name. Without one, the old output is renamed to ``.OUT.previous-PID-XXXX``
    first; a kill between the two renames leaves no ``out`` for a moment, which
    :func:`_recover` repairs at the next run (the lock guarantees no other run
    looks at ``out`` meanwhile).
    """
    if not (out.exists() or out.is_symlink()):
        staging.rename(out)
        return None
    if _exchange(staging, out):
        return staging
    previous = out.parent / f".{out.name}.previous-{os.getpid()}-{secrets.token_hex(4)}"
    out.rename(previous)
    _reached("moved-aside")
    try:
        staging.rename(out)
    except OSError:
        previous.rename(out)
        raise
    return previous


def _make_staging(staging: Path, shown: Path) -> None:
    """Create the staging folder (usual permissions) with the marker file in it."""
    try:
        staging.mkdir()
        (staging / MARKER).write_text("written by fabflow; replaced by the next run\n")
    except OSError as exc:
        raise InputError(f"cannot create the output folder: {exc.strerror or exc}", shown) from None


@contextlib.contextmanager
def atomic_output_dir(out: str | Path) -> Iterator[Path]:
    """Yield a staging folder that replaces ``out`` when the block completes.

    Why each step is the way it is:

    * **Lock**: the run holds an exclusive lock on ``out`` from its checks to
      the end, so two runs for one folder cannot interleave their renames (they
      raced before: ``Directory not empty``). The second run stops at once with
      an :class:`InputError` rather than waiting minutes.
    * **Exchange**: an existing ``out`` is swapped with the staging folder in
      one atomic step (Linux ``renameat2(RENAME_EXCHANGE)``), so a kill at any
      moment leaves the old complete output or the new one, never none. Where
      the platform cannot exchange, ``out`` is moved aside and the staging
      folder moved in; a kill between the two is repaired by the next run, which
      puts the previous output back.
    * **Signals**: SIGTERM and SIGINT raise into this block, whose cleanup
      removes the staging folder; the moves and the cleanup themselves finish
      before the signal is acted on (the process then exits with 143 for
      SIGTERM). Previous handlers are restored on exit.
    * **Leftovers**: staging folders (named after their process id) of runs
      that are gone, and previous outputs moved aside, are removed by the next
      run for ``out``, which prints one line saying so.
    * **Symbolic link**: when ``out`` is a symbolic link the folder it points to
      is replaced and the link kept.

    Parameters
    ----------
    out
        The destination folder. Its parent is created if needed. An existing
        ``out`` is replaced only after the block has finished without error, and
        only if it is empty or an earlier fabflow output.

    Yields
    ------
    Path
        An empty folder (but for the marker file) on the same file system as
        ``out``; write everything there.

    Raises
    ------
    InputError
        When ``out`` cannot be used (a file, a foreign non-empty folder, not
        writable, a symbolic link loop) or another run is writing it.
    """
    shown = Path(out)
    target = _target(shown)
    _check_name(target, shown)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create the output folder: {exc.strerror or exc}", shown) from None
    signals = _Signals()
    signals.install()
    try:
        with _output_lock(target, shown, signals):
            _check_destination(target, shown)
            with signals.held():
                try:
                    note = _recover(target)
                except OSError as exc:
                    note = f"could not clean up after interrupted runs: {exc.strerror or exc}"
            if note:
                sys.stderr.write(f"note: {shown}: {note}\n")
            staging = target.parent / f".{target.name}.staging-{os.getpid()}-{secrets.token_hex(4)}"
            try:
                _make_staging(staging, shown)
                _reached("staging-created")
                yield staging
                _reached("before-replace")
                with signals.held():
                    try:
                        old = _replace(staging, target)
                    except OSError as exc:
                        raise InputError(
                            f"cannot move the results into place: {exc.strerror or exc}", shown
                        ) from None
                    _reached("replaced")
                    if old is not None:
                        shutil.rmtree(old, ignore_errors=True)
            finally:
                with signals.held():
                    if staging.exists():
                        shutil.rmtree(staging, ignore_errors=True)
    finally:
        signals.restore()


@contextlib.contextmanager
def atomic_file(path: str | Path) -> Iterator[Path]:
    """Yield a temporary file beside ``path`` that replaces ``path`` when the block completes.

    For a single output file (an export): write the whole file to the yielded
    path (it exists, empty, with the usual permissions); it is renamed onto
    ``path`` in one step only when the block finishes without error. A block
    that fails, or a run stopped by SIGTERM or SIGINT, removes the temporary
    file and leaves ``path`` as it was. A symbolic link given as ``path`` is
    kept: the file it points to is replaced.

    Parameters
    ----------
    path
        The file to write. Its folder is created if needed.

    Yields
    ------
    Path
        ``.NAME.tmp-PID-XXXX`` beside the target, on the same file system.

    Raises
    ------
    InputError
        When ``path`` is a folder, or its folder cannot be created or written.
    """
    shown = Path(path)
    target = Path(os.path.realpath(shown)) if shown.is_symlink() else shown
    if target.is_dir():
        raise InputError("output path is a folder; expected a file name", shown)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(
            f"cannot create the output file's folder: {exc.strerror or exc}", shown
        ) from None
    tmp = target.parent / f".{target.name}.tmp-{os.getpid()}-{secrets.token_hex(4)}"
    signals = _Signals()
    signals.install()
    try:
        try:
            os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
        except OSError as exc:
            reason = exc.strerror or exc
            raise InputError(f"cannot write the output file: {reason}", shown) from None
        try:
            yield tmp
            with signals.held():
                try:
                    os.replace(tmp, target)
                except OSError as exc:
                    raise InputError(
                        f"cannot move the output file into place: {exc.strerror or exc}", shown
                    ) from None
        finally:
            with signals.held(), contextlib.suppress(OSError):
                tmp.unlink(missing_ok=True)
    finally:
        signals.restore()


def write_json(path: str | Path, data: Any) -> Path:
    """Write ``data`` as indented JSON (numpy converted, NaN and infinity as null).

    Parameters
    ----------
    path
        Target file; its parent folder must exist.
    data
        JSON-compatible data, possibly holding numpy arrays.
    """
    path = Path(path)
    path.write_text(json_text(data), encoding="utf-8")
    return path
