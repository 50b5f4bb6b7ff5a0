"""Alembic migrations of the run catalog (`rig.store.catalog`): one file per schema change in `versions/`."""
