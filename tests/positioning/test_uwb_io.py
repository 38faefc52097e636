"""UWB range and IMU files: impossible or malformed input is an InputError naming file and line."""

from __future__ import annotations

import string
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fabflow.errors import InputError
from fabflow.positioning.eskf_input import (
    MAX_ANGULAR_RATE,
    MAX_IMU_GAP_S,
    MAX_SPECIFIC_FORCE,
    coverage_problem,
    imu_problem,
)
from fabflow.positioning.uwb_io import read_imu_csv, read_ranges_csv, write_imu_csv

IDS = ["A1", "A2", "A3", "A4"]
IMU_HEADER = "t,ax,ay,az,gx,gy,gz\n"


def _imu_text(rows: list[str]) -> str:
    return IMU_HEADER + "".join(r + "\n" for r in rows)


GOOD = ["0.00,0,0,9.81,0,0,0", "0.01,0,0,9.81,0,0,0", "0.02,0,0,9.81,0,0,0"]


@pytest.mark.parametrize(
    ("rows", "line", "what"),
    [
        ([*GOOD[:1], "0.01,1e308,0,9.81,0,0,0", *GOOD[2:]], "line 3", "specific force"),
        ([*GOOD[:2], "0.02,0,0,9.81,0,0,-150"], "line 4", "angular rate"),
        ([*GOOD[:1], "0.01,0,0,9.81,0,nan,0"], "line 3", "not finite"),
        ([*GOOD[:1], "0.01,0,0,inf,0,0,0"], "line 3", "not finite"),
        ([*GOOD[:2], "1000000000.02,0,0,9.81,0,0,0"], "line 4", "gap of 1e\\+09 s"),
        ([*GOOD[:1], "1.5,0,0,9.81,0,0,0"], "line 3", "gap of 1.5 s"),
    ],
)
def test_imu_values_beyond_an_imu_are_refused(
    tmp_path: Path, rows: list[str], line: str, what: str
) -> None:
    path = tmp_path / "imu.csv"
    path.write_text(_imu_text(rows))
    with pytest.raises(InputError, match=what) as exc:
        read_imu_csv(path)
    assert exc.value.source == str(path) and exc.value.location == line


def test_imu_at_the_bounds_is_read(tmp_path: Path) -> None:
    path = tmp_path / "imu.csv"
    a = 0.999 * MAX_SPECIFIC_FORCE
    w = 0.999 * MAX_ANGULAR_RATE
    dt = 0.999 * MAX_IMU_GAP_S
    path.write_text(_imu_text([f"0,{a},0,0,0,0,{w}", f"{dt},0,0,9.81,0,0,0"]))
    t, accel, gyro = read_imu_csv(path)
    assert t[1] == dt and accel[0, 0] == a and gyro[0, 2] == w


def test_imu_problem_and_coverage() -> None:
    t = np.arange(5) * 0.01
    a = np.tile([0.0, 0.0, 9.81], (5, 1))
    w = np.zeros((5, 3))
    assert imu_problem(t, a, w) is None
    a[3, 1] = np.nan
    w[2, 0] = 1e300
    k, msg = imu_problem(t, a, w)
    assert k == 2 and "angular rate" in msg  # the first sample wins, whatever the check
    assert coverage_problem(t, np.array([0.0, 0.04])) is None
    assert coverage_problem(t, np.array([-0.05, 0.1])) is None  # within the margin
    assert "does not cover" in coverage_problem(t, np.array([100.0, 101.0]))
    assert "does not cover" in coverage_problem(t, np.array([-3.0, 0.02]))


@pytest.mark.parametrize("reader", ["ranges", "imu"])
def test_non_utf8_and_oversized_fields(tmp_path: Path, reader: str) -> None:
    def read(path: Path) -> object:
        if reader == "ranges":
            return read_ranges_csv(path, IDS, n_tags=1)
        return read_imu_csv(path)

    header = b"t,anchor,range\n0.0,A1,3.0\n" if reader == "ranges" else IMU_HEADER.encode()
    path = tmp_path / f"{reader}.csv"
    path.write_bytes(header + b"0.1,A2,3.\xff1\n")
    with pytest.raises(InputError, match="not UTF-8") as exc:
        read(path)
    assert str(path) in str(exc.value)
    assert exc.value.location == ("line 3" if reader == "ranges" else "line 2")
    path.write_bytes(header + b"0.1,A2," + b"9" * 200_000 + b"\n")
    with pytest.raises(InputError, match="field is longer than") as exc:
        read(path)
    assert str(path) in str(exc.value)
    assert exc.value.location == ("line 3" if reader == "ranges" else "line 2")


def test_byte_order_mark_and_tag_digits(tmp_path: Path) -> None:
    path = tmp_path / "r.csv"
    path.write_bytes(b"\xef\xbb\xbft,tag,anchor,range\n0.0,1,A1,3.0\n")
    log = read_ranges_csv(path, IDS, n_tags=2)
    assert log.tag.tolist() == [1]
    for tag in ["\u00b2", "1" * 5000]:  # a superscript two is a digit to str.isdigit
        path.write_text(f"t,tag,anchor,range\n0.0,{tag},A1,3.0\n", encoding="utf-8")
        with pytest.raises(InputError, match="is not an index"):
            read_ranges_csv(path, IDS, n_tags=2)


def test_imu_round_trip(tmp_path: Path) -> None:
    t = np.arange(4) * 0.01
    a = np.array([[0.1, -0.2, 9.8]] * 4)
    w = np.array([[0.001, 0.0, -0.002]] * 4)
    t2, a2, w2 = read_imu_csv(write_imu_csv(tmp_path / "imu.csv", t, a, w))
    np.testing.assert_allclose(t2, t)
    np.testing.assert_allclose(a2, a)
    np.testing.assert_allclose(w2, w)


CSV_CHARS = string.digits + ".,-+eE\n\r\"' \tA1naif\x00\u00b2\u00e9"
junk_text = st.text(alphabet=CSV_CHARS, max_size=300)


def _check_junk(data: bytes) -> None:
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "x.csv"
        path.write_bytes(data)
        try:
            log = read_ranges_csv(path, IDS, n_tags=2)
        except InputError as exc:
            assert str(path) in str(exc)
        else:
            assert np.all(np.isfinite(log.t)) and np.all(log.range >= 0)
            assert np.all(np.diff(log.t) >= 0)
        try:
            t, a, w = read_imu_csv(path)
        except InputError as exc:
            assert str(path) in str(exc)
        else:
            assert imu_problem(t, a, w) is None and np.all(np.diff(t) > 0)


@settings(deadline=None, max_examples=150, suppress_health_check=[HealthCheck.too_slow])
@given(
    prefix=st.sampled_from(["", "t,anchor,range\n", "t,tag,anchor,range\n", IMU_HEADER]),
    body=junk_text,
    raw=st.binary(max_size=64),
)
def test_random_junk_raises_only_input_errors(prefix: str, body: str, raw: bytes) -> None:
    _check_junk(prefix.encode() + body.encode())
    _check_junk(prefix.encode() + raw + body.encode())
