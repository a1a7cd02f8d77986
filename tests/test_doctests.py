"""The Python API's docstring examples (issue 30.4), each run as a doctest from a folder holding the samples."""

from __future__ import annotations

import doctest

import pytest

from condtrack_cli import api
from conftest import SAMPLES

EXAMPLES = [test for test in doctest.DocTestFinder().find(api) if test.examples]


def test_every_public_name_has_an_example():
    named = {test.name.removeprefix("condtrack_cli.api.") for test in EXAMPLES}
    assert named == {"track", "read_tracks", "Tracks", "Tracks.to_csv", "Tracks.to_hdf5"}


@pytest.mark.parametrize("example", EXAMPLES, ids=lambda test: test.name)
def test_docstring_example(example, tmp_path, monkeypatch):
    (tmp_path / "sample_sequences").symlink_to(SAMPLES)
    monkeypatch.chdir(tmp_path)
    runner = doctest.DocTestRunner(optionflags=doctest.NORMALIZE_WHITESPACE)
    report: list[str] = []
    result = runner.run(example, out=report.append)
    assert result.failed == 0, "".join(report)
