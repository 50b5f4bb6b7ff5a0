"""Where runs' sample files live: a local folder (the store's home by default) or object storage.

`HDRIG_DATA` names the root: a folder, or a URL fsspec knows (`s3://bucket/prefix` through s3fs, whose
endpoint and credentials come from the usual AWS settings: `AWS_ENDPOINT_URL`, `AWS_ACCESS_KEY_ID`...).
Under it, `runs/<id>/` holds a run's part, merged and sealed Parquet files, as in the home folder.

The crash-safety promise holds on both: a file appears whole or not at all. A local file is written under
a temporary name and renamed into place (`rig.store.runfile`); an object is written to a local temporary file
and uploaded with one PUT (a multipart upload for large files), which the object store makes visible only
once complete, so a process killed mid-upload leaves nothing under the file's name.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from datetime import datetime
from pathlib import Path
from typing import Any

import fsspec
import pyarrow.parquet as pq

from rig.store.catalog import StoreError

RUNS_DIR = "runs"


def default_data_url(home: Path) -> str:
    """The data root: `$HDRIG_DATA` when set, else the store's home folder."""
    return os.environ.get("HDRIG_DATA") or str(home)


class RunData:
    """The sample files of runs under one root (a folder or an fsspec URL)."""

    def __init__(self, url: str | os.PathLike[str]) -> None:
        text = os.fspath(url)
        self.is_local = "://" not in text or text.startswith("file://")
        if self.is_local:
            self.root = str(Path(text.removeprefix("file://")).expanduser())
            self.fs: Any = fsspec.filesystem("file")
            self.url = self.root
        else:
            try:
                self.fs, self.root = fsspec.core.url_to_fs(text)
            except (ImportError, ValueError) as exc:
                raise StoreError(f"HDRIG_DATA {text!r}: cannot use this data location ({exc})") from None
            self.root = self.root.rstrip("/")
            self.url = text.rstrip("/")

    def run_folder(self, run_id: str) -> str:
        return f"{self.root}/{RUNS_DIR}/{run_id}"

    def path(self, run_id: str, name: str) -> str:
        return f"{self.run_folder(run_id)}/{name}"

    def display(self, relative: str) -> str:
        """A catalog path (`runs/<id>/data.parquet`) as a user can find it: a local path or a URL."""
        return str(Path(self.root) / relative) if self.is_local else f"{self.url}/{relative}"

    def make_run_folder(self, run_id: str) -> None:
        if self.is_local:
            Path(self.run_folder(run_id)).mkdir(parents=True, exist_ok=True)
        # object stores have no folders: a key's prefix is enough

    def names(self, run_id: str) -> list[str]:
        """The file names in a run's folder, fresh (never from a cached listing); empty when none."""
        folder = self.run_folder(run_id)
        if self.is_local:
            try:
                return os.listdir(folder)
            except FileNotFoundError:
                return []
        self.fs.invalidate_cache(folder)  # another process may have added or removed files since
        try:
            return [p.rsplit("/", 1)[-1] for p in self.fs.ls(folder, detail=False)]
        except FileNotFoundError:
            return []

    def exists(self, path: str) -> bool:
        if self.is_local:
            return os.path.exists(path)
        self.fs.invalidate_cache(path.rsplit("/", 1)[0])
        return bool(self.fs.exists(path))

    def modified_s(self, path: str) -> float:
        """When the file was last written, seconds since the epoch."""
        if self.is_local:
            return os.stat(path).st_mtime
        moment: datetime = self.fs.modified(path)
        return moment.timestamp()

    def delete(self, path: str) -> None:
        if self.is_local:
            Path(path).unlink(missing_ok=True)
        else:
            with contextlib.suppress(FileNotFoundError):
                self.fs.rm_file(path)

    @contextlib.contextmanager
    def parquet(self, path: str) -> Iterator[pq.ParquetFile]:
        """A Parquet file opened for reading its footer and row groups (ranged reads on object storage).
        A missing file is FileNotFoundError, as on disk."""
        if self.is_local:
            with pq.ParquetFile(path) as parquet:
                yield parquet
            return
        with self.fs.open(path, "rb") as handle, pq.ParquetFile(handle) as parquet:
            yield parquet

    @contextlib.contextmanager
    def writing(self, run_id: str, name: str) -> Iterator[Path]:
        """A local path to write the file `name` of a run to; in place once the block ends without error.

        Local: the file's own path (the run-file writers write a temporary file and rename it). Object
        storage: a temporary file, uploaded whole at the end, then removed.
        """
        if self.is_local:
            yield Path(self.path(run_id, name))
            return
        with tempfile.TemporaryDirectory(prefix="hdrig-upload-") as folder:
            local = Path(folder) / name
            yield local
            self.fs.put_file(str(local), self.path(run_id, name))
