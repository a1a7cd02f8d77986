"""The numbers in the documents stay true (issue 47, items 19, 20 and 22).

Every table of measured numbers in README.md, docs/*.md and bench/results.md says where it comes from: its
section names the commit it was measured at (a hash git knows). The cheap ones are rerun here and compared
cell by cell: the forward-backward round trip of ``make paper`` on the corridor (docs/paper.md), the
summary line of ``condtrack track`` and the failure report of ``condtrack compare`` (README.md).
bench/results.md holds today's tables, its history apart.
"""

from __future__ import annotations

import re
import shlex
import shutil
import subprocess
from pathlib import Path

import pytest
from click.testing import CliRunner

from condtrack_cli.cli import cli
from condtrack_cli.evaluate import paper_figures
from condtrack_cli.evaluate.bench import __main__ as bench_main
from conftest import REPO, SAMPLES, shared_sequence

#: The documents whose tables of numbers must say where they come from.
DOCUMENTS = ("README.md", "bench/results.md", *sorted(f"docs/{page.name}" for page in (REPO / "docs").glob("*.md")))
#: A measured number in a table cell: at least two decimals (0.853, 14.85); "2.0" or "§3.2" are not measurements.
MEASURED = re.compile(r"\d\.\d\d")
#: A short or full commit hash: hexadecimal with a letter and a digit (checked against git's history).
HASH = re.compile(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}\b")
SEPARATOR = re.compile(r"^\|(\s*:?-+:?\s*\|)+\s*$")


def markdown_tables(text: str) -> list[tuple[int, list[list[str]], str]]:
    """(line number, rows of cells, provenance) of every table outside code fences.

    A table's provenance is its section's text from the last heading up to the table, and the paragraph just
    after it: where a table says which command and commit produced it. A ``###`` subsection is part of its section
    (the per-group tables of the section against LK and DIS share its command and commit).
    """
    lines = text.splitlines()
    tables = []
    fenced = False
    heading = 0
    index = 0
    while index < len(lines):
        line = lines[index]
        if line.startswith("```"):
            fenced = not fenced
        elif not fenced and line.startswith("#") and not line.startswith("###"):
            heading = index
        elif (not fenced and line.startswith("|") and index + 1 < len(lines)
              and SEPARATOR.match(lines[index + 1])):
            end = index
            while end < len(lines) and lines[end].startswith("|"):
                end += 1
            after = end
            while after < len(lines) and not lines[after].strip():
                after += 1
            stop = after
            while stop < len(lines) and lines[stop].strip() and not lines[stop].startswith(("#", "|", "```")):
                stop += 1
            rows = [[cell.strip() for cell in row.strip().strip("|").split("|")]
                    for row in [lines[index]] + lines[index + 2:end]]
            tables.append((index + 1, rows, "\n".join(lines[heading:index] + lines[after:stop])))
            index = end
            continue
        index += 1
    return tables


def measured(rows: list[list[str]]) -> bool:
    """A table of measurements: a cell beyond the first column of a body row holds a number with two decimals."""
    return any(MEASURED.search(cell) for row in rows[1:] for cell in row[1:])


def known_commits(candidates: set[str]) -> set[str]:
    """The candidates that name a commit of this repository (all of them when git or its history is absent)."""
    if shutil.which("git") is None or not candidates:
        return candidates
    query = "".join(f"{name}^{{commit}}\n" for name in sorted(candidates))
    done = subprocess.run(["git", "cat-file", "--batch-check"], cwd=REPO, input=query, capture_output=True,
                          text=True)
    if done.returncode != 0:
        return candidates
    answers = done.stdout.splitlines()
    return {name for name, answer in zip(sorted(candidates), answers) if not answer.endswith("missing")}


def test_the_table_reader():
    text = ("# A\n\nAt commit 35ed7c7:\n\n| set | x |\n|---|---|\n| a | 0.853 |\n\nafter\n\n"
            "## B\n\n| code | meaning |\n|---|---|\n| 0 | ok |\n\n```\n| a | 0.12 |\n|---|---|\n```\n")
    tables = markdown_tables(text)
    assert [(line, rows) for line, rows, _ in tables] == [(5, [["set", "x"], ["a", "0.853"]]),
                                                           (13, [["code", "meaning"], ["0", "ok"]])]
    assert "35ed7c7" in tables[0][2] and "after" in tables[0][2] and "35ed7c7" not in tables[1][2]
    assert measured(tables[0][1]) and not measured(tables[1][1])
    assert HASH.findall("at 35ed7c7, not 1234567 or abcdefa; 5caea02.") == ["35ed7c7", "5caea02"]
    assert known_commits({"35ed7c7", "0000000a"}) == {"35ed7c7"}


