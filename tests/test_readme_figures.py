"""The benchmark figures of the README and of docs/*.md against the JSON they come from (no
Taichi, fast).

A table (or paragraph) of these pages whose figures come from a benchmark is preceded by a comment
naming its JSON file(s), e.g. `<!-- figures: bench/results/deformation.json -->`; the block is
the lines after it up to the first blank line. Every number in the block (outside its header
row) must be one of the JSON's numbers as printed: a value v of the file matches a printed
number with d decimals when |v − number| ≤ half a unit of its last digit (4.4 for 4.42,
1.2e-04 for 1.23e-4), or v in thousandths (millimetres from metres). A number printed as a
ratio ("3.4×") may also be the ratio of two numbers of one JSON object ("SOFA / tissue")."""

import itertools
import json
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TAG = re.compile(r"<!-- figures: ([^>]*?) -->")
NUMBER = re.compile(r"(?<![\w.])([-−]?\d[\d,]*(?:\.\d+)?(?:e[-+]?\d+)?)(×?)")


PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def tagged_blocks(text: str):
    """(files, lines) of every tagged block of a page."""
    lines = text.splitlines()
    for i, line in enumerate(lines):
        match = TAG.search(line)
        if match:
            block = list(itertools.takewhile(str.strip, lines[i + 1:]))
            yield match.group(1).split(), block


def json_values(path: Path) -> tuple[list[float], list[float]]:
    """Every number of the file and its thousandths; the ratios of two numbers of one object."""
    values, ratios = [], []

    def walk(node):
        if isinstance(node, dict):
            numbers = [v for v in node.values() if isinstance(v, (int, float)) and not isinstance(v, bool)]
            values.extend(numbers)
            ratios.extend(a / b for a in numbers for b in numbers if b)
            for v in node.values():
                if isinstance(v, (dict, list)):
                    walk(v)
        elif isinstance(node, list):
            for v in node:
                if isinstance(v, (int, float)) and not isinstance(v, bool):
                    values.append(v)
                else:
                    walk(v)

    walk(json.loads(path.read_text()))
    return values + [1e3 * v for v in values], ratios


def printed_numbers(line: str) -> list[tuple[str, bool]]:
    """The numbers of a line outside inline code, each with whether it is printed as a ratio."""
    line = re.sub(r"`[^`]*`", "", line)
    return [(n, times == "×") for n, times in NUMBER.findall(line)]


def half_unit(text: str) -> float:
    mantissa, _, exponent = text.lower().partition("e")
    decimals = len(mantissa.partition(".")[2])
    return 0.5 * 10.0 ** (-decimals) * 10.0 ** int(exponent or 0)


def matches(text: str, values) -> bool:
    number = float(text.replace(",", "").replace("−", "-"))
    tolerance = half_unit(text.replace(",", "")) * (1 + 1e-9)
    return any(abs(v - number) <= tolerance for v in values)


def blocks():
    return [block for page in PAGES for block in tagged_blocks(page.read_text())]


def test_the_pages_tag_their_benchmark_tables():
    """The start-up, deformation, versus and stability figures are tagged."""
    named = {f for files, _ in blocks() for f in files}
    for name in ("startup.json", "deformation.json", "versus.json", "stability.json"):
        assert f"bench/results/{name}" in named, name


@pytest.mark.parametrize("index", range(len(blocks())))
def test_every_figure_of_a_tagged_block_is_in_its_json(index):
    files, lines = blocks()[index]
    found = [json_values(ROOT / f) for f in files]
    values = [v for plain, _ in found for v in plain]
    ratios = values + [v for _, r in found for v in r]
    rows = [line for line in lines if not re.fullmatch(r"\|[-| ]*\|", line.strip())]
    body = rows[1:] if rows and rows[0].startswith("|") else rows     # a table's header row names columns
    missing = [(n, line[:60]) for line in body for n, ratio in printed_numbers(line)
               if not matches(n, ratios if ratio else values)]
    assert not missing, f"{files}: figures not in the JSON: {missing[:10]}"


def test_the_check_catches_a_wrong_figure():
    """Controls: two figures the README printed before this check (768,000 tetrahedra for
    806,400; 2.12 ms for the 1,512-tet matrix-free step of 2.1149 ms)."""
    values, ratios = json_values(ROOT / "bench/results/deformation.json")
    assert matches("806,400", values) and not matches("768,000", values)
    assert matches("2.11", values) and not matches("2.12", values)
    assert matches("2.3×".rstrip("×"), ratios)
