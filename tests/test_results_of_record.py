"""The committed tables of record (`results/`): the README shows exactly what the records hold,
the records are one code version's and whole, and they stay within the size budget."""

from __future__ import annotations

import gzip
import json
from pathlib import Path

from experiments import print_tables as pt

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "results"
RECORDS = RESULTS / "records.jsonl.gz"
#: issue 23: "a compressed JSONL artifact committed under a size budget of a few MB"
BUDGET_BYTES = 4 * 2**20


def test_every_table_the_readme_embeds_equals_the_committed_records(capsys):
    assert pt.main([str(RECORDS), "--embedded", str(REPO / "README.md")]) == 0
    out = capsys.readouterr().out
    header, _ = pt.read_records_file(RECORDS)
    names = [t["name"] for t in header["tables"]]
    # every table of the manifest is shown, none twice
    assert f"{len(names)} embedded tables equal the records" in out
    assert sorted(name for name, _, _ in pt.embedded_tables((REPO / "README.md").read_text())) == sorted(names)


def test_the_records_are_one_code_version_and_whole():
    header, records = pt.read_records_file(RECORDS)
    assert not header["mixed"] and not header["subset"]
    assert len({r["key"] for r in records}) == len(records)
    tables = pt.build_tables(header, records)
    for table in tables["tables"]:
        for row in table["rows"]:
            assert row["episodes"] == row["planned"], (table["name"], row["label"])


def test_the_tables_file_is_what_the_printer_makes_of_the_records():
    header, records = pt.read_records_file(RECORDS)
    assert (RESULTS / "tables.md").read_text() == pt.format_document(pt.build_tables(header, records))
    assert (RESULTS / "tables.json").read_text() == pt.tables_json(pt.build_tables(header, records))


def test_the_records_file_keeps_the_size_budget_and_is_plain_gzip_jsonl():
    assert RECORDS.stat().st_size <= BUDGET_BYTES
    with gzip.open(RECORDS, "rt") as f:
        assert json.loads(f.readline())["format"] == pt.FORMAT
