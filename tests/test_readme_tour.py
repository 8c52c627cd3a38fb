"""The README's links and commands: every file it names exists, it opens with the two
commands, every verb teaches with ``--help``. Its shell blocks (the instrument tour on
``afmctl sim``, the offline tour, the real-data one) run as written in
tests/test_doc_blocks.py, which also checks the figures they print against the README's."""
from __future__ import annotations

from pathlib import Path

import pytest

from afmctl.cli import main

ROOT = Path(__file__).resolve().parent.parent


def test_readme_mentions_only_existing_files():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    import re
    for rel in re.findall(r"\((docs/[^)\s]+)\)", text) + re.findall(r"(examples/[\w.]+)", text):
        assert (ROOT / rel).exists(), rel
    lines = [ln for ln in text.splitlines() if ln.strip()]
    assert lines[1] == "```sh" and lines[2].startswith("make demo") and lines[3].startswith("make test")


@pytest.mark.parametrize("verb", ["demo", "run", "sim", "identify", "compensate", "model", "drift",
                                  "amp", "log", "report", "schema", "calibrate", "learn"])
def test_every_verb_has_help(verb, capsys):
    with pytest.raises(SystemExit) as exc:
        main([verb, "--help"])
    assert exc.value.code == 0
    assert len(capsys.readouterr().out) > 200
