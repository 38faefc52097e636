"""The ``fabflow`` command line: a thin layer over the library.

Errors caused by the user's input are printed as one message and exit with
code 2; nothing is left half-written. Each command imports the library it needs
when it runs, so that ``fabflow --help`` and a mistyped command answer at once
(this module and ``fabflow/__init__.py`` are the only ones allowed to).
"""

from __future__ import annotations

import functools
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, TypeVar

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from fabflow.errors import FabflowError, LocalizationError
from fabflow.version import __version__

if TYPE_CHECKING:
    from fabflow.positioning.result import BasePose
    from fabflow.project import Project

app = typer.Typer(
    name="fabflow",  # its help is main()'s docstring
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
    rich_markup_mode=None,  # plain help: the boxed one imports markdown_it (0.3 s a --help)
    context_settings={"max_content_width": 120},
)
localize_app = typer.Typer(
    help="Localize the robot base from measurements; writes the base pose JSON.",
    no_args_is_help=True,
    rich_markup_mode=None,
)
app.add_typer(localize_app, name="localize")
console = Console()
err_console = Console(stderr=True)

F = TypeVar("F", bound=Callable[..., Any])


def user_errors(func: F) -> F:
    """Turn a :class:`FabflowError` into one message on stderr and exit code 2."""

    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return func(*args, **kwargs)
        except FabflowError as exc:
            err_console.print(
                f"[bold red]error:[/] {escape(str(exc))}", highlight=False, soft_wrap=True
            )
            raise typer.Exit(code=exc.exit_code) from None

    return wrapper  # type: ignore[return-value]


ProjectArg = Annotated[
    Path, typer.Argument(help="A project YAML file, or a folder holding project.yaml.")
]
OutOption = Annotated[
    Path, typer.Option("--out", "-o", help="Output folder (replaced atomically).")
]
AlertLimitOption = Annotated[
    float | None,
    typer.Option(
        "--alert-limit",
        help="Largest protection level (m) a pose may have when it passed its tests only by "
        "leaving observations out; default: the project's tolerances.position (0.01).",
    ),
]


def _version(value: bool) -> None:
    if value:
        console.print(f"fabflow {__version__}")
        raise typer.Exit()


@app.callback()
def main(
    version: Annotated[
        bool, typer.Option("--version", callback=_version, is_eager=True, help="Show the version.")
    ] = False,
) -> None:
    """From an architectural design to a mobile construction robot."""


@app.command()
@user_errors
def validate(project: ProjectArg) -> None:
    """Check a project file and report every problem with its field path and line."""
    from fabflow.project import load_project

    p = load_project(project)
    console.print(f"[green]ok[/] {p.path}: project '{p.name}' is valid")


@app.command()
def schema(
    elements: Annotated[
        bool,
        typer.Option(
            "--elements", help="The schema of an elements file (elements: - file:) instead."
        ),
    ] = False,
) -> None:
    """Print the JSON Schema of the project file (or of an elements file)."""
    from fabflow.design.element_records import elements_file_schema
    from fabflow.json_format import json_text
    from fabflow.project import project_json_schema

    sys.stdout.write(json_text(elements_file_schema() if elements else project_json_schema()))


def print_summary(rows: list[tuple[str, str, str]], title: str) -> None:
    """Print ``(stage, item, value)`` rows as a table."""
    table = Table(title=title, show_lines=False)
    table.add_column("stage", style="cyan")
    table.add_column("item")
    table.add_column("value", justify="right")
    for stage, item, value in rows:
        table.add_row(stage, item, value)
    console.print(table)


def run_stages(project: Project, out: Path, command: str, until: str | None = None) -> None:
    """Run the build stages (up to ``until``) with a status line, then print the summary."""
    from fabflow.build.runner import run_build

    with console.status(command) as status:
        ctx = run_build(
            project, out, on_stage=lambda name: status.update(f"stage: {name}"), until=until
        )
    print_summary(ctx.summary, title=f"fabflow {command}: {project.name}")
    console.print(f"[green]wrote[/] {Path(out).resolve()}")


@app.command()
@user_errors
def build(
    project: ProjectArg,
    out: OutOption,
) -> None:
    """Run every stage on a project and write the results under OUT."""
    from fabflow.project import load_project

    run_stages(load_project(project), out, "build")


