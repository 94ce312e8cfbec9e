"""What each export file selects: every codebook column has one source, and the select list follows the codebook."""

from __future__ import annotations

import pytest

from experiment.codebook import EXPORT_FILES, columns
from server.export.queries import FILE_QUERIES, Converted, Derived, ExportTarget, FileQuery, Filled

TARGET = ExportTarget(study_id=1, slug="a-study", title="A study")
QUERIED_FILES = [name for name in EXPORT_FILES if name != "codebook.csv"]  # the codebook is the table itself


def test_every_export_file_but_the_codebook_has_a_query():
    assert sorted(FILE_QUERIES) == sorted(QUERIED_FILES)


@pytest.mark.parametrize("name", QUERIED_FILES)
def test_the_select_list_names_exactly_the_codebook_columns(name):
    query = FILE_QUERIES[name]
    assert [column for column, _ in query.sources] == columns(name)
    selected = [c.name for c in query.select(TARGET).selected_columns]
    assert selected == [column for column, source in query.sources if not isinstance(source, Filled | Derived)]


@pytest.mark.parametrize("name", QUERIED_FILES)
def test_rows_read_back_put_every_value_under_its_own_column(name):
    """A selected row whose values are their column names, keyset keys appended, comes back in file order."""
    query = FILE_QUERIES[name]
    selected = [c.name for c in query.select(TARGET).selected_columns]
    [row] = query.file_rows([(*selected, *("key",) * len(query.keys))], TARGET)
    expected = []
    for column, source in query.sources:
        if isinstance(source, Filled):
            expected.append(source.value(TARGET))
        elif isinstance(source, Converted):
            expected.append(source.convert(column))
        elif isinstance(source, Derived):  # from its inputs' values as selected (here their names)
            expected.append(source.derive(TARGET, *source.inputs))
        else:
            expected.append(column)
    assert row == tuple(expected)


def test_a_codebook_column_without_a_source_or_a_source_without_a_column_is_refused():
    events = FILE_QUERIES["events.csv"]
    sources = dict(events.sources)
    kind = sources.pop("kind")
    with pytest.raises(ValueError, match=r"codebook columns without a source: \['kind'\]"):
        FileQuery("events.csv", sources, lambda query, target: query, events.keys)
    with pytest.raises(ValueError, match=r"sources without a codebook column: \['kind_of'\]"):
        FileQuery("events.csv", {**sources, "kind": kind, "kind_of": kind}, lambda query, target: query, events.keys)