@pytest.mark.parametrize("document", DOCUMENTS)
def test_every_table_of_numbers_names_the_commit_it_was_measured_at(document):
    tables = [(line, provenance) for line, rows, provenance in
              markdown_tables((REPO / document).read_text(encoding="utf-8")) if measured(rows)]
    named = {line: set(HASH.findall(provenance)) for line, provenance in tables}
    commits = known_commits(set().union(*named.values())) if named else set()
    unsourced = [f"{document}:{line}" for line, hashes in named.items() if not hashes & commits]
    assert not unsourced, ("tables of measured numbers whose section names no commit of this repository "
                           "(add the commit they were measured at, or rerun them): " + ", ".join(unsourced))


# --- docs/paper.md: the forward-backward round trip of `make paper` ---------------------------------------

ROUND_TRIP_HEADER = ["sequence", "frames", "method", "points", "median (px)", "p90 (px)"]
#: The rows rerun here (a few seconds): the corridor's three and the garden's stk.
RERUN = (("oxford_corridor_nogt", "stk"), ("oxford_corridor_nogt", "clf"), ("oxford_corridor_nogt", "cnlf"),
         ("flowergarden_nogt", "stk"))
STATS = ("points", "median_px", "p90_px", "came_back", "left_view", "within", "visible_end", "visible_both")


def round_trip_table() -> dict[tuple[str, str], list[str]]:
    """docs/paper.md's round-trip table: (sequence, method) -> the cells after those two, as printed."""
    text = (REPO / "docs" / "paper.md").read_text(encoding="utf-8")
    [rows] = [rows for _, rows, _ in markdown_tables(text) if rows[0][:len(ROUND_TRIP_HEADER)] == ROUND_TRIP_HEADER]
    return {(row[0], row[2]): [row[1]] + row[3:] for row in rows[1:]}


@pytest.mark.parametrize(("sequence", "method"), RERUN)
@pytest.mark.filterwarnings("ignore:.*queries are untrackable:condtrack_cli.errors.CondtrackWarning")  # the way back starts where the forward leg ended
def test_the_round_trip_table_is_what_make_paper_prints(sequence, method, tmp_path):
    folder = shared_sequence(sequence)
    frames = dict((name, count) for name, _, count in paper_figures.SEQUENCES)[sequence]
    if frames is not None:
        folder = paper_figures.linked_folder(folder, tmp_path / sequence, frames)
    trip = paper_figures.round_trip(folder, paper_figures.detect(folder), method, tmp_path)
    stats = paper_figures.round_trip_stats(trip)
    printed = [str(trip.forward.info.n_frames), str(stats["points"]), paper_figures._fmt(stats["median_px"]),
               paper_figures._fmt(stats["p90_px"])] + [f"{stats[key]:.2f}" for key in STATS[3:]]
    assert round_trip_table()[sequence, method] == printed


def test_the_round_trip_table_holds_every_row_make_paper_prints():
    assert sorted(round_trip_table()) == sorted((name, method) for name, _, _ in paper_figures.SEQUENCES
                                                for method in paper_figures.METHODS)


# --- README.md: the summary line and compare's failure report ------------------------------------------------


def readme_summary_example() -> tuple[list[str], str]:
    """The README's example command whose summary line it shows, and that line (the commented line after it)."""
    lines = (REPO / "README.md").read_text(encoding="utf-8").splitlines()
    [index] = [k for k, line in enumerate(lines) if re.match(r"#\s+\d+ points, .* s/frame", line)]
    command = lines[index - 1]
    assert command.startswith("condtrack track "), command
    return shlex.split(command)[1:], lines[index].lstrip("#").strip()


def test_the_readme_summary_line_is_what_its_command_prints(tmp_path, monkeypatch):
    arguments, shown = readme_summary_example()
    (tmp_path / "sample_sequences").symlink_to(SAMPLES)  # the README's paths are relative to the repository
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(cli, arguments)  # stderr is not a terminal: the summary line alone
    assert result.exit_code == 0, result.output
    [printed] = result.stderr.splitlines()
    seconds = r"\d+\.\d{3}"  # the seconds a frame are the machine's
    assert re.search(seconds + r" s/frame", shown), shown
    expected = re.escape(re.sub(seconds, "SECONDS", shown)).replace("SECONDS", seconds)
    assert re.fullmatch(expected, printed), f"README shows {shown!r}, the command prints {printed!r}"
    assert (tmp_path / "tracks.csv").is_file()