@app.command()
@user_errors
def plan(
    project: ProjectArg,
    out: OutOption,
) -> None:
    """Slice a project into per-station work packages: OUT/plan.json and OUT/site_plan.dxf."""
    from fabflow.build.plan import plan_rows, write_plan_outputs
    from fabflow.design.generate import generate_elements
    from fabflow.localize.layout import site_layout
    from fabflow.output import atomic_output_dir
    from fabflow.project import load_project
    from fabflow.tasks.planner import make_plan
    from fabflow.tasks.split import with_pieces

    p = load_project(project).without_stone_wall("plan")
    with console.status("planning"), atomic_output_dir(out) as staging:
        elements = generate_elements(p.elements, p.path, p.limits)
        result = make_plan(p, elements)
        layout = site_layout(p, result, with_pieces(elements, result.split_elements))
        write_plan_outputs(staging, p, elements, result, layout)
    rows = plan_rows(result) + layout.rows(result)
    print_summary([("plan", i, v) for i, v in rows], title=f"fabflow plan: {p.name}")
    console.print(f"[green]wrote[/] {Path(out).resolve() / 'plan.json'}")


@app.command()
@user_errors
def program(
    project: ProjectArg,
    out: OutOption,
    fmt: Annotated[
        str | None,
        typer.Option(
            "--format",
            "-f",
            help="krl, rapid, urscript, json or gcode (default: the project's format).",
        ),
    ] = None,
) -> None:
    """Write one robot program per work package under OUT/programs (plans and localizes first)."""
    from fabflow.programs.writers import writer_for
    from fabflow.project import load_project

    p = load_project(project)
    if fmt is not None:
        writer_for(fmt, p.robot.name)
        p = p.with_program_format(fmt)
    run_stages(p, out, "program", until="program")


def report_base_pose(
    pose: BasePose, out: Path, method: str, rows: list[tuple[str, str]], alert_limit: float
) -> None:
    """Write ``OUT/base_pose.json`` atomically and print the pose with its uncertainty.

    A pose that passed its tests only by leaving observations out fails when its
    protection level exceeds ``alert_limit``
    (:func:`~fabflow.positioning.integrity.guard_exclusion`); a failed or
    untested pose is written (with its tests) and the command exits with 2.

    Parameters
    ----------
    pose
        The localization result.
    out
        Output folder.
    method
        Name shown in the summary (``uwb``, ``total-station``, ``icp``).
    rows
        Method-specific ``(item, value)`` rows shown first.
    alert_limit
        Largest acceptable protection level (metres).
    """
    from fabflow.localize.report import guarded, pose_rows
    from fabflow.output import atomic_output_dir

    pose = guarded(pose, alert_limit)
    with atomic_output_dir(out) as staging:
        pose.write(staging / "base_pose.json")
    rows = [*rows, *pose_rows(pose)]
    print_summary([(method, i, v) for i, v in rows], title=f"fabflow localize {method}")
    written = (Path(out) / "base_pose.json").resolve()
    console.print(f"[green]wrote[/] {written}")
    if pose.integrity is None or pose.integrity.failed:
        reason = "untested" if pose.integrity is None else pose.integrity.reason
        raise LocalizationError(
            f"integrity failed: {reason}; do not build from this pose (its tests are in {written})"
        )


