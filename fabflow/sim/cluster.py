"""Where a study's runs execute: a local Dask cluster or a running scheduler.

:func:`dask_client` starts a local cluster, or connects to a scheduler by its
address (``--scheduler``) or through the scheduler file that ``dask scheduler
--scheduler-file`` writes (``--scheduler-file``; :func:`scheduler_file_address`).
The workers of a scheduler may stand anywhere: a study sends them data, not
paths (:attr:`fabflow.sim.run.Study.file_data`), but they must compute what this
machine would. Before any run is submitted every worker's versions of fabflow,
Python, numpy and scipy (:func:`environment`) are compared with this machine's
(:func:`check_environments`); a worker that joins later is checked by each task
it runs (:func:`run_checked`).
"""

from __future__ import annotations

import json
import logging
import math
import platform
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np
import scipy

from fabflow.errors import InputError, UnsupportedError
from fabflow.files import read_text
from fabflow.version import __version__

if TYPE_CHECKING:
    from distributed import Client

T = TypeVar("T")

MAX_SCHEDULER_FILE_BYTES = 2**20
"""Largest scheduler file read (bytes); Dask writes a few hundred."""
MAX_LISTED_WORKERS = 5
"""Workers named in one version message; the rest are counted."""


def scheduler_address(text: str, option: str = "--scheduler") -> str:
    """A Dask scheduler address as ``tcp://HOST:PORT`` (``HOST:PORT`` means TCP).

    Parameters
    ----------
    text
        The address as given.
    option
        The option named as the location of a problem.

    Raises
    ------
    InputError
        Another protocol (TLS needs certificates, ``inproc`` only works inside
        one process), no host or port, or a port out of range.
    """
    from distributed.comm.addressing import parse_host_port

    scheme, _, location = text.strip().rpartition("://")
    expected = "expected tcp://HOST:PORT, e.g. tcp://127.0.0.1:8786"
    if scheme not in ("", "tcp"):
        raise InputError(
            f"unsupported Dask scheduler address {text!r}: {expected}", location=option
        )
    try:
        host, port = parse_host_port(location)
    except ValueError:
        host, port = "", 0
    if not host or any(c.isspace() for c in host) or not 0 < int(port) < 65536:
        raise InputError(f"not a Dask scheduler address: {text!r}: {expected}", location=option)
    return f"tcp://{location}"


def scheduler_file_address(path: str | Path) -> str:
    """The scheduler address in a Dask scheduler file (JSON with ``"address"``).

    Raises
    ------
    InputError
        Naming the file: missing, not a regular file, unreadable, larger than
        :data:`MAX_SCHEDULER_FILE_BYTES`, not JSON (with the line), without an
        ``address``, or an address :func:`scheduler_address` refuses.
    """
    what = "Dask scheduler file"
    text = read_text(path, what, MAX_SCHEDULER_FILE_BYTES)
    hint = "write it with 'dask scheduler --scheduler-file FILE'"
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(
            f"not a {what}: not JSON ({exc.msg}); {hint}", path, f"line {exc.lineno}"
        ) from None
    except (ValueError, RecursionError):
        raise InputError(f"not a {what}: not JSON; {hint}", path) from None
    address = doc.get("address") if isinstance(doc, dict) else None
    if not isinstance(address, str):
        raise InputError(f"not a {what}: no scheduler 'address' in it; {hint}", path)
    try:
        return scheduler_address(address, "--scheduler-file")
    except InputError as exc:
        raise InputError(exc.message, path, "address") from None


