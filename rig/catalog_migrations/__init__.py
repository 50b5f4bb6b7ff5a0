"""Alembic migrations of the run catalog (`rig.catalog`): one file per schema change in `versions/`."""
