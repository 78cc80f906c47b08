"""Every ``torchmm-run`` command in README.md, docs/*.md and the comments of conf/experiment/*.yaml (the files
users are told to copy) runs as written: composed, validated and its
scenario, estimators and learn entries built dry, as ``torchmm-run`` checks a command before it creates a
folder (experiments.config.precheck). Allowed: only what the reader must bring - a data file of their own
(the command names a path that is not shipped), a GPU, a Hydra launcher plugin the docs say to install, an
earlier run folder to resume."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest
import torch

from experiments.config import precheck
from experiments.run import CONFIG_DIR

ROOT = Path(__file__).resolve().parents[1]


def _commands() -> list[tuple[str, str]]:
    out = []
    for file in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        lines = file.read_text().splitlines()
        i = 0
        while i < len(lines):
            line = lines[i].strip()
            # a command (not an example of its output, "torchmm-run: error: ...")
            if re.match(r"^(\.venv/bin/)?torchmm-run(\s|$)", line):
                start = i
                while line.endswith("\\"):
                    i += 1
                    line = line[:-1] + " " + lines[i].strip()
                out.append((f"{file.relative_to(ROOT)}:{start + 1}", line))
            i += 1
    for file in sorted((ROOT / "conf" / "experiment").glob("*.yaml")):
        lines = file.read_text().splitlines()
        for i, line in enumerate(lines):
            if not line.lstrip().startswith("#"):
                continue
            text = line.lstrip()[1:].strip()
            # a command on its own comment line (continued by "\" on the next), or inline in `backticks`
            found = [text] if re.match(r"^torchmm-run(\s|$)", text) else re.findall(r"`(torchmm-run[^`]*)`", text)
            for command in found:
                j = i
                while command.endswith("\\") and j + 1 < len(lines) and lines[j + 1].lstrip().startswith("#"):
                    j += 1
                    command = command[:-1] + " " + lines[j].lstrip()[1:].strip()
                out.append((f"{file.relative_to(ROOT)}:{i + 1}", command))
    return out


COMMANDS = _commands()


def _allowed(message: str) -> bool:
    """A failure that only the reader's own setting can remove."""
    return (": no such file" in message and "experiments/data" not in message
            or "CUDA is not available" in message and not torch.cuda.is_available()
            or "hydra/launcher=ray: no such config" in message
            or "resume=" in message and "expected latest or an existing run folder" in message)


def test_the_docs_have_commands():
    assert len(COMMANDS) > 40


@pytest.mark.parametrize("where, command", COMMANDS, ids=[w for w, _ in COMMANDS])
def test_a_documented_command_passes_the_precheck(where, command, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)  # (relative data paths: the shipped data, or a file of the reader's)
    argv = shlex.split(command, comments=True)[1:]
    try:
        precheck(argv, CONFIG_DIR)
    except SystemExit:
        message = capsys.readouterr().err.strip()
        assert _allowed(message), f"{where}: {command}\n{message}"