@localize_app.command("total-station")
@user_errors
def localize_total_station(
    observations: Annotated[
        Path, typer.Argument(help="Observations: CSV (hz_gon,v_gon,...) or Leica GSI-8/16.")
    ],
    robot_points: Annotated[
        Path,
        typer.Option("--robot-points", help="CSV point_id,x_m,y_m,z_m: prisms in the base frame."),
    ],
    out: OutOption,
    project: Annotated[
        Path | None, typer.Option("--project", help="Take instrument and pose from a project.")
    ] = None,
    instrument: Annotated[
        str | None, typer.Option(help="leica_ms50, hilti_pos150 or custom.")
    ] = None,
    distance_sigma_mm: Annotated[float | None, typer.Option(help="Distance sigma (mm).")] = None,
    distance_ppm: Annotated[float | None, typer.Option(help="Distance ppm part.")] = None,
    angle_sigma_arcsec: Annotated[float | None, typer.Option(help='Angle sigma (").')] = None,
    prism_centring_mm: Annotated[float | None, typer.Option(help="Prism centring (mm).")] = None,
    atmosphere_ppm: Annotated[float | None, typer.Option(help="Atmosphere scale (ppm).")] = None,
    instrument_xyz: Annotated[
        str | None, typer.Option(help="Instrument position 'x,y,z' in the world (m).")
    ] = None,
    instrument_abc_deg: Annotated[
        str | None, typer.Option(help="Instrument orientation 'A,B,C' (deg, Rz Ry Rx).")
    ] = None,
    instrument_height: Annotated[
        float | None, typer.Option(help="Trunnion height above the given pose (m).")
    ] = None,
    robot_sigma: Annotated[float, typer.Option(help="Robot positioning sigma (m).")] = 0.0,
    optimize: Annotated[
        bool, typer.Option("--optimize", help="Solve eqs 7-8 with SLSQP, not closed form.")
    ] = False,
    keep_outliers: Annotated[
        bool, typer.Option("--keep-outliers", help="Do not drop a flagged bad prism reading.")
    ] = False,
    robot: Annotated[
        str | None, typer.Option(help="Robot model for robot points given as joint values.")
    ] = None,
    tcp_xyz: Annotated[
        str | None, typer.Option(help="Prism position 'x,y,z' in the flange frame (m).")
    ] = None,
    station: Annotated[str | None, typer.Option(help="Station id stored in the result.")] = None,
    alert_limit: AlertLimitOption = None,
) -> None:
    """Localize the robot base from total station readings of prisms on the robot."""

    from fabflow.localize.report import alert_limit_for, check_options, optional_numbers
    from fabflow.localize.total_station import localize_files
    from fabflow.project import load_project

    numbers = {
        "distance_sigma_mm": distance_sigma_mm,
        "distance_ppm": distance_ppm,
        "angle_sigma_arcsec": angle_sigma_arcsec,
        "prism_centring_mm": prism_centring_mm,
        "atmosphere_ppm": atmosphere_ppm,
        "instrument_xyz": optional_numbers(
            instrument_xyz, "--instrument-xyz", "x,y,z", " (metres, world frame)"
        ),
        "instrument_abc_deg": optional_numbers(
            instrument_abc_deg, "--instrument-abc-deg", "A,B,C", " (degrees, Rz Ry Rx)"
        ),
        "instrument_height": instrument_height,
        "robot_sigma": robot_sigma,
        "tcp_xyz": optional_numbers(tcp_xyz, "--tcp-xyz", "x,y,z", " (metres, flange frame)"),
    }
    check_options(numbers, cli=True)
    loaded = None if project is None else load_project(project)
    limit = alert_limit_for(alert_limit, loaded)
    pose = localize_files(
        observations,
        robot_points,
        project=loaded,
        instrument=instrument,
        method="optimize" if optimize else "closed_form",
        reject_outlier=not keep_outliers,
        station=station,
        robot=robot,
        **numbers,  # type: ignore[arg-type]
    )
    q = pose.quality
    rows = [("points used", f"{q['n_inliers']} of {q['n_points']}")]
    test = q.get("outlier_test")
    if test is not None and test["flagged"]:
        bad = q["point_ids"][test["index"]]
        rows.append(("bad reading", f"{bad} (p = {test['p_value']:.2g})"))
    report_base_pose(pose, out, "total-station", rows, limit)


@localize_app.command("uwb")
@user_errors
def localize_uwb(
    ranges: Annotated[Path, typer.Argument(help="CSV t,anchor,range[,tag]: one range per line.")],
    anchors: Annotated[
        Path,
        typer.Option("--anchors", help="YAML: the localization.uwb section (+ T_platform_base)."),
    ],
    out: OutOption,
    imu: Annotated[
        Path | None, typer.Option("--imu", help="CSV t,ax,ay,az,gx,gy,gz: fuse with the ESKF.")
    ] = None,
    alert_limit: AlertLimitOption = None,
) -> None:
    """Localize the robot base from UWB ranges (and an IMU); writes OUT/base_pose.json."""

    from fabflow.localize.report import alert_limit_for
    from fabflow.localize.uwb_files import localize_from_files

    limit = alert_limit_for(alert_limit, None)
    pose = localize_from_files(ranges, anchors, imu)
    q = pose.quality
    rows = [("estimator", str(q["estimator"])), ("ranges", str(q["n_ranges"]))]
    if q.get("unobserved"):
        rows.append(("not observed", ", ".join(q["unobserved"])))
    report_base_pose(pose, out, "uwb", rows, limit)


