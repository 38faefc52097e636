"""Atomic output folders: exchange, lock, signals, leftovers of killed runs, links, JSON."""

from __future__ import annotations

import ctypes
import errno
import json
import math
import os
import signal
import subprocess
import sys
import time
import weakref
from pathlib import Path

import numpy as np
import pytest
from helpers import DATA, PROJECTS, ROOT

import fabflow.output as output
from fabflow.errors import InputError
from fabflow.json_format import json_text
from fabflow.output import MARKER, atomic_output_dir


def write_output(out: Path, name: str, text: str) -> None:
    with atomic_output_dir(out) as staging:
        (staging / name).write_text(text)


def listing(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


def dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_the_exchange_works_on_this_file_system(tmp_path: Path) -> None:
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir()
    b.mkdir()
    (a / "from_a").touch()
    (b / "from_b").touch()
    if not output._exchange(a, b):
        pytest.skip("no atomic exchange on this platform or file system")
    assert listing(a) == ["from_b"] and listing(b) == ["from_a"]


def test_replacing_uses_the_exchange_and_leaves_nothing_beside(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "out"
    write_output(out, "first.txt", "1")
    swaps: list[tuple[Path, Path]] = []
    real = output._exchange
    monkeypatch.setattr(output, "_exchange", lambda a, b: swaps.append((a, b)) or real(a, b))
    write_output(out, "second.txt", "2")
    assert len(swaps) == 1 and swaps[0][1] == out
    assert listing(out) == [MARKER, "second.txt"]
    assert listing(tmp_path) == ["out"]


@pytest.mark.parametrize("err", [errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP])
def test_an_unsupported_exchange_falls_back_to_two_renames(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, err: int
) -> None:
    def unsupported(*args: object) -> int:
        ctypes.set_errno(err)
        return -1

    monkeypatch.setattr(output, "_renameat2", unsupported)
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir()
    b.mkdir()
    assert output._exchange(a, b) is False
    out = tmp_path / "out"
    write_output(out, "first.txt", "1")
    write_output(out, "second.txt", "2")
    assert listing(out) == [MARKER, "second.txt"]
    assert listing(tmp_path) == ["a", "b", "out"]


def test_no_renameat2_falls_back(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(output, "_renameat2", None)
    out = tmp_path / "out"
    write_output(out, "first.txt", "1")
    write_output(out, "second.txt", "2")
    assert listing(out) == [MARKER, "second.txt"]
    assert listing(tmp_path) == ["out"]


def test_another_exchange_error_is_an_input_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def denied(*args: object) -> int:
        ctypes.set_errno(errno.EACCES)
        return -1

    out = tmp_path / "out"
    write_output(out, "first.txt", "1")
    monkeypatch.setattr(output, "_renameat2", denied)
    with pytest.raises(InputError, match="cannot move the results into place: Permission"):
        write_output(out, "second.txt", "2")
    assert listing(out) == [MARKER, "first.txt"]
    assert listing(tmp_path) == ["out"]


def test_a_second_run_for_the_same_folder_stops_with_a_message(tmp_path: Path) -> None:
    out = tmp_path / "out"
    with atomic_output_dir(out) as staging:
        (staging / "a.txt").write_text("a")
        with pytest.raises(InputError) as info:
            write_output(out, "b.txt", "b")
        message = str(info.value)
        assert "another fabflow run" in message and f"process {os.getpid()}" in message
        assert str(out) in message
        assert listing(tmp_path) == sorted([".out.lock", staging.name])
    assert listing(out) == [MARKER, "a.txt"]
    assert listing(tmp_path) == ["out"]


def test_a_second_cli_run_exits_2_while_the_folder_is_locked(cli, tmp_path: Path) -> None:
    out = tmp_path / "out"
    with atomic_output_dir(out):
        result = cli("plan", str(PROJECTS / "cabin"), "-o", str(out))
    assert result.returncode == 2
    assert "another fabflow run" in result.stderr and "Traceback" not in result.stderr
    assert listing(out) == [MARKER]  # what the first run wrote, nothing of the second


def test_a_lock_file_left_by_a_killed_run_does_not_block(tmp_path: Path) -> None:
    (tmp_path / ".out.lock").write_text("12345\n")
    write_output(tmp_path / "out", "a.txt", "a")
    assert listing(tmp_path) == ["out"]


def test_leftovers_of_dead_runs_are_removed_with_one_message(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    write_output(out, "a.txt", "a")
    for name in (f".out.staging-{dead_pid()}-0a1b", ".out.staging-old5x_k", ".out.previous-1-ff"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "big.bin").write_bytes(b"x" * 500_000)
    live = tmp_path / f".out.staging-{os.getppid()}-beef"  # a live process: left alone
    live.mkdir()
    other = tmp_path / f".other.staging-{dead_pid()}-0000"  # another output's: not ours
    other.mkdir()
    capsys.readouterr()
    write_output(out, "b.txt", "b")
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert "removed 3 folder(s) left by interrupted runs (1.5 MB)" in err and str(out) in err
    assert listing(tmp_path) == sorted(["out", live.name, other.name])
    capsys.readouterr()
    write_output(out, "c.txt", "c")
    assert capsys.readouterr().err == ""


def test_a_previous_output_moved_aside_is_restored(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    write_output(out, "old.txt", "old")
    out.rename(tmp_path / ".out.previous-4242-abcd")  # killed between the two renames
    (tmp_path / f".out.staging-{dead_pid()}-abcd").mkdir()
    with pytest.raises(InputError, match="later failure"), atomic_output_dir(out):
        raise InputError("later failure")
    err = capsys.readouterr().err
    assert "restored the previous output" in err and "removed 1 folder(s)" in err
    assert listing(out) == [MARKER, "old.txt"]
    assert listing(tmp_path) == ["out"]


def test_sigterm_removes_the_staging_folder_and_exits_143(tmp_path: Path) -> None:
    out = tmp_path / "out"
    write_output(out, "old.txt", "old")
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(SystemExit) as info, atomic_output_dir(out) as staging:
        assert signal.getsignal(signal.SIGTERM) is not before
        (staging / "new.txt").write_text("new")
        os.kill(os.getpid(), signal.SIGTERM)
        pytest.fail("SIGTERM did not stop the run")
    assert info.value.code == 143
    assert signal.getsignal(signal.SIGTERM) is before
    assert listing(out) == [MARKER, "old.txt"]
    assert listing(tmp_path) == ["out"]


def _sigterm_when_collected() -> weakref.ref:
    """A weak reference whose callback sends SIGTERM, its object already collected: the
    signal's handler runs inside the callback (where Python ignores exceptions)."""

    class Collected:
        pass

    def callback(_: object) -> None:
        os.kill(os.getpid(), signal.SIGTERM)
        sum(range(1000))  # the handler runs here, inside the callback

    thing = Collected()
    ref = weakref.ref(thing, callback)
    del thing
    return ref


def test_a_sigterm_inside_a_garbage_collector_callback_still_stops_the_run(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    # Python ignores an exception raised inside a weakref callback or __del__ (it
    # prints "Exception ignored ..." with a traceback and goes on): a SIGTERM whose
    # handler ran there was lost, and the build ran to its end
    out = tmp_path / "out"
    write_output(out, "old.txt", "old")
    hook = sys.unraisablehook
    with pytest.raises(SystemExit) as info, atomic_output_dir(out) as staging:
        (staging / "new.txt").write_text("new")
        ref = _sigterm_when_collected()
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline:
            time.sleep(0.001)
        pytest.fail(f"SIGTERM was lost in the callback of {ref}")
    assert info.value.code == 143
    assert "Exception ignored" not in capfd.readouterr().err
    assert sys.unraisablehook is hook
    assert listing(out) == [MARKER, "old.txt"]
    assert listing(tmp_path) == ["out"]


def test_a_sigterm_lost_in_a_callback_at_the_end_of_the_run_still_stops_it(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    # the callback's signal is raised again a millisecond later; a run that ends
    # before that raises it on the way out instead of dropping it
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as info, atomic_output_dir(out) as staging:
        (staging / "new.txt").write_text("new")
        ref = _sigterm_when_collected()  # the last statement: the run ends within the millisecond
    assert info.value.code == 143 and ref() is None
    time.sleep(0.01)  # the cancelled re-raise does not come afterwards
    assert "Exception ignored" not in capfd.readouterr().err


def test_sigint_is_a_keyboard_interrupt_that_cleans_up(tmp_path: Path) -> None:
    out = tmp_path / "out"
    # Python's own SIGINT handling, whatever an earlier test in this process left
    # (an ignored SIGINT stays ignored: test_an_ignored_signal_stays_ignored)
    outer = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt), atomic_output_dir(out):
            signal.raise_signal(signal.SIGINT)  # to this thread, not any of the process
            pytest.fail("SIGINT did not stop the run")
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGINT, outer)
    assert listing(tmp_path) == []


def test_a_signal_during_the_replacement_waits_for_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "out"
    write_output(out, "old.txt", "old")

    def term_at(point: str) -> None:
        if point == "replaced":
            os.kill(os.getpid(), signal.SIGTERM)

    monkeypatch.setattr(output, "_reached", term_at)
    with pytest.raises(SystemExit), atomic_output_dir(out) as staging:
        (staging / "new.txt").write_text("new")
    assert listing(out) == [MARKER, "new.txt"]
    assert listing(tmp_path) == ["out"]


def test_an_ignored_signal_stays_ignored(tmp_path: Path) -> None:
    before = signal.signal(signal.SIGTERM, signal.SIG_IGN)
    try:
        with atomic_output_dir(tmp_path / "out"):
            assert signal.getsignal(signal.SIGTERM) is signal.SIG_IGN
            os.kill(os.getpid(), signal.SIGTERM)
        assert signal.getsignal(signal.SIGTERM) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGTERM, before)
    assert listing(tmp_path) == ["out"]


def test_a_symbolic_link_is_kept_and_its_target_replaced(tmp_path: Path) -> None:
    real = tmp_path / "disk" / "results"
    write_output(real, "old.txt", "old")
    link = tmp_path / "out"
    link.symlink_to(real)
    write_output(link, "new.txt", "new")
    assert link.is_symlink() and link.resolve() == real.resolve()
    assert listing(real) == [MARKER, "new.txt"]
    assert listing(tmp_path) == ["disk", "out"]
    assert listing(tmp_path / "disk") == ["results"]


def test_a_dangling_link_gets_its_target_created(tmp_path: Path) -> None:
    link = tmp_path / "out"
    link.symlink_to(tmp_path / "later" / "results")
    write_output(link, "new.txt", "new")
    assert link.is_symlink()
    assert listing(tmp_path / "later" / "results") == [MARKER, "new.txt"]


def test_a_link_to_a_foreign_folder_or_a_loop_is_refused(tmp_path: Path) -> None:
    home = tmp_path / "home"
    home.mkdir()
    (home / "notes.txt").write_text("keep")
    (tmp_path / "out").symlink_to(home)
    with pytest.raises(InputError, match="not written by fabflow"):
        write_output(tmp_path / "out", "x.txt", "x")
    assert listing(home) == ["notes.txt"]
    (tmp_path / "loop").symlink_to(tmp_path / "loop")
    with pytest.raises(InputError, match="loop"):
        write_output(tmp_path / "loop", "x.txt", "x")
    assert listing(tmp_path) == ["home", "loop", "out"]


def test_json_text_never_writes_nan_or_infinity() -> None:
    data = {"a": math.nan, "b": [math.inf, -math.inf, 1.5], "c": np.array([np.nan, 2.0])}
    text = json_text(data)
    assert "NaN" not in text and "Infinity" not in text
    assert json.loads(text) == {"a": None, "b": [None, None, 1.5], "c": [None, 2.0]}
    assert json_text([1.0, math.nan], indent=None) == "[1.0, null]\n"


def test_two_builds_racing_for_one_folder(tmp_path: Path) -> None:
    out = tmp_path / "out"
    args = [sys.executable, "-m", "fabflow", "build", str(DATA / "sim" / "project.yaml")]
    env = dict(os.environ, COLUMNS="200", NO_COLOR="1")
    runs = [
        subprocess.Popen(
            [*args, "-o", str(out)],
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
        )
        for _ in range(2)
    ]
    results = [(p.wait(timeout=120), p.stderr.read()) for p in runs]
    for p in runs:
        p.stdout.close()
        p.stderr.close()
    assert {code for code, _ in results} <= {0, 2}, results
    assert any(code == 0 for code, _ in results)
    for code, err in results:
        assert "Traceback" not in err
        if code == 2:
            assert "another fabflow run" in err
    assert (out / MARKER).exists() and json.loads((out / "summary.json").read_text())
    assert listing(tmp_path) == ["out"]


def test_every_json_goes_through_json_text() -> None:
    offenders = [
        f"{path.relative_to(ROOT)}:{k}"
        for path in sorted((ROOT / "fabflow").rglob("*.py"))
        if path.name != "json_format.py"
        for k, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
        if "json.dump" in line
    ]
    assert not offenders, "write JSON with fabflow.json_format.json_text: " + ", ".join(offenders)


def test_a_link_loop_above_the_output_is_refused(tmp_path: Path) -> None:
    (tmp_path / "loop").symlink_to(tmp_path / "loop")
    with pytest.raises(InputError, match="cannot create the output folder"):
        write_output(tmp_path / "loop" / "out", "x.txt", "x")


def test_a_cleanup_that_fails_is_a_note_not_a_failure(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    def denied(out: Path) -> None:
        raise PermissionError(errno.EACCES, "Permission denied")

    monkeypatch.setattr(output, "_recover", denied)
    write_output(tmp_path / "out", "a.txt", "a")
    assert "could not clean up after interrupted runs: Permission denied" in capsys.readouterr().err
    assert listing(tmp_path / "out") == [MARKER, "a.txt"]


def test_atomic_file_replaces_only_with_a_complete_file(tmp_path: Path) -> None:
    target = tmp_path / "sub" / "plan.3dm"
    with output.atomic_file(target) as tmp:
        assert tmp.parent == target.parent and tmp.exists() and not target.exists()
        tmp.write_text("first")
    umask = os.umask(0o022)
    os.umask(umask)
    assert target.read_text() == "first" and target.stat().st_mode & 0o777 == 0o666 & ~umask
    with pytest.raises(RuntimeError), output.atomic_file(target) as tmp:
        tmp.write_text("half")
        raise RuntimeError("writer failed")
    assert target.read_text() == "first" and os.listdir(target.parent) == ["plan.3dm"]
    link = tmp_path / "link.3dm"
    link.symlink_to(target)
    with output.atomic_file(link) as tmp:
        tmp.write_text("through the link")
    assert link.is_symlink() and target.read_text() == "through the link"
    with pytest.raises(InputError, match="is a folder"), output.atomic_file(tmp_path):
        pass
