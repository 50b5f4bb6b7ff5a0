"""Pytest fixtures of the fleet's real parts (a pytest plugin, named in tests/conftest.py): PostgreSQL,
an S3 API and a Dask LocalCluster, each on loopback.

A part that is not installed skips the tests that need it with a line saying what to install; under CI
(`CI` set) it fails them instead, since CI must never skip them (.ci/run installs every part).
"""

from __future__ import annotations

import os
import uuid
from collections.abc import Iterator
from typing import Any

import pytest

from hdrig_testing.fleet_services import (
    MissingPartError,
    PostgresServer,
    S3Server,
    postgres_server,
    s3_server,
)


def missing(why: str) -> None:
    """Skip, saying why, or fail under CI."""
    if os.environ.get("CI"):
        pytest.fail(f"CI must not skip this: {why}")
    pytest.skip(f"skipped here: {why}")


@pytest.fixture(scope="session")
def postgres() -> Iterator[PostgresServer]:
    try:
        with postgres_server() as server:
            yield server
    except MissingPartError as exc:
        missing(str(exc))


@pytest.fixture
def pg_url(postgres: PostgresServer) -> str:
    """A fresh, empty PostgreSQL database for one test; its URL."""
    try:
        import psycopg  # noqa: F401
    except ImportError:
        missing("psycopg is not installed (`pip install -e '.[fleet]'`; make test installs it)")
    return postgres.new_database()


@pytest.fixture(scope="session")
def s3() -> Iterator[S3Server]:
    try:
        import s3fs  # noqa: F401
    except ImportError:
        missing("s3fs is not installed (`pip install -e '.[fleet]'`; make test installs it)")
    try:
        with s3_server() as server:
            yield server
    except MissingPartError as exc:
        missing(str(exc))


@pytest.fixture
def s3_data(s3: S3Server, monkeypatch: pytest.MonkeyPatch) -> str:
    """A fresh prefix in the test bucket, with this process' AWS settings pointing at the server; its URL."""
    for name, value in s3.env.items():
        monkeypatch.setenv(name, value)
    return s3.url(f"t-{uuid.uuid4().hex[:8]}")


@pytest.fixture(scope="module")
def dask_cluster(s3: S3Server) -> Iterator[Any]:
    """A Dask LocalCluster of two worker processes, one thread each, on loopback; its workers reach the
    test's S3 server (their environment has its settings, as a real cluster's workers have their own)."""
    try:
        from distributed import LocalCluster
    except ImportError:
        missing("dask/distributed is not installed (`pip install -e '.[fleet]'`; make test installs it)")
    with pytest.MonkeyPatch.context() as patch:
        for name, value in s3.env.items():
            patch.setenv(name, value)  # inherited by the worker processes started here
        with LocalCluster(
            n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address=None
        ) as cluster:
            yield cluster
