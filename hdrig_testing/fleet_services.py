"""Real services on loopback for the fleet's tests and benchmark: PostgreSQL from Debian's `postgresql`
package in a temporary folder, and an S3 API (moto's server mode).

Both bind 127.0.0.1 only and stop with their context. A missing part is `MissingPartError`, which the
tests turn into a skip that names what to install, or a failure under CI (`CI` set), which must never
skip them.
"""

from __future__ import annotations

import contextlib
import glob
import os
import pwd
import shutil
import socket
import subprocess
import tempfile
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

PG_START_TIMEOUT_S = 60.0  # pg_ctl -w waits up to this for the server to accept connections


class MissingPartError(RuntimeError):
    """A part these tests need is not installed; the message says which and how to install it."""


def _pg_bin() -> Path:
    found = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"), key=lambda p: int(Path(p).parts[-3]))
    if not found:
        raise MissingPartError(
            "PostgreSQL is not installed (`apt-get install postgresql`; .ci/run installs it)"
        )
    return Path(found[-1]).parent


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


@dataclass
class PostgresServer:
    """A running PostgreSQL on 127.0.0.1:`port`, superuser `hdrig` with trust authentication."""

    port: int
    folder: Path
    bin_dir: Path
    run_as: dict[str, Any]

    def url(self, database: str = "postgres") -> str:
        return f"postgresql://hdrig@127.0.0.1:{self.port}/{database}"

    def new_database(self) -> str:
        """A fresh empty database; its URL."""
        import psycopg

        name = f"t_{uuid.uuid4().hex[:12]}"
        with psycopg.connect(
            f"host=127.0.0.1 port={self.port} user=hdrig dbname=postgres", autocommit=True
        ) as db:
            db.execute(f'CREATE DATABASE "{name}"')
        return self.url(name)


@contextlib.contextmanager
def postgres_server(fsync: bool = False) -> Iterator[PostgresServer]:
    """Start PostgreSQL in a temporary folder (initdb, pg_ctl), stop it and remove the folder after.

    PostgreSQL refuses to run as root: as root, the server runs as the `postgres` user the package
    made (or `nobody`), which owns the folder. `fsync=False` for tests (nothing need survive a power
    cut); the benchmark keeps it on.
    """
    bin_dir = _pg_bin()
    run_as: dict[str, Any] = {}
    folder = Path(tempfile.mkdtemp(prefix="hdrig-pg-"))
    if os.geteuid() == 0:
        for name in ("postgres", "nobody"):
            with contextlib.suppress(KeyError):
                user = pwd.getpwnam(name)
                break
        else:
            raise MissingPartError("running as root with no `postgres` or `nobody` user to run PostgreSQL as")
        run_as = {"user": user.pw_uid, "group": user.pw_gid, "extra_groups": []}
        os.chown(folder, user.pw_uid, user.pw_gid)
    data, sockets = folder / "data", folder / "sockets"
    port = _free_port()
    env = {**os.environ, "LC_ALL": "C"}

    def run(*args: str) -> None:
        done = subprocess.run(args, capture_output=True, text=True, env=env, cwd=folder, **run_as)
        if done.returncode:
            raise RuntimeError(f"{' '.join(args[:2])} failed: {done.stderr.strip() or done.stdout.strip()}")

    try:
        run(str(bin_dir / "initdb"), "-D", str(data), "-U", "hdrig", "-A", "trust", "-E", "UTF8", "--no-sync")
        sockets.mkdir()
        if run_as:
            os.chown(sockets, run_as["user"], run_as["group"])
        options = f"-h 127.0.0.1 -p {port} -k {sockets} -c max_connections=200" + (
            "" if fsync else " -F -c synchronous_commit=off"
        )
        run(
            str(bin_dir / "pg_ctl"), "-D", str(data), "-l", str(folder / "log"), "-o", options, "-w",
            "-t", str(int(PG_START_TIMEOUT_S)), "start",
        )  # fmt: skip
        try:
            yield PostgresServer(port, folder, bin_dir, run_as)
        finally:
            run(str(bin_dir / "pg_ctl"), "-D", str(data), "-m", "fast", "-w", "stop")
    finally:
        shutil.rmtree(folder, ignore_errors=True)


@dataclass
class S3Server:
    """An S3 API on 127.0.0.1:`port` (moto), with one bucket; `env` holds the settings a client needs."""

    endpoint: str
    bucket: str

    @property
    def env(self) -> dict[str, str]:
        return {
            "AWS_ENDPOINT_URL": self.endpoint,
            "AWS_ACCESS_KEY_ID": "hdrig-test",
            "AWS_SECRET_ACCESS_KEY": "hdrig-test",
            "AWS_DEFAULT_REGION": "us-east-1",
        }

    def url(self, prefix: str) -> str:
        return f"s3://{self.bucket}/{prefix}"


@contextlib.contextmanager
def s3_server(bucket: str = "hdrig-runs") -> Iterator[S3Server]:
    """moto's S3 server on a free loopback port, with `bucket` made; stopped after."""
    try:
        import boto3
        from moto.server import ThreadedMotoServer
    except ImportError:
        raise MissingPartError(
            "moto is not installed (`pip install -e '.[fleet]'`; make test installs it)"
        ) from None
    port = _free_port()
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=port, verbose=False)
    server.start()
    try:
        found = S3Server(f"http://127.0.0.1:{port}", bucket)
        env = found.env
        boto3.client(
            "s3",
            endpoint_url=found.endpoint,
            aws_access_key_id=env["AWS_ACCESS_KEY_ID"],
            aws_secret_access_key=env["AWS_SECRET_ACCESS_KEY"],
            region_name=env["AWS_DEFAULT_REGION"],
        ).create_bucket(Bucket=bucket)
        yield found
    finally:
        server.stop()
