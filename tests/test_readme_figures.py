"""Every figure the README quotes is one a benchmark printed.

A paragraph or list item that names `benchmarks/NAME.md` (or `.py`) takes its figures from that report, and
so do the lists and tables right after such a paragraph. Each number there must appear in the report(s)
named, so a report made again with other results fails this test until the README says what the report
says. Other paragraphs state facts of the design (pitches, counts, defaults), tested where they are
defined; `test_measured_figures_stand_only_where_a_report_is_named` keeps measured figures out of them.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"

NUMBER = re.compile(r"(?<![\w.\-/^])[-+]?\d[\d,]*(?:\.\d+)?(?:e[-+]?\d+)?(?![\w/])")
# In a report a figure may run into its unit ("53x", "12ms").
PRINTED = re.compile(r"(?<![\w.\-/^])[-+]?\d[\d,]*(?:\.\d+)?(?:e[-+]?\d+)?")
REPORT = re.compile(r"benchmarks/(\w+)\.(?:md|py)")
# Milliseconds, microseconds, memory and speed ratios: figures only a run can give. (Seconds are left out:
# the README states timeouts and intervals of the design in seconds.)
MEASURED = re.compile(r"(?<![\w.])\d+(?:\.\d+)?(?:\s*(?:ms|us|MiB|KiB|GB)\b|x\b| times (?:faster|slower|less|more))")


def _prose(paragraph: str) -> str:
    """The paragraph without code spans, links and citation years, whose numbers are not figures."""
    text = re.sub(r"`[^`]*`", "", paragraph)
    text = re.sub(r"\]\([^)]*\)", "]", text)
    return re.sub(r"\b(?:19|20)\d\d\)", ")", text)


def _paragraphs():
    """(section heading, paragraph or list item, reports its figures come from) for all the README's prose."""
    text = re.sub(r"```.*?```", "", README.read_text(encoding="utf-8"), flags=re.S)
    for section in re.split(r"\n(?=#+ )", text):
        heading = section.splitlines()[0] if section.strip() else ""
        introduced: frozenset[str] = frozenset()
        for paragraph in re.split(r"\n\s*\n", section):
            if not paragraph.lstrip().startswith(("* ", "|")):              # "**bold**" opens a paragraph
                introduced = frozenset(REPORT.findall(paragraph))
                yield heading, paragraph, introduced
                continue
            for item in re.split(r"\n(?=\* )", paragraph):
                yield heading, item, frozenset(REPORT.findall(item)) or introduced


def _numbers(text: str, pattern: re.Pattern = NUMBER) -> list[str]:
    return [n.rstrip(",").replace(",", "").lstrip("+") for n in pattern.findall(text)]


def _quoted_figures():
    for heading, paragraph, reports in _paragraphs():
        if reports:
            yield pytest.param(paragraph, reports, id=f"{heading[:40]}|{paragraph[:40]}")


@pytest.mark.parametrize(("paragraph", "reports"), list(_quoted_figures()))
def test_every_figure_is_in_the_report_its_paragraph_names(paragraph, reports):
    printed = set()
    for name in reports:
        report = ROOT / "benchmarks" / f"{name}.md"
        assert report.exists(), f"the README names benchmarks/{name}.md, which no benchmark has written"
        printed |= set(_numbers(report.read_text(encoding="utf-8"), PRINTED))
    missing = [n for n in _numbers(_prose(paragraph)) if n not in printed]
    assert not missing, f"figures not in {sorted(reports)}: {missing}"


def test_measured_figures_stand_only_where_a_report_is_named():
    unsourced = [(heading, hit.group(0)) for heading, paragraph, reports in _paragraphs() if not reports
                 for hit in MEASURED.finditer(_prose(paragraph))]
    assert not unsourced, f"measured figures with no report named before them: {unsourced}"


def test_a_figure_the_report_does_not_print_is_caught(tmp_path):
    """The check itself: a made-up figure in a paragraph naming a real report is not found in it."""
    report = (ROOT / "benchmarks" / "forward.md").read_text(encoding="utf-8")
    assert "987654.3" not in set(_numbers(report, PRINTED))
    assert "987654.3" in _numbers(_prose("From `benchmarks/forward.md`: 987654.3 ms a frame."))
    assert MEASURED.search(_prose("a frame takes 12.5 ms"))
