"""Total station files: GSI-8/GSI-16 and CSV readers, robot points, their bounds and messages."""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import pytest
from helpers import TS_DATA
from hypothesis import given, settings
from hypothesis import strategies as st

from fabflow.errors import InputError, LocalizationError, UnsupportedError
from fabflow.positioning.gsi import parse_gsi, read_gsi
from fabflow.positioning.polar import DEG, GON, INSTRUMENTS, MAX_READINGS
from fabflow.positioning.total_station import localize_observations
from fabflow.positioning.ts_io import read_observations, read_robot_points
from fabflow.transforms.se3 import make_T, pose_error
from fabflow.transforms.so3 import exp_so3

T_TRUE = make_T(exp_so3([0.0, 0.0, np.radians(30.0)]), [6.0, 4.0, 0.5])


def test_gsi8_sample() -> None:
    obs = read_gsi(TS_DATA / "obs_gsi8.gsi")
    assert obs.point_ids == ("P1", "P2", "P3", "P4", "P5")
    assert obs.lines == (2, 3, 4, 5, 6)
    assert obs.hz[0] == pytest.approx(59.38845 * GON, abs=1e-12)
    assert obs.v[1] == pytest.approx(84.92614 * GON, abs=1e-12)
    assert obs.sd[4] == pytest.approx(8.218)
    assert np.all(obs.prism_height == 0.0) and np.all(np.isnan(obs.xyz))
    assert obs.station_xyz is None


def test_gsi16_sample_with_station_block() -> None:
    obs = read_observations(TS_DATA / "obs_gsi16.gsi")
    assert obs.point_ids == ("P1", "P2", "P3", "P4", "P5")
    assert obs.hz[0] == pytest.approx(53.44961 * DEG, abs=1e-12)
    assert obs.sd[0] == pytest.approx(8.5665)
    np.testing.assert_array_equal(obs.station_xyz, [0.0, 0.0, 0.0])
    assert obs.instrument_height == 0.0
    g8 = read_gsi(TS_DATA / "obs_gsi8.gsi")
    np.testing.assert_allclose(obs.hz, g8.hz, atol=2e-7)


def test_gsi_units_and_words() -> None:
    text = (
        "110001+0000000A 21.104+12330150 22.104+09000000 31..01+00010000 87..10+00000150\n"
        "*110002+000000000000000B 81..06+0000000000012345 82..06-0000000000005000 "
        "83..06+0000000000001000 \n"
        "410003+00000007 42....+00000001\n"
    )
    obs = parse_gsi(text, "x.gsi")
    assert obs.point_ids == ("A", "B")
    assert obs.hz[0] == pytest.approx((123 + 30 / 60 + 15.0 / 3600) * DEG)
    assert obs.v[0] == pytest.approx(np.pi / 2)
    assert obs.sd[0] == pytest.approx(10.0 * 0.3048)  # feet, unit 1
    assert obs.prism_height[0] == pytest.approx(0.150)
    np.testing.assert_allclose(obs.xyz[1], [1.2345, -0.5, 0.1])
    assert np.isnan(obs.hz[1])


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("110001+0000000A 21.102+1234567 22.102+10000000 31..00+00001000\n", "line 1: word"),
        ("\n110001+0000000A 21.109+12345678 22.102+10000000 31..00+00001000\n", "line 2: unknown"),
        ("110001+0000000A 21.102+12345678 22.102+10000000\n", r"lacks word\(s\) 31"),
        ("21.102+12345678 22.102+10000000 31..00+00001000\n", "no point id"),
        ("110001+0000000A 21.102+1234A678 22.102+10000000 31..00+00001000\n", "not a number"),
        ("110001+0000000A 21.102*12345678 22.102+10000000 31..00+00001000\n", "no sign"),
        ("410001+00000001\n", "no observations"),
        ("110001+0000000A 81..00+00001000 82..00+00001000\n", "81, 82, 83"),
    ],
)
def test_gsi_errors_name_the_line(text: str, message: str) -> None:
    with pytest.raises(InputError, match=message) as info:
        parse_gsi(text, "bad.gsi")
    assert "bad.gsi" in str(info.value)


def test_gsi_mil_is_unsupported() -> None:
    with pytest.raises(UnsupportedError, match="line 1: angles in mil"):
        parse_gsi("110001+0000000A 21.105+12345678 22.102+10000000 31..00+00001000\n", "m.gsi")


def test_csv_sample_and_robot_points() -> None:
    obs = read_observations(TS_DATA / "obs.csv")
    assert obs.point_ids == ("P1", "P2", "P3", "P4", "P5")
    assert obs.lines[0] == 3  # after the comment and the header
    assert obs.hz[2] == pytest.approx(51.72527 * GON)
    rp = read_robot_points(TS_DATA / "robot_points.csv")
    assert rp.point_ids[-1] == "P9" and rp.xyz is not None and rp.xyz.shape == (6, 3)
    assert rp.joints is None and rp.lines[0] == 2
    np.testing.assert_allclose(rp.xyz[1], [1.5, -0.8, 1.6])


