"""The ``fabflow`` command line: a thin layer over the library.

Errors caused by the user's input are printed as one message and exit with
code 2; nothing is left half-written.
"""

from __future__ import annotations

import functools
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any, TypeVar

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from fabflow import __version__
from fabflow.errors import FabflowError

app = typer.Typer(
    name="fabflow",
    help="From an architectural design to a mobile construction robot.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)
localize_app = typer.Typer(
    help="Localize the robot base from measurements; writes the base pose JSON.",
    no_args_is_help=True,
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
def schema() -> None:
    """Print the JSON Schema of the project file."""
    from fabflow.project import project_json_schema

    sys.stdout.write(json.dumps(project_json_schema(), indent=2) + "\n")


def print_summary(rows: list[tuple[str, str, str]], title: str) -> None:
    """Print ``(stage, item, value)`` rows as a table."""
    table = Table(title=title, show_lines=False)
    table.add_column("stage", style="cyan")
    table.add_column("item")
    table.add_column("value", justify="right")
    for stage, item, value in rows:
        table.add_row(stage, item, value)
    console.print(table)


@app.command()
@user_errors
def build(
    project: ProjectArg,
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder (replaced atomically).")],
) -> None:
    """Run every stage on a project and write the results under OUT."""
    from fabflow.pipeline import run_build
    from fabflow.project import load_project

    p = load_project(project)
    with console.status("building") as status:
        ctx = run_build(p, out, on_stage=lambda name: status.update(f"stage: {name}"))
    print_summary(ctx.summary, title=f"fabflow build: {p.name}")
    console.print(f"[green]wrote[/] {Path(out).resolve()}")


if __name__ == "__main__":  # pragma: no cover
    app()