def environment() -> dict[str, str]:
    """The versions that fix a run's numbers bit for bit: fabflow, Python, numpy, scipy."""
    return {
        "fabflow": __version__,
        "python": platform.python_version(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
    }


def environment_problem(
    address: str, found: Any, expected: Mapping[str, str], where: str = "here"
) -> str | None:
    """What differs between a worker's :func:`environment` and ``expected``; ``None`` if nothing.

    Parameters
    ----------
    address
        The worker, named in the text.
    found
        What the worker returned: its environment, or the exception it raised
        (e.g. it has no fabflow to run the check with).
    expected
        The environment the worker must have.
    where
        Whose ``expected`` is, in the text (``"here"``: this machine's).
    """
    if isinstance(found, BaseException):
        return (
            f"the Dask worker at {address} cannot run fabflow "
            f"({type(found).__name__}: {found}): install fabflow {expected['fabflow']} there"
        )
    if not isinstance(found, Mapping):
        return f"the Dask worker at {address} gave no versions (got {type(found).__name__})"
    wrong = [
        f"{name} {found.get(name, 'unknown')} ({where} {version})"
        for name, version in expected.items()
        if found.get(name) != version
    ]
    if not wrong:
        return None
    return f"the Dask worker at {address} runs " + ", ".join(wrong)


def check_environments(
    workers: Mapping[str, Any], expected: Mapping[str, str], option: str = "--scheduler"
) -> None:
    """Refuse workers whose versions differ from this machine's.

    Parameters
    ----------
    workers
        Worker address to its :func:`environment` (or the exception it raised),
        as ``client.run(environment, on_error="return")`` gives them.
    expected
        This machine's :func:`environment`.
    option
        The option named as the location of the problem.

    Raises
    ------
    UnsupportedError
        Naming every differing worker (up to :data:`MAX_LISTED_WORKERS`), its
        versions and this machine's.
    """
    problems = [
        p
        for address in sorted(workers)
        if (p := environment_problem(address, workers[address], expected)) is not None
    ]
    if not problems:
        return
    shown = problems[:MAX_LISTED_WORKERS]
    if len(problems) > len(shown):
        shown.append(f"and {len(problems) - len(shown)} more worker(s)")
    raise UnsupportedError(
        "; ".join(shown) + ": a study needs the same fabflow, Python, numpy and scipy on "
        "every worker as here to give the same results; install them there or stop the worker",
        location=option,
    )


def run_checked(expected: Mapping[str, str], func: Callable[..., T], *args: Any) -> T:
    """``func(*args)`` on a Dask worker whose :func:`environment` is ``expected``.

    The task of a study: it also guards against a worker that joined after the
    versions were checked.

    Raises
    ------
    UnsupportedError
        When this worker's versions differ (naming it and both versions).
    """
    from distributed import get_worker

    problem = environment_problem(get_worker().address, environment(), expected, "client")
    if problem is not None:
        raise UnsupportedError(
            problem + ": a study needs the same versions on every worker as on the client; "
            "install them there or stop the worker"
        )
    return func(*args)


@contextmanager
def _scheduler_client(
    address: str, shown: str, option: str, timeout: float, start_workers: str
) -> Iterator[Client]:
    """A client of the scheduler at ``address`` with at least one worker, every worker checked."""
    from distributed import Client

    try:
        client = Client(address, timeout=timeout)
    except (OSError, TimeoutError, ValueError) as exc:
        raise InputError(
            f"cannot connect to the Dask scheduler at {shown}: {exc}", location=option
        ) from None
    with client:
        try:
            client.wait_for_workers(1, timeout=timeout)
        except (TimeoutError, OSError):
            raise InputError(
                f"the Dask scheduler at {shown} has no worker after {timeout:g} s: "
                f"start workers ({start_workers}) or wait longer (--timeout)",
                location=option,
            ) from None
        check_environments(client.run(environment, on_error="return"), environment(), option)
        yield client


KEPT_HEAP = "MALLOC_TRIM_THRESHOLD_"
"""The variable Dask's nanny sets in its workers' environment (64 KiB by default) so that
glibc returns freed memory to the system at once. Set, it also stops glibc from raising
its mmap threshold, so every array over 128 KiB is mapped and unmapped afresh: a
simulated run, which makes many such arrays, took 1.3-1.4 times its CPU time in a plain
process. The local cluster's workers keep glibc's own default; workers started by hand
keep Dask's unless their Dask configuration leaves it out of
``distributed.nanny.pre-spawn-environ``."""


def worker_environ() -> dict[str, Any]:
    """The environment Dask's nanny gives the local cluster's workers: its configured
    one (``distributed.nanny.pre-spawn-environ``: one thread per linear-algebra
    library) without :data:`KEPT_HEAP`."""
    import dask

    environ = dict(dask.config.get("distributed.nanny.pre-spawn-environ", default={}) or {})
    environ.pop(KEPT_HEAP, None)
    return environ


@contextmanager
def dask_client(
    scheduler: str | None = None,
    n_workers: int = 2,
    timeout: float = 30.0,
    dashboard: bool = False,
    scheduler_file: str | Path | None = None,
) -> Iterator[Client]:
    """A Dask client: connected to a running scheduler, or on a new local cluster.

    Parameters
    ----------
    scheduler
        Address of a running scheduler (``tcp://host:8786``); its workers need the
        same fabflow, Python, numpy and scipy as this machine (checked). ``None``
        (and no ``scheduler_file``) starts a :class:`~distributed.LocalCluster` of
        ``n_workers`` single-threaded worker processes, closed on exit.
    n_workers
        Worker processes of the local cluster.
    timeout
        Seconds to wait for the scheduler to answer, and then for its first worker.
    dashboard
        Serve the local cluster's dashboard (on 127.0.0.1, a free port; its address
        is ``client.dashboard_link``). Off by default. The local cluster listens on
        127.0.0.1 only, whether the dashboard is on or off.
    scheduler_file
        Instead of ``scheduler``: the file ``dask scheduler --scheduler-file`` wrote,
        holding its address.

    Raises
    ------
    InputError
        When both ``scheduler`` and ``scheduler_file`` are given, the address or
        the file is malformed, the scheduler cannot be reached, or it has no worker
        within ``timeout``.
    UnsupportedError
        When a worker runs other versions than this machine (:func:`check_environments`).
    """
    import dask
    from distributed import Client, LocalCluster

    if not (math.isfinite(timeout) and timeout > 0):
        raise InputError(
            f"must be a positive number of seconds, got {timeout}", location="--timeout"
        )
    if scheduler is not None and scheduler_file is not None:
        raise InputError(
            "give either --scheduler or --scheduler-file, not both", location="--scheduler-file"
        )
    if scheduler_file is not None:
        address = scheduler_file_address(scheduler_file)
        shown = f"{address} (from {scheduler_file})"
        start = f"dask worker --scheduler-file {scheduler_file}"
        with _scheduler_client(address, shown, "--scheduler-file", timeout, start) as client:
            yield client
        return
    if scheduler is not None:
        address = scheduler_address(scheduler)
        start = f"dask worker {address}"
        with _scheduler_client(address, repr(scheduler), "--scheduler", timeout, start) as client:
            yield client
        return
    http = (
        "127.0.0.1:0"  # the scheduler's HTTP server (health, metrics) runs even without a dashboard
    )
    with (
        dask.config.set({"distributed.nanny.pre-spawn-environ": worker_environ()}),
        LocalCluster(
            n_workers=n_workers,
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            dashboard_address=http if dashboard else None,
            scheduler_kwargs=None if dashboard else {"dashboard_address": http},
            silence_logs=logging.ERROR,
        ) as cluster,
        Client(cluster) as client,
    ):
        yield client