@pytest.mark.parametrize("name", ["obs_gsi8.gsi", "obs_gsi16.gsi", "obs.csv"])
def test_samples_localize_the_known_pose(name: str) -> None:
    obs = read_observations(TS_DATA / name)
    rp = read_robot_points(TS_DATA / "robot_points.csv")
    assert rp.xyz is not None
    reg, matched = localize_observations(obs, rp.point_ids, rp.xyz, INSTRUMENTS["leica_ms50"])
    assert matched == ("P1", "P2", "P3", "P4", "P5")
    err = pose_error(reg.T_world_base, T_TRUE)
    assert np.linalg.norm(err[:3]) < 1e-3  # readings rounded to 1 mm / 0.1 mm
    assert np.linalg.norm(err[3:]) < 2e-4
    assert reg.rejected == ()


def test_csv_errors(tmp_path: Path) -> None:
    cases = {
        "point_id,hz_gon,v_gon\nP1,1,2\n": "expected columns",
        "point_id,hz_gon,v_gon,slope_distance_m\nP1,1,2\n": "line 2: expected 4 values",
        "point_id,hz_gon,v_gon,slope_distance_m\nP1,1,abc,3\n": "line 2: column 'v_gon'",
        "point_id,hz_gon,v_gon,slope_distance_m\nP1,1,2,-3\n": "line 2: .*not between 0.2",
        "point_id,hz_gon,v_gon,slope_distance_m\n": "no data rows",
        "": "empty",
    }
    for k, (text, message) in enumerate(cases.items()):
        f = tmp_path / f"o{k}.csv"
        f.write_text(text)
        with pytest.raises(InputError, match=message):
            read_observations(f)
    f = tmp_path / "pts.csv"
    f.write_text("point_id,x_m,y_m,z_m\nA,1,2,3\nA,1,2,4\n")
    with pytest.raises(InputError, match="line 3: point id 'A' appears twice"):
        read_robot_points(f)
    with pytest.raises(InputError, match="does not exist"):
        read_robot_points(tmp_path / "missing.csv")


def test_too_few_matching_ids(tmp_path: Path) -> None:
    obs = read_observations(TS_DATA / "obs.csv")
    with pytest.raises(LocalizationError, match="only 2 observed point id"):
        localize_observations(obs, ("P1", "P2", "X"), np.eye(3), INSTRUMENTS["leica_ms50"])


@settings(deadline=None, max_examples=40)
@given(
    hz=st.floats(0.0, 399.99999),
    v=st.floats(0.001, 199.999),
    sd=st.floats(0.5, 9999.0),
    gsi16=st.booleans(),
    pid=st.from_regex(r"[A-Z][A-Z0-9]{0,6}", fullmatch=True),
)
def test_gsi_round_trip(hz: float, v: float, sd: float, gsi16: bool, pid: str) -> None:
    width = 16 if gsi16 else 8
    hz_i, v_i, sd_i = round(hz * 1e5), round(v * 1e5), round(sd * (1e5 if gsi16 else 1e3))
    unit = "8" if gsi16 else "0"  # 0.01 mm in GSI-16, 1 mm in GSI-8

    def word(wi: str, info: str, data: str) -> str:
        return f"{wi}{info}+{data.rjust(width, '0')}"

    line = " ".join(
        [
            word("11", "0001", pid),
            word("21", ".102", str(hz_i)),
            word("22", ".102", str(v_i)),
            word("31", f"..0{unit}", str(sd_i)),
        ]
    )
    obs = parse_gsi(("*" if gsi16 else "") + line + " \n")
    assert obs.point_ids == (pid,)
    assert obs.hz[0] == pytest.approx(hz_i * 1e-5 * GON, abs=1e-12)
    assert obs.v[0] == pytest.approx(v_i * 1e-5 * GON, abs=1e-12)
    assert obs.sd[0] == pytest.approx(sd_i * (1e-5 if gsi16 else 1e-3), rel=1e-12)


HEADER = "point_id,hz_gon,v_gon,slope_distance_m\n"


@pytest.mark.parametrize("reader", [read_observations, read_robot_points])
def test_encoding_and_long_fields_name_the_line(tmp_path: Path, reader) -> None:
    head = HEADER if reader is read_observations else "point_id,x_m,y_m,z_m\n"
    f = tmp_path / "f.csv"
    f.write_bytes(b"# comment\n" + head.encode() + b"P1,1,2,3\nP2,1,\xff,3\n")
    with pytest.raises(InputError, match="not UTF-8") as exc:
        reader(f)
    assert exc.value.location == "line 4" and exc.value.source == str(f)
    f.write_bytes(head.encode() + b"P1,1,2,3\nP2,1," + b"9" * 200_000 + b",3\n")
    with pytest.raises(InputError, match="longer than 131072") as exc:
        reader(f)
    assert exc.value.location == "line 3" and "9" * 50 not in str(exc.value)