def readme_compare_example() -> tuple[list[list[str]], list[str]]:
    """The README's golden-file commands (track golden.csv, track today.csv, compare) and the lines of its failure
    example up to its ``...``."""
    lines = (REPO / "README.md").read_text(encoding="utf-8").splitlines()
    commands = [shlex.split(line.split("#")[0])[1:] for line in lines
                if line.startswith("condtrack ") and re.search(r"golden\.csv|today\.csv", line)]
    start = lines.index("differ: A=golden.csv B=today.csv (64 points, 30 frames)")
    return commands, lines[start:lines.index("...", start)]


def test_the_readme_compare_failure_is_what_its_commands_print(tmp_path, monkeypatch):
    commands, shown = readme_compare_example()
    assert [command[0] for command in commands] == ["track", "track", "compare"]
    (tmp_path / "sample_sequences").symlink_to(SAMPLES)
    monkeypatch.chdir(tmp_path)
    commands[1] += ["--set", "measure.search_max=8"]  # the change the example's prose names
    for command in commands[:2]:
        assert CliRunner().invoke(cli, command).exit_code == 0
    result = CliRunner().invoke(cli, commands[2])
    assert result.exit_code == 1
    printed = result.stdout.splitlines()
    # The counts are this machine's ("another machine's differ in the last digits"): the report's lines down to its
    # table's header read the same with every number masked, and the differing cells are within a tenth of the shown.
    header = shown.index("largest differences:") + 2
    assert [_masked(line) for line in printed[:header]] == [_masked(line) for line in shown[:header]]
    shown_cells, printed_cells = (_differing_cells(lines) for lines in (shown, printed))
    assert abs(printed_cells - shown_cells) <= 0.1 * shown_cells


def _masked(line: str) -> str:
    """``line`` with each number replaced by ``#``."""
    return re.sub(r"\d+(\.\d+)?", "#", line)


def _differing_cells(lines: list[str]) -> int:
    """The count of ``compare``'s ``differing cells: N of M`` line."""
    return int(re.search(r"differing cells: (\d+) of", "\n".join(lines)).group(1))


# --- bench/results.md: today's tables, the history apart (issue 47, item 22) ---------------------------------

#: A reader finds a section's first table within this many lines of its heading (about one screen).
SCREEN = 40


def sections(text: str) -> dict[str, list[str]]:
    """``## `` heading -> the section's lines after it."""
    found: dict[str, list[str]] = {}
    current = None
    for line in text.splitlines():
        if line.startswith("## "):
            current = line
            found[current] = []
        elif current is not None:
            found[current].append(line)
    return found


def test_make_bench_keeps_the_sections_it_does_not_write():
    old = "# t\n\nintro\n\n## Speed (issue 13)\n\nold speed\n\n## Hard cases (issue 31)\n\n| a |\n\n## Many clips\n\nx\n"
    assert bench_main.other_sections(old) == ["## Hard cases (issue 31)", "", "| a |", ""]
    assert bench_main.other_sections("# t\n\nno sections\n") == []


def test_results_md_holds_todays_tables_and_points_to_the_history():
    results = (REPO / "bench" / "results.md").read_text(encoding="utf-8")
    history = (REPO / "bench" / "history.md").read_text(encoding="utf-8")
    assert results.startswith("# condtrack benchmark\n\n" + "\n".join(bench_main.INTRO) + "\n")  # as make bench writes it
    assert "`bench/history.md`" in results
    found = sections(results)
    late = [heading for heading, lines in found.items() if any(line.startswith("|") for line in lines)
            and not any(line.startswith("|") for line in lines[:SCREEN])]
    assert not late, f"sections whose first table is more than {SCREEN} lines down: {late}"
    assert len(results.splitlines()) < 750  # the section against LK and DIS holds a table per group of sets (issue 45)
    titles = {heading[3:].split(" (")[0] for heading in found}
    assert titles >= set(bench_main.WRITTEN_SECTIONS) - {"Covariance calibration"}
    # every section of the history is one of results.md's, so a reader finds the history of what they read
    assert {heading for heading in sections(history)} <= set(found)
