"""The database: the engine (``engine``), units of work (``units``), SQLite's group commit (``walsync``) and
migrations (``migrate``). ``docs/architecture.md`` says why units of work run where they do."""
