"""The README's commands are run, so the docs cannot drift from the code.

So are those of the docs in ``RUN_DOCS``. Every ``console`` block holds
``$ fabflow ...`` commands followed by the output they print; ``...`` in the
expected output matches anything (including nothing). Outputs the README
writes under ``out/`` go to a temporary folder.
"""

from __future__ import annotations

import doctest
import re
import shlex

import pytest
from helpers import ROOT

README = (ROOT / "README.md").read_text(encoding="utf-8")
RUN_DOCS = ("docs/integrity.md",)
"""Docs whose ``console`` blocks run as well (the others show outputs of files
that are not in the repository)."""


def console_examples(text: str) -> list[tuple[str, str]]:
    """(command, expected output) pairs from the console blocks of ``text``."""
    examples = []
    for block in re.findall(r"```console\n(.*?)```", text, flags=re.S):
        command, expected = None, []
        for line in block.splitlines():
            if line.startswith("$ "):
                if command:
                    examples.append((command, "\n".join(expected)))
                command, expected = line[2:], []
            else:
                expected.append(line)
        if command:
            examples.append((command, "\n".join(expected)))
    return examples


def matches(expected: str, actual: str) -> bool:
    """Whether ``actual`` contains ``expected``, with ``...`` as a wildcard."""
    parts = [re.escape(p) for p in expected.strip().split("...")]
    return re.search(".*?".join(parts), actual, flags=re.S) is not None


EXAMPLES = console_examples(README)
DOC_EXAMPLES = [
    e for doc in RUN_DOCS for e in console_examples((ROOT / doc).read_text(encoding="utf-8"))
]


def test_readme_has_examples() -> None:
    assert len(EXAMPLES) >= 4 and DOC_EXAMPLES
    assert all(cmd.startswith("fabflow ") for cmd, _ in EXAMPLES + DOC_EXAMPLES)


@pytest.mark.parametrize(
    ("command", "expected"),
    EXAMPLES + DOC_EXAMPLES,
    ids=[c for c, _ in EXAMPLES + DOC_EXAMPLES],
)
def test_readme_example(cli, tmp_path, command: str, expected: str) -> None:
    args = [
        a.replace("out/", f"{tmp_path}/", 1) if a.startswith("out/") else a
        for a in shlex.split(command)[1:]
    ]
    result = cli(*args)
    output = result.stdout + result.stderr
    is_error = any(line.startswith("error:") for line in expected.splitlines())
    assert result.returncode == (2 if is_error else 0), output
    assert matches(expected, output), f"expected:\n{expected}\n\ngot:\n{output}"


def test_quickstart_has_exactly_two_commands() -> None:
    section = README.split("## Quickstart", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```bash\n(.*?)```", section, flags=re.S)
    commands = [line for b in blocks for line in b.splitlines() if line.strip()]
    assert len(commands) == 2
    assert "fabflow build projects/cabin" in commands[0]
    assert commands[1] == "bash scripts/test"


def test_project_reference_lists_every_top_level_field() -> None:
    from fabflow.project import Project

    section = README.split("## Project file", 1)[1].split("\n## ", 1)[0]
    for field in Project.model_fields:
        if field != "path":
            assert f"| `{field}` |" in section, field


def test_python_api_examples(monkeypatch: pytest.MonkeyPatch) -> None:
    """The README's ``pycon`` blocks run as doctests, from the repository root."""
    blocks = re.findall(r"```pycon\n(.*?)```", README, flags=re.S)
    assert blocks
    monkeypatch.chdir(ROOT)
    parser = doctest.DocTestParser()
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS)
    for i, block in enumerate(blocks):
        test = parser.get_doctest(block, {}, f"README pycon block {i + 1}", "README.md", 0)
        runner.run(test)
    result = runner.summarize(verbose=False)
    assert result.attempted > 0 and result.failed == 0
