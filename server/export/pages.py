"""Reading an export file page by page: keyset pagination in short read-only sessions.

Memory: rows are read by keyset pagination (``PAGE_ROWS`` rows per query,
ordered by an indexed key; trials and answers ``PARTICIPANT_BATCH``
participants per query so that no query sorts a whole study), each page in its own short read-only session that
is closed before the page is formatted and yielded. Memory is bounded by one
page plus one encoded chunk, whatever the number of rows. On SQLite every
transaction takes the write lock (``BEGIN IMMEDIATE``, see ``server.db.engine``), so a
single long read transaction would stall participants while a slow client
downloads; short per-page transactions hold it for milliseconds. The price is
that an export taken while a study runs is not one snapshot: rows committed
during the export may or may not appear, but no row appears twice or half
written, and each row is internally consistent.

``factory`` is the app's ``server.db.units.Database`` (a ``sessionmaker`` in tests), or any callable returning a context
manager that yields a session (``lambda: nullcontext(session)`` reads within
a transaction that is already open, as the model fit does).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from typing import Any

from sqlalchemy import Select, select, tuple_

from experiment.codebook import CODEBOOK, EXPORT_FILES, codebook_rows
from server.db.units import SessionOpener
from server.export.queries import FILE_QUERIES, ExportTarget, participant_condition
from server.models import Participant

#: Rows fetched per query (one short transaction each: on SQLite it holds the write lock, so keep it small).
PAGE_ROWS = 1000
#: Participants whose trials (or answers) one query covers (then paged by ``PAGE_ROWS``).
PARTICIPANT_BATCH = 5
#: Participant ids fetched per query to form those batches.
ID_PAGE = 1000


def iter_values(factory: SessionOpener, target: ExportTarget, name: str,
                page_rows: int = PAGE_ROWS) -> Iterator[list[tuple[Any, ...]]]:
    """Pages of one file's rows as raw values in the file's column order (formatted by ``TableWriter``)."""
    if name not in CODEBOOK:
        raise KeyError(f"unknown export file {name!r}; files: {', '.join(EXPORT_FILES)}")
    if name == "codebook.csv":
        yield codebook_rows()
        return
    file = FILE_QUERIES[name]
    query = file.select(target)
    if file.per_participant:
        pages = _participant_pages(factory, target, query, file.keys, page_rows)
    else:
        pages = _pages(factory, query, file.keys, page_rows)
    for page in pages:
        yield file.file_rows(page, target)


def _pages(factory: SessionOpener, query: Select[Any], keys: tuple[Any, ...],
           page_rows: int) -> Iterator[Sequence[Any]]:
    """Keyset pagination: each page in its own short session, closed before the page is used."""
    n_keys, last = len(keys), None
    query = query.add_columns(*keys).order_by(*keys).limit(page_rows)
    while True:
        page_query = query
        if last is not None:
            page_query = query.where(tuple_(*keys) > tuple_(*last) if n_keys > 1 else keys[0] > last[0])
        with factory() as session:  # read only: nothing is added, the transaction is rolled back on close
            rows = session.connection().execute(page_query).all()
        if rows:
            yield rows
        if len(rows) < page_rows:
            return
        last = tuple(rows[-1][-n_keys:])


def _participant_pages(factory: SessionOpener, target: ExportTarget, query: Select[Any],
                       keys: tuple[Any, ...], page_rows: int) -> Iterator[Sequence[Any]]:
    """Keyset pages of per-participant rows, ``PARTICIPANT_BATCH`` participants per query.

    Ordering all of a study's trials by (participant, id) in one query makes the database sort
    every row of the study for each page (quadratic); restricting each query to a small batch of
    participant ids keeps every page's work (and the time it holds SQLite's lock) proportional to
    the batch.
    """
    last_id = 0
    while True:
        with factory() as session:
            ids = session.scalars(select(Participant.id).where(participant_condition(target), Participant.id > last_id)
                                  .order_by(Participant.id).limit(ID_PAGE)).all()
        for start in range(0, len(ids), PARTICIPANT_BATCH):
            batch = ids[start:start + PARTICIPANT_BATCH]
            yield from _pages(factory, query.where(Participant.id.in_(batch), keys[0].in_(batch)), keys, page_rows)
        if len(ids) < ID_PAGE:
            return
        last_id = ids[-1]
