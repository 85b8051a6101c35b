"""benchmarks/results_file.py: where a benchmark's row lands in RESULTS.md."""

from pathlib import Path

from conftest import load_benchmark


def test_a_row_goes_below_the_table_not_below_the_text_after_it(tmp_path: Path) -> None:
    results = load_benchmark("results_file")
    path = tmp_path / "RESULTS.md"
    path.write_text(
        "# Benchmark results\n\n## Speed\n\nintro\n\n| a | b |\n|---|---|\n| 1 | 2 |\n\nReading of the rows above.\n\n"
        "## Other\n\ntext\n"
    )
    results.append_row("Speed", "intro", ["a", "b"], ["3", "4"], path=str(path))
    assert "| 1 | 2 |\n| 3 | 4 |\n\nReading of the rows above.\n\n## Other" in path.read_text()
    # a new section: heading, intro, header, rule, row at the end
    results.append_row("New", "what it measures", ["x"], ["5"], path=str(path))
    assert path.read_text().endswith("## New\n\nwhat it measures\n\n| x |\n|---|\n| 5 |\n")
    # a section without its table (the header changed): the row goes to the section's end, before the next heading
    results.append_row("Speed", "intro", ["a", "b", "c"], ["6", "7", "8"], path=str(path))
    assert "Reading of the rows above.\n| 6 | 7 | 8 |\n\n## Other" in path.read_text()