@localize_app.command("icp")
@user_errors
def localize_icp(
    scan: Annotated[Path, typer.Argument(help="A LiDAR scan in the sensor frame (PLY/XYZ/CSV).")],
    map_file: Annotated[
        Path, typer.Option("--map", help="The site map in the world frame (PLY/XYZ/CSV).")
    ],
    init: Annotated[
        str, typer.Option("--init", help="Planned platform pose 'x,y,yaw' (m, m, deg).")
    ],
    out: OutOption,
    project: Annotated[
        Path | None,
        typer.Option("--project", help="Take LiDAR mounting and thresholds from a project."),
    ] = None,
    lift: Annotated[float, typer.Option(help="Lift height of the arm base (m).")] = 0.0,
    station: Annotated[str | None, typer.Option(help="Station id stored in the result.")] = None,
    alert_limit: AlertLimitOption = None,
) -> None:
    """Localize the robot base by ICP of a LiDAR scan against a map; writes OUT/base_pose.json."""

    from fabflow.localize.icp import localize_files
    from fabflow.localize.report import alert_limit_for, check_options, parse_numbers
    from fabflow.project import load_project

    start = parse_numbers(init, "--init", "x,y,yaw", " (metres, metres, degrees)")
    check_options({"init": start, "lift": lift}, cli=True)
    loaded = None if project is None else load_project(project)
    limit = alert_limit_for(alert_limit, loaded)
    pose = localize_files(scan, map_file, start, project=loaded, lift=lift, station=station)
    q = pose.quality
    rows = [
        ("scan points", f"{q['n_points']} used of {q['n_scan_points']}"),
        ("fitness", f"{q['fitness']:.3f} (structure {q['structure_fitness']:.3f})"),
    ]
    report_base_pose(pose, out, "icp", rows, limit)


@app.command()
@user_errors
def preview(
    project: ProjectArg,
    port: Annotated[
        int, typer.Option(help="Port of the live preview (next free one if busy).")
    ] = 8080,
    host: Annotated[str, typer.Option(help="Interface to listen on.")] = "127.0.0.1",
    export: Annotated[
        Path | None,
        typer.Option(help="Write one self-contained HTML file that plays offline, then exit."),
    ] = None,
    colour_by: Annotated[
        str | None,
        typer.Option(
            "--colour-by",
            help="station, state, layer or deviation (default: station; state in an export).",
        ),
    ] = None,
    sim: Annotated[
        Path | None,
        typer.Option(
            help="fabflow simulate output (deviations, localization) or build output folder."
        ),
    ] = None,
) -> None:
    """Show the construction sequence in the browser (viser), or export it as one HTML file."""
    from fabflow.preview.command import run_preview

    run_preview(
        project,
        port=port,
        host=host,
        export=export,
        colour_by=colour_by,
        sim=sim,
        say=lambda text: console.print(escape(text), highlight=False),
    )


@app.command()
@user_errors
def simulate(
    project: ProjectArg,
    out: OutOption,
    runs: Annotated[
        int | None,
        typer.Option("--runs", "-n", min=1, help="Runs per method (default: simulation.runs)."),
    ] = None,
    methods: Annotated[
        str | None,
        typer.Option(help="Comma-separated methods to compare: uwb,total_station,icp."),
    ] = None,
    seed: Annotated[int | None, typer.Option(help="Study seed (default: simulation.seed).")] = None,
    scheduler: Annotated[
        str | None,
        typer.Option(help="Address of a running Dask scheduler (default: a local cluster)."),
    ] = None,
    scheduler_file: Annotated[
        Path | None,
        typer.Option(
            help="Connect through the file 'dask scheduler --scheduler-file' wrote "
            "(instead of --scheduler); its workers need the same fabflow version."
        ),
    ] = None,
    workers: Annotated[
        int,
        typer.Option(min=0, help="Worker processes of the local cluster; 0 runs in-process."),
    ] = 2,
    timeout: Annotated[
        float,
        typer.Option(help="Seconds to wait for the scheduler to answer and for its first worker."),
    ] = 30.0,
    dashboard: Annotated[
        bool, typer.Option(help="Serve the local cluster's Dask dashboard on 127.0.0.1.")
    ] = False,
    plots: Annotated[bool, typer.Option(help="Write the PNG plots.")] = True,
    fidelity: Annotated[
        str,
        typer.Option(
            help="sensors (simulate every visit's sensors) or covariance (fast Gaussian "
            "surrogate calibrated per visit).",
        ),
    ] = "sensors",
    stationing: Annotated[
        str | None,
        typer.Option(
            help="Total station set-ups registered on control_points (Procedure B), "
            "robot_points (Procedure A), or both, comma-separated: one study each "
            "(default: the project's).",
        ),
    ] = None,
) -> None:
    """Monte Carlo tolerance study: N simulated construction runs per localization method."""
    from fabflow.sim.command import run_simulate

    run_simulate(
        project, out, runs, methods, seed, scheduler, workers, timeout, dashboard, plots,
        fidelity, stationing, console, scheduler_file=scheduler_file,
    )  # fmt: skip


