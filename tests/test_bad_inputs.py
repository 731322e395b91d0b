"""The bad-input corpus (tests/bad_inputs/cases.yaml): every malformed scenario, command-line
value, DBC file and log gives exit status 2 and one message naming the file or option and the
field, no traceback, and writes nothing."""
from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from canbrake.cli import main

from conftest import ROOT

DIR = Path(__file__).resolve().parent / "bad_inputs"
CASES = yaml.safe_load((DIR / "cases.yaml").read_text())


def test_the_corpus_is_large_enough():
    assert len(CASES) >= 40
    assert len({c["name"] for c in CASES}) == len(CASES)


@pytest.mark.parametrize("case", CASES, ids=[c["name"] for c in CASES])
def test_bad_input(case, tmp_path, capsys):
    args = [a.format(dir=DIR, root=ROOT, tmp=tmp_path) for a in case["args"]]
    rc = main(args)
    cap = capsys.readouterr()
    assert rc == 2, (rc, cap.err)
    assert "Traceback" not in cap.err + cap.out
    errors = [ln for ln in cap.err.splitlines() if ln.startswith("canbrake: error:")]
    assert len(errors) == 1, cap.err
    for fragment in case["expect"]:
        assert fragment in cap.err, (fragment, cap.err)
    assert not (tmp_path / "out").exists()  # nothing written before validation passed
