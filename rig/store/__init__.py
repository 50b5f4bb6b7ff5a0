"""The run store: where runs, their catalog and their files live.

- `runs.py`: `RunStore`, the one door to a store — recording runs as they play (Parquet parts, sealed on
  stop), listing, showing, exporting and importing them, the analyses' folders.
- `catalog.py` and `catalog_migrations/`: the catalog of runs, keys and audit lines (SQLAlchemy on
  SQLite or PostgreSQL, migrated by Alembic under a lock).
- `datastore.py`: where the run data sits (a folder or `s3://`).
- `runfile.py`: the run format on disk (columns, metadata, units) shared with the model's `Run`.
- `importmap.py`: reading runs recorded elsewhere (CSV/Parquet with a column map).
"""

from rig.store.runs import RunStore

__all__ = ["RunStore"]