@pytest.mark.parametrize("name", ["obs.csv", "obs.gsi"])
def test_devices_pipes_and_big_files_are_refused_at_once(tmp_path: Path, name: str) -> None:
    with pytest.raises(InputError, match="not a regular file"):
        read_observations(Path("/dev/zero").with_name("zero"))  # /dev/zero as it is
    fifo = tmp_path / name
    os.mkfifo(fifo)
    with pytest.raises(InputError, match="not a regular file"):
        read_observations(fifo)  # would block if opened
    big = tmp_path / f"big_{name}"
    big.write_bytes(HEADER.encode() + b"P1,52.33412,96.12005,6.2341\n" * 1_100_000)  # 30 MB
    start = time.perf_counter()
    with pytest.raises(InputError, match=r"MiB, more than the 2\.0 MiB"):
        read_observations(big)
    assert time.perf_counter() - start < 1.0


def test_rows_are_bounded_and_read_linearly(tmp_path: Path) -> None:
    rows = "".join(f"P{k},{k % 400}.5,97.5,{5 + k % 7}\n" for k in range(MAX_READINGS + 1))
    f = tmp_path / "obs.csv"
    f.write_text(HEADER + rows)
    with pytest.raises(InputError, match=f"more than {MAX_READINGS} data rows") as exc:
        read_observations(f)
    assert exc.value.location == f"line {MAX_READINGS + 2}"
    f.write_text(HEADER + rows[: rows.rindex("P")])
    start = time.perf_counter()
    assert len(read_observations(f)) == MAX_READINGS
    assert time.perf_counter() - start < 2.0
    gsi = tmp_path / "obs.gsi"
    gsi.write_text(
        "".join(
            f"11{k:04d}+{k:08d} 21.102+05938845 22.102+08954901 31..00+00008566\n"
            for k in range(MAX_READINGS + 1)
        )
    )
    with pytest.raises(InputError, match=f"more than {MAX_READINGS} observations") as exc:
        read_observations(gsi)
    assert exc.value.location == f"line {MAX_READINGS + 1}"


@pytest.mark.parametrize(
    ("row", "what"),
    [
        ("P2,100,0,5", "points straight up or down"),
        ("P2,100,200.05,5", "points straight up or down"),
        ("P2,100,95,0.1", "not between 0.2 and 10000 m"),
        ("P2,100,95,20000", "not between 0.2 and 10000 m"),
        ("P2,1e9,95,5", "beyond a full turn"),
        ("P2,100,95,5,250", "prism height 250 m"),
    ],
)
def test_readings_beyond_an_instrument_name_the_line(tmp_path: Path, row: str, what: str) -> None:
    f = tmp_path / "obs.csv"
    header = HEADER if row.count(",") == 3 else HEADER.strip() + ",prism_height_m\n"
    f.write_text(header + "P1,52.3,96.1,6.2" + ("" if row.count(",") == 3 else ",0") + "\n" + row)
    with pytest.raises(InputError, match=what) as exc:
        read_observations(f)
    assert exc.value.location == "line 3" and "point 'P2'" in str(exc.value)


def test_coordinate_rows_and_robot_points_are_bounded(tmp_path: Path) -> None:
    f = tmp_path / "obs.csv"
    f.write_text("point_id,x_m,y_m,z_m\nP1,1,2,3\nP2,1e9,2,3\n")
    with pytest.raises(InputError, match="beyond 1e\\+08 m") as exc:
        read_observations(f)
    assert exc.value.location == "line 3"
    f.write_text("point_id,x_m,y_m,z_m\nP1,1,2,3\nP2,1,2,300\n")
    with pytest.raises(InputError, match="more than 100 m from the robot base") as exc:
        read_robot_points(f)
    assert exc.value.location == "line 3"
    f.write_text("point_id,q1_deg,q2_deg\nP1,1,nan\n")
    with pytest.raises(InputError, match="'q2_deg': 'nan' is not finite"):
        read_robot_points(f)


@pytest.mark.parametrize(
    ("text", "what"),
    [
        ("*110001+000000000000STN1 84..10+9999999999999999\n", "station coordinate"),
        ("*110001+000000000000STN1 88..10+0000000001000000\n", "instrument height"),
        ("110001+0000000A 21.102+\xb2\xb3345678 22.102+10000000 31..00+00001000\n", "number"),
        ("110001+0000000A 21.102+" + "1" * 500 + "\n", "characters, expected 15"),
    ],
)
def test_gsi_bounds_and_short_quotes(tmp_path: Path, text: str, what: str) -> None:
    f = tmp_path / "x.gsi"
    f.write_bytes(text.encode("latin-1"))
    with pytest.raises(InputError, match=what) as exc:
        read_observations(f)
    assert exc.value.location == "line 1" and "1" * 100 not in str(exc.value)
