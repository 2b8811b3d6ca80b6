"""The generated tables of README.md and docs/*.md match the records they are made from.

Each page's ``<!-- records:NAME -->`` blocks are made again in memory from
``benchmarks/results/*.json`` (``benchmarks/docs_tables.py``, no solve) and compared with the page;
``make docs-tables`` rewrites them after a record changed.
"""

import importlib.util
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("docs_tables", ROOT / "benchmarks" / "docs_tables.py")
docs_tables = importlib.util.module_from_spec(spec)
spec.loader.exec_module(docs_tables)


@pytest.mark.parametrize("page", docs_tables.PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_generated_blocks_match_the_records(page):
    text = page.read_text()
    assert docs_tables.render(text) == text, f"{page.relative_to(ROOT)}: run `make docs-tables`"


def test_every_table_is_used_and_names_its_record():
    """Every table of docs_tables.TABLES has a block on some page, and names the record it came from."""
    used = {m.group("name") for page in docs_tables.PAGES for m in docs_tables.BLOCK.finditer(page.read_text())}
    assert used == set(docs_tables.TABLES)
    for name, make in docs_tables.TABLES.items():
        assert "benchmarks/results/" in make() or "No record yet" in make(), name


def test_a_block_is_rewritten_and_an_unknown_one_refused():
    stale = "x\n<!-- records:sweeps -->\nold\n<!-- /records:sweeps -->\ny\n"
    new = docs_tables.render(stale)
    assert new.startswith("x\n<!-- records:sweeps -->\n| nodes |") and new.endswith("<!-- /records:sweeps -->\ny\n")
    assert docs_tables.render(new) == new
    with pytest.raises(KeyError, match="no such table"):
        docs_tables.render("<!-- records:nope -->\n<!-- /records:nope -->")
