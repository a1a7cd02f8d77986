"""Progress of a single clip (issue 30.1): a bar with frames, fps and time left on a terminal, one summary line elsewhere."""

from __future__ import annotations

import re

from click.testing import CliRunner

from condtrack_cli.cli import cli
from conftest import FORCED_TERMINAL, SAMPLES

SAMPLE = SAMPLES / "occlusion"  # 30 frames, latest query on frame 7: the backward pass reads 8 frames
TRACK = ["track", str(SAMPLE), "-p", str(SAMPLE / "queries.csv"), "-m", "stk"]
SUMMARY = re.compile(r"^64 points, [\d.]+% of tracked rows visible, [\d.]+ s/frame \(stk\) -> .*o\.csv$")


def test_a_terminal_gets_a_bar_with_frames_fps_and_time_left_then_the_summary(tmp_path):
    result = CliRunner().invoke(cli, [*TRACK, "-o", str(tmp_path / "o.csv")], env=FORCED_TERMINAL)
    assert result.exit_code == 0, result.output
    drawn = re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "", result.stderr)  # without the terminal's control sequences
    last = [line for line in drawn.replace("\r", "\n").splitlines() if line.startswith("tracking")][-1]
    assert re.fullmatch(r"tracking \S+ 38/38 frames [\d.]+ fps \d:\d\d:\d\d\s*", last), last
    assert SUMMARY.match(drawn.strip().splitlines()[-1])


def test_without_a_terminal_only_the_summary_line_and_with_q_nothing(tmp_path):
    result = CliRunner().invoke(cli, [*TRACK, "-o", str(tmp_path / "o.csv")])
    assert result.exit_code == 0 and len(result.stderr.splitlines()) == 1 and SUMMARY.match(result.stderr.strip())
    quiet = CliRunner().invoke(cli, [*TRACK, "-o", str(tmp_path / "q.csv"), "-q"], env=FORCED_TERMINAL)
    assert quiet.exit_code == 0 and quiet.stderr == ""
