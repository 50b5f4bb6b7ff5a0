"""API keys: salted and slow to test, never the last admin revoked, every change in the audit log.

Issue 23 items 7, 8 and the keys' part of 10: keys were unsalted SHA-256; an admin could revoke its own
key and the last admin key (nobody could manage keys after); `hdrig keys create` and the first start's
admin key were missing from the audit log.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import pytest
import sqlalchemy as sa
from fastapi.testclient import TestClient

from api.app import create_app
from rig.config import load_rig_config
from rig.core import access
from rig.store import catalog as tables
from rig.store.runs import RunStore

API = "/api/v1"
REPO = Path(__file__).resolve().parents[1]


def hdrig(home: Path, *args: str) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, HDRIG_HOME=str(home))
    env.pop("HDRIG_CATALOG", None)
    return subprocess.run(
        [sys.executable, "-m", "rig", *args], capture_output=True, text=True, env=env, cwd=REPO, timeout=300
    )


def stored_hashes(store: RunStore) -> dict[str, str]:
    with store.catalog.read() as db:
        return {name: h for name, h in db.execute(sa.select(tables.keys.c.name, tables.keys.c.hash))}


@pytest.fixture
def store(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> RunStore:
    monkeypatch.delenv("HDRIG_CATALOG", raising=False)
    return RunStore(tmp_path / "home")


def test_keys_are_kept_as_salted_scrypt_not_their_sha256(store: RunStore) -> None:
    tokens = {name: access.create_key(store, "viewer", name) for name in ("one", "two")}
    hashes = stored_hashes(store)
    salts = set()
    for name, token in tokens.items():
        assert hashes[name] != hashlib.sha256(token.encode()).hexdigest()
        kind, n, _r, _p, salt, _derived = hashes[name].split("$")
        assert kind == "scrypt" and int(n) >= 2**14 and len(bytes.fromhex(salt)) >= 16
        assert access.authenticate(store, token) == (name, access.Role.VIEWER)
        salts.add(salt)
    assert len(salts) == 2  # a salt per key
    assert access.authenticate(store, tokens["one"][:-1] + "x") is None
    assert access.authenticate(store, "") is None and access.authenticate(store, "no.such-key") is None


def test_a_revoke_by_another_process_ends_a_key_this_process_verified(store: RunStore) -> None:
    token = access.create_key(store, "operator", "op")
    assert access.authenticate(store, token) is not None  # now remembered as verified
    assert hdrig(store.home, "keys", "revoke", "op").returncode == 0
    assert access.authenticate(store, token) is None


def test_the_migration_salts_the_keys_of_an_older_store_and_they_still_work(tmp_path: Path) -> None:
    from alembic import command

    path = tmp_path / "home" / "catalog.sqlite"
    path.parent.mkdir()
    legacy = "an-old-key-made-before-the-key-ids"
    engine = sa.create_engine(f"sqlite:///{path}")
    with engine.begin() as conn:
        config = tables._alembic_config()
        config.attributes["connection"] = conn
        command.upgrade(config, "0003")
        conn.execute(
            sa.text("INSERT INTO keys (name, role, hash, created) VALUES ('old', 'admin', :h, 'then')"),
            {"h": hashlib.sha256(legacy.encode()).hexdigest()},
        )
    engine.dispose()
    store = RunStore(tmp_path / "home", catalog=f"sqlite:///{path}")
    assert stored_hashes(store)["old"].startswith("scrypt$")
    assert access.authenticate(store, legacy) == ("old", access.Role.ADMIN)
    assert access.authenticate(store, legacy + "x") is None


def service(store: RunStore) -> TestClient:
    config = load_rig_config("configs/rigs/sim.yaml").model_copy(update={"pace": "virtual"})
    return TestClient(create_app(config, store))


def test_the_last_admin_key_cannot_be_revoked_nor_revoke_itself_alone(store: RunStore) -> None:
    first = access.create_key(store, "admin", "first")
    viewer = access.create_key(store, "viewer", "someone")
    with service(store) as client:
        as_first = {"Authorization": f"Bearer {first}"}
        refused = client.delete(f"{API}/keys/first", headers=as_first)
        assert refused.status_code == 409, refused.text
        assert "last live admin key" in refused.json()["detail"]
        assert client.get(f"{API}/keys", headers=as_first).status_code == 200  # still an admin
        assert client.delete(f"{API}/keys/someone", headers=as_first).status_code == 200
        second = client.post(f"{API}/keys", json={"role": "admin", "name": "second"}, headers=as_first).json()
        as_second = {"Authorization": f"Bearer {second['key']}"}
        assert client.delete(f"{API}/keys/first", headers=as_first).status_code == 200  # another remains
        assert client.delete(f"{API}/keys/second", headers=as_second).status_code == 409
        assert client.get(f"{API}/keys", headers=as_second).status_code == 200
    assert access.authenticate(store, viewer) is None
    # The command line obeys the same rule: exit 2 and one line.
    refused_cli = hdrig(store.home, "keys", "revoke", "second")
    assert refused_cli.returncode == 2 and "last live admin key" in refused_cli.stderr
    assert len(refused_cli.stderr.strip().splitlines()) == 1


def test_every_key_change_from_every_door_is_in_the_audit_log(store: RunStore, tmp_path: Path) -> None:
    made = hdrig(store.home, "keys", "create", "--role", "admin", "--name", "cli-admin")
    assert made.returncode == 0, made.stderr
    assert hdrig(store.home, "keys", "create", "--role", "viewer", "--name", "cli-viewer").returncode == 0
    assert hdrig(store.home, "keys", "revoke", "cli-viewer").returncode == 0
    with service(store) as client:
        admin = {"Authorization": f"Bearer {made.stdout.strip()}"}
        assert client.post(f"{API}/keys", json={"role": "viewer", "name": "api-v"}, headers=admin).is_success
        assert client.delete(f"{API}/keys/api-v", headers=admin).is_success
    lines = [(e.who, e.action, e.target) for e in access.audit_log(store)]
    assert lines == [
        (None, "key.create", "cli-admin"),
        (None, "key.create", "cli-viewer"),
        (None, "key.revoke", "cli-viewer"),
        ("cli-admin", "key.create", "api-v"),
        ("cli-admin", "key.revoke", "api-v"),
    ]


def test_the_first_start_admin_key_is_in_the_audit_log(tmp_path: Path) -> None:
    # `hdrig serve`'s first start on a store without keys, up to the point it would serve: the same code
    # path, with uvicorn.run replaced by nothing (the service itself is tested in test_api_server).
    script = (
        "import sys, uvicorn; uvicorn.run = lambda *a, **k: None\n"
        "uvicorn.Server.run = lambda self, *a, **k: None\n"
        "from rig.cli import main\n"
        "sys.exit(main(['serve', '--rig', 'configs/rigs/sim.yaml', '--port', '1']))\n"
    )
    env = dict(os.environ, HDRIG_HOME=str(tmp_path / "home"))
    env.pop("HDRIG_CATALOG", None)
    ran = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, env=env, cwd=REPO, timeout=300
    )
    store = RunStore(tmp_path / "home")
    assert access.audit_log(store), ran.stderr[-2000:]
    (line,) = access.audit_log(store)
    assert (line.who, line.action, line.target) == (None, "key.create", "admin")
    assert "first start" in (line.detail or "")
