"""Study exports (SPEC §7, §10): streamed CSV files, their codebook, a zip with a manifest.

Files (UTF-8 without BOM, one header row, ``\\n`` line ends, RFC 4180 quoting):

- ``trials.csv``: one row per completed trial (practice included, ``practice=1``).
  The leading columns are ``experiment.records.MODEL_COLUMNS`` exactly, so
  ``experiment.records.read_sequences`` reads the file as it is.
- ``surveys.csv``: one row per questionnaire item answer.
- ``participants.csv``: one row per participant (withdrawn ones marked; deleted ones are gone).
- ``events.csv``: the fine-grained event log, in the order it was written.
- ``codebook.csv``: one row per column of every file (this one included), from
  the hand-written table ``experiment.codebook.CODEBOOK``.
- ``manifest.json`` (zip and directory exports): row counts and hashes of the
  files, the configuration versions, and ``instruments``: every questionnaire
  of every version as its document holds it (citation, DOI, version, item
  texts and kinds, scale, reverse-coded items, attention checks, scoring rule),
  which surveys.csv's provenance columns refer to by version and id.

Columns, their types and the decimal places numbers are rounded to are
declared once in ``experiment.codebook``, whose ``TableWriter`` formats and
writes every file (the simulator's ``trials.csv`` too): see there for the
cell format.

The package, in the order data flows through it:

- ``queries``: what each file selects, column by codebook column name, and
  the order of its rows;
- ``pages``: keyset pagination, each page in its own short session (memory
  bound, SQLite's write lock);
- ``writers``: the CSV stream, the streamed zip with ``manifest.json``, the
  directory export, and the audit record of an export.
"""

from experiment.codebook import EXPORT_FILES
from server.export.pages import PAGE_ROWS, iter_values
from server.export.queries import ExportTarget, export_target
from server.export.writers import (
    CSV_MEDIA_TYPE,
    FORMAT_VERSION,
    FileSummary,
    RowCounter,
    export_study,
    iter_csv,
    iter_zip,
    manifest,
    record_export,
)

__all__ = [
    "CSV_MEDIA_TYPE",
    "EXPORT_FILES",
    "FORMAT_VERSION",
    "PAGE_ROWS",
    "ExportTarget",
    "FileSummary",
    "RowCounter",
    "export_study",
    "export_target",
    "iter_csv",
    "iter_values",
    "iter_zip",
    "manifest",
    "record_export",
]