@app.command("export")
@user_errors
def export_command(
    build_dir: Annotated[Path, typer.Argument(help="A fabflow build output folder.")],
    to: Annotated[
        Path,
        typer.Option(
            "--to",
            "-o",
            help="The file to write: .3dm (Rhino) or .json (COMPAS JSON); replaced atomically.",
        ),
    ],
    asbuilt: Annotated[
        Path | None,
        typer.Option(
            help="A fabflow simulate output folder (or its asbuilt_run0.csv): "
            "export the simulated as-built poses of run 0 too."
        ),
    ] = None,
) -> None:
    """Export a build's elements, stations and site layout to Rhino (.3dm) or COMPAS (.json)."""
    from fabflow.build.export import export_build

    result = export_build(build_dir, to, asbuilt)
    console.print(f"[green]wrote[/] {escape(str(result.path.resolve()))}", highlight=False)
    console.print(escape(result.line()), highlight=False)


@app.command()
@user_errors
def track(
    project: ProjectArg,
    out: OutOption,
    seed: Annotated[
        int | None, typer.Option(min=0, help="Seed (default: simulation.seed).")
    ] = None,
) -> None:
    """Print a path on the simulated hydraulic excavator, closed and open loop (paper 000)."""
    from fabflow.tracking.command import run_track

    run_track(project, out, seed, console)


@app.command()
@user_errors
def stream(
    program: Annotated[Path, typer.Argument(help="A JSON command stream (fabflow program).")],
    to: Annotated[str, typer.Option("--to", help="The gateway's HOST:PORT.")],
    profile: Annotated[
        str | None, typer.Option(help="hydraulic or rsi (default: the program's robot's).")
    ] = None,
    cycle: Annotated[float | None, typer.Option(help="Cycle (s); RSI: 0.004 or 0.012.")] = None,
    watchdog: Annotated[float | None, typer.Option(help="Feedback watchdog (s).")] = None,
    bound: Annotated[float | None, typer.Option(help="Tracking error bound (rad).")] = None,
    log: Annotated[
        Path | None, typer.Option(help="Packet log CSV (default: PROGRAM.stream.csv beside it).")
    ] = None,
) -> None:
    """Stream a program to a machine gateway over UDP; exit 0 only if it completed."""
    from fabflow.link.command import run_stream

    code = run_stream(program, to, profile, cycle, watchdog, bound, log, console)
    raise typer.Exit(code)


@app.command("machine-sim")
@user_errors
def machine_sim(
    port: Annotated[int, typer.Option(min=0, max=65535, help="UDP port (0: any free).")],
    host: Annotated[str, typer.Option(help="Address to listen on.")] = "127.0.0.1",
    robot: Annotated[str, typer.Option(help="Catalogue robot.")] = "kuka_kr60_3",
    profile: Annotated[str | None, typer.Option(help="hydraulic or rsi.")] = None,
    cycle: Annotated[float | None, typer.Option(help="Cycle (s).")] = None,
    watchdog: Annotated[float | None, typer.Option(help="Watchdog (s).")] = None,
    loss: Annotated[float, typer.Option(help="Fraction of datagrams lost.")] = 0.0,
    delay: Annotated[float, typer.Option(help="One-way delay (s).")] = 0.0,
    jitter: Annotated[float, typer.Option(help="Extra delay up to this (s).")] = 0.0,
    reorder: Annotated[float, typer.Option(help="Fraction of datagrams reordered.")] = 0.0,
    seed: Annotated[int, typer.Option(help="Seed of the network faults.")] = 0,
    log: Annotated[Path | None, typer.Option(help="Packet log CSV.")] = None,
) -> None:
    """A simulated machine gateway for 'fabflow stream' (hydraulic machine or RSI servo)."""
    from fabflow.link.command import run_machine_sim
    from fabflow.link.gateway import Impairments

    faults = Impairments(loss=loss, delay=delay, jitter=jitter, reorder=reorder)
    args = (port, host, robot, profile, cycle, watchdog, faults, seed, log, console)
    raise typer.Exit(run_machine_sim(*args))


if __name__ == "__main__":  # pragma: no cover
    app()
