"""Run the command line as ``python -m fabflow``."""

from fabflow.cli import app

app(prog_name="fabflow")
