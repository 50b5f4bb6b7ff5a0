"""The run list in pages: the catalog (SQLite and PostgreSQL), the core, REST (`GET /runs?limit=&cursor=`
with `Link` and `X-Total-Count`), the client and `hdrig runs list --limit/--all`.

Pages go from the newest run to the oldest by (`started`, `id`), each oldest first. The promise checked
here: a walk lists every run that was in the catalog when it began exactly once, in order, however many
runs are added between its pages, and `started` ties (runs of one millisecond) are cut by id.
"""

from __future__ import annotations

import json
import sqlite3
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import sqlalchemy as sa
from fastapi.testclient import TestClient

from api.app import create_app
from api.client import HdrigClient
from model.errors import UserInputError
from rig import cli
from rig.config import load_rig_config
from rig.core import access, actions
from rig.store import catalog as tables
from rig.store.catalog import DEFAULT_PAGE, MAX_PAGE, Cursor, head_revision
from rig.store.runs import RunStore

API = "/api/v1"
EPOCH = datetime(2026, 3, 1, tzinfo=UTC)
RUN_KEYS = {"id", "experiment", "status", "started", "samples"}  # ../shared/CONTRACT.md's list fields


def add_runs(store: RunStore, first: int, count: int, per_ms: int = 3, **fields: Any) -> list[str]:
    """`count` complete runs numbered from `first`, `per_ms` of them sharing each `started` (a tie that
    only the id orders), one bulk insert; their ids, oldest first."""
    rows = []
    for n in range(first, first + count):
        started = (EPOCH + timedelta(milliseconds=n // per_ms)).isoformat(timespec="milliseconds")
        # ids not in `started` order within a tie (the suffix runs backwards): the order must come from
        # the key (started, id), not from insertion
        run_id = f"r{n // per_ms:06d}-{per_ms - n % per_ms:02d}"
        row = {"id": run_id, "experiment": "pulse", "rig": "bench", "status": "complete", "started": started,
               "samples": n, "metrics": json.dumps({"n": n}), "path": f"runs/{run_id}",
               "meta": json.dumps({"params": {"n": n}})}  # fmt: skip
        rows.append(row | {k: (v(n) if callable(v) else v) for k, v in fields.items()})
    with store.catalog.write() as db:
        db.execute(tables.runs.insert(), rows)
    return [r["id"] for r in sorted(rows, key=lambda r: (r["started"], r["id"]))]


def walk(store: RunStore, limit: int, between: Any = None, **filters: Any) -> tuple[list[str], list[int]]:
    """Every page from the newest, calling `between(k)` after page k: the ids oldest first, and each
    page's `total`."""
    pages: list[list[str]] = []
    totals: list[int] = []
    cursor = None
    while True:
        page = actions.list_runs(store, limit=limit, cursor=cursor, **filters)
        ids = [r.id for r in page.runs]
        starts = [(r.started, r.id) for r in page.runs]
        assert starts == sorted(starts), "a page is oldest first"
        assert len(ids) <= limit
        pages.append(ids)
        totals.append(page.total)
        if page.next_cursor is None:
            break
        assert len(ids) == limit, "only the last page is short"
        cursor = page.next_cursor
        if between is not None:
            between(len(pages))
    return [i for ids in reversed(pages) for i in ids], totals


@pytest.fixture(params=["sqlite", "postgresql"])
def store(request: pytest.FixtureRequest, tmp_path: Path) -> RunStore:
    if request.param == "sqlite":
        return RunStore(tmp_path / "home", catalog=f"sqlite:///{tmp_path / 'catalog.sqlite'}")
    return RunStore(tmp_path / "home", catalog=request.getfixturevalue("pg_url"))


def test_a_walk_lists_every_run_once_in_order_while_runs_are_added(store: RunStore) -> None:
    before = add_runs(store, 0, 61)  # 61 = 8 pages of 7 and 5, cutting through ties of 3

    added: list[str] = []

    def more(k: int) -> None:  # newer runs land between pages: bulk ones, and a real one every 3rd page
        added.extend(add_runs(store, 1000 + 10 * k, 2))
        if k % 3 == 0:
            with store.open_run("step", "bench", None, None, ["t"], {}) as writer:
                writer.append({"t": np.arange(3) / 1e3})
            added.append(writer.run_id)

    ids, totals = walk(store, 7, between=more)
    assert ids == before  # none skipped, none repeated, oldest first
    assert len(added) == 2 * 8 + 2  # 9 pages: 8 gaps between them, a real run after pages 3 and 6
    # each page counts the catalog as it is then: the first 61, then 2 (or 3) more a page
    assert totals[0] == 61 and totals == sorted(totals) and totals[-1] == 61 + len(added)
    newest = actions.list_runs(store, limit=len(added))
    assert {r.id for r in newest.runs} == set(added)  # the next walk starts with them


def test_a_page_is_a_summary_with_tags_and_a_cursor_is_a_position(store: RunStore) -> None:
    ids = add_runs(store, 0, 10, per_ms=1, unit=lambda n: f"HD25-{n % 2:04d}")
    with store.catalog.write() as db:
        db.execute(
            tables.run_tags.insert(), [{"run_id": ids[8], "tag": "line=1"}, {"run_id": ids[8], "tag": "a"}]
        )
    page = actions.list_runs(store, limit=3)
    assert [r.id for r in page.runs] == ids[7:] and page.total == 10
    assert [r.tags for r in page.runs] == [[], ["a", "line=1"], []]
    assert [r.metrics for r in page.runs] == [{"n": 7}, {"n": 8}, {"n": 9}]
    assert all(r.meta == {} and r.artifacts == [] for r in page.runs)  # no metadata decoded for a list
    assert actions.run_document(store, ids[8]).meta == {"params": {"n": 8}}  # one run's document has it
    assert Cursor.decode(str(page.next_cursor)) == Cursor(page.runs[0].started or "", ids[7])
    assert [r.id for r in actions.list_runs(store, limit=None).runs] == ids
    last = actions.list_runs(store, limit=10)
    assert last.next_cursor is None and len(last.runs) == 10


def test_filters_select_before_paging_and_count_what_they_select(store: RunStore) -> None:
    ids = add_runs(
        store, 0, 40, per_ms=2,
        unit=lambda n: f"HD25-{n % 4:04d}", experiment=lambda n: ("pulse", "step")[n % 3 == 0],
        status=lambda n: ("complete", "aborted")[n % 5 == 0],
    )  # fmt: skip
    with store.catalog.write() as db:
        db.execute(tables.run_tags.insert(), [{"run_id": i, "tag": "line=1"} for i in ids[::2]])
    rows = {r["id"]: r for r in _rows(store)}
    cases: list[tuple[dict[str, Any], Any]] = [
        ({"unit": "HD25-0001"}, lambda r: r["unit"] == "HD25-0001"),
        ({"experiment": "st*"}, lambda r: r["experiment"] == "step"),
        ({"status": "aborted"}, lambda r: r["status"] == "aborted"),
        ({"tags": ["line=1"], "unit": "HD25-000?"}, lambda r: r["id"] in ids[::2]),
        ({"tags": ["line=1"], "status": "complete", "experiment": "pulse"},
         lambda r: r["id"] in ids[::2] and r["status"] == "complete" and r["experiment"] == "pulse"),
    ]  # fmt: skip
    for filters, wanted in cases:
        expected = [i for i in ids if wanted(rows[i])]
        found, totals = walk(store, 3, **filters)
        assert found == expected, filters
        assert set(totals) == {len(expected)}, filters


def _rows(store: RunStore) -> list[dict[str, Any]]:
    with store.catalog.read() as db:
        return [dict(r._mapping) for r in db.execute(sa.select(tables.runs))]


def run_of(store: RunStore, run_id: str) -> dict[str, Any]:
    return next(r for r in _rows(store) if r["id"] == run_id)


def test_a_bad_limit_or_cursor_is_one_line_naming_it(tmp_path: Path) -> None:
    store = RunStore(tmp_path / "home")
    for limit in (0, -1):
        with pytest.raises(UserInputError, match=rf"^limit {limit}: a page holds at least 1 run$"):
            actions.list_runs(store, limit=limit)
    not_ours = ["garbage!", "e30", "WyJhIl0", "WzEsMl0"]  # not base64; {}; ["a"]; [1,2]
    for cursor in not_ours:
        with pytest.raises(UserInputError, match=r"^cursor '.*': not a cursor of this catalog") as bad:
            actions.list_runs(store, cursor=cursor)
        assert "\n" not in str(bad.value)


def test_a_catalog_of_the_previous_schema_is_upgraded_in_place_and_pages(tmp_path: Path) -> None:
    from alembic import command

    path = tmp_path / "home" / "catalog.sqlite"
    path.parent.mkdir()
    engine = sa.create_engine(f"sqlite:///{path}")
    with engine.begin() as conn:  # the catalog as the fleet's code left it (revision 0002)
        config = tables._alembic_config()
        config.attributes["connection"] = conn
        command.upgrade(config, "0002")
        conn.execute(
            tables.runs.insert(),
            [{"id": f"old-{n}", "experiment": "pulse", "rig": "sim", "status": "complete",
              "started": f"2025-01-01T00:00:0{n}.000+00:00", "samples": n, "path": f"runs/old-{n}",
              "meta": '{"kept": true}'} for n in range(5)],
        )  # fmt: skip
    engine.dispose()
    store = RunStore(tmp_path / "home")
    with sqlite3.connect(path) as db:
        assert db.execute("SELECT version_num FROM alembic_version").fetchall() == [(head_revision(),)]
        indexes = {row[1] for row in db.execute("PRAGMA index_list(runs)")}
    assert "runs_started_id" in indexes and "runs_started" not in indexes
    page = actions.list_runs(store, limit=2)
    assert [r.id for r in page.runs] == ["old-3", "old-4"] and page.total == 5
    rest = actions.list_runs(store, limit=5, cursor=page.next_cursor)
    assert [r.id for r in rest.runs] == ["old-0", "old-1", "old-2"] and rest.next_cursor is None
    assert store.get("old-0")["meta"] == {"kept": True}  # nothing lost on the way


def test_a_deep_page_is_a_seek_on_the_index_not_a_sort(tmp_path: Path) -> None:
    """SQLite's plan for the page query: the (started, id) index, no temporary B-tree sorting all runs
    before the cursor (which is what made a deep page cost as much as the whole list)."""
    store = RunStore(tmp_path / "home")
    ids = add_runs(store, 0, 500)
    cursor = actions.list_runs(store, limit=400).next_cursor
    statements: list[tuple[str, Any]] = []

    def seen(conn: Any, cursor_: Any, statement: str, parameters: Any, context: Any, many: bool) -> None:
        if statement.lstrip().upper().startswith("SELECT"):
            statements.append((statement, parameters))

    sa.event.listen(store.catalog.engine, "before_cursor_execute", seen)
    try:
        page = actions.list_runs(store, limit=50, cursor=cursor)
    finally:
        sa.event.remove(store.catalog.engine, "before_cursor_execute", seen)
    assert [r.id for r in page.runs] == ids[50:100]
    statement, parameters = statements[0]  # the page itself (then its tags, then the count)
    assert "ORDER BY" in statement and "LIMIT" in statement
    with sqlite3.connect(str(store.catalog_path)) as db:
        plan = " | ".join(row[-1] for row in db.execute(f"EXPLAIN QUERY PLAN {statement}", parameters))
    assert "runs_started_id" in plan and "TEMP B-TREE" not in plan, plan


# ---- REST and the client ---------------------------------------------------------------------------


@pytest.fixture
def service(tmp_path: Path) -> Iterator[tuple[TestClient, RunStore]]:
    store = RunStore(tmp_path / "home")
    token = access.create_key(store, "viewer", "reader")
    with TestClient(create_app(load_rig_config("configs/rigs/sim.yaml"), store)) as client:
        client.headers["Authorization"] = f"Bearer {token}"
        yield client, store


def test_rest_pages_follow_link_while_runs_are_added(service: tuple[TestClient, RunStore]) -> None:
    client, store = service
    ids = add_runs(store, 0, 25, experiment=lambda n: ("pulse", "step")[n % 2])
    first = client.get(f"{API}/runs", params={"limit": 10})
    assert first.status_code == 200, first.text
    assert [r["id"] for r in first.json()] == ids[-10:]  # the newest page, oldest first as before
    assert first.headers["X-Total-Count"] == "25"
    assert all(set(r) >= RUN_KEYS for r in first.json())
    seen, answer, k = [first.json()], first, 0
    while "next" in answer.links:
        k += 1
        add_runs(store, 100 + 10 * k, 3)  # newer runs between pages
        answer = client.get(answer.links["next"]["url"])
        assert answer.status_code == 200, answer.text
        assert answer.headers["X-Total-Count"] == str(25 + 3 * k)
        seen.append(answer.json())
    assert k == 2 and [r["id"] for page in reversed(seen) for r in page] == ids
    # the Link keeps the filters: a walk of one experiment stays in it
    steps = [i for i in ids if run_of(store, i)["experiment"] == "step"]
    page = client.get(f"{API}/runs", params={"experiment": "step", "limit": 5})
    assert "experiment=step" in page.links["next"]["url"]
    following = client.get(page.links["next"]["url"]).json()
    assert [r["id"] for r in following + page.json()] == steps[-10:]
    assert page.headers["X-Total-Count"] == str(len(steps))


@pytest.mark.parametrize(
    ("query", "field"),
    [
        ({"limit": 0}, "query.limit"),
        ({"limit": MAX_PAGE + 1}, "query.limit"),
        ({"limit": "ten"}, "query.limit"),
        ({"status": "lost"}, "query.status"),
    ],
)
def test_rest_bad_paging_is_422_naming_the_field(
    service: tuple[TestClient, RunStore], query: dict[str, Any], field: str
) -> None:
    client, _ = service
    answer = client.get(f"{API}/runs", params=query)
    assert answer.status_code == 422 and answer.headers["content-type"].startswith("application/problem+json")
    body = answer.json()
    assert body["errors"][0]["field"] == field and body["detail"].startswith(field)


def test_rest_a_cursor_not_given_by_the_service_is_422_naming_it(
    service: tuple[TestClient, RunStore],
) -> None:
    client, _ = service
    answer = client.get(f"{API}/runs", params={"cursor": "not-a-cursor"})
    assert answer.status_code == 422 and answer.json()["detail"].startswith("cursor 'not-a-cursor'")


def test_the_client_walks_pages_for_more_than_one_answer_holds(service: tuple[TestClient, RunStore]) -> None:
    test_client, store = service
    ids = add_runs(store, 0, MAX_PAGE + 205, per_ms=4)
    client = HdrigClient("http://testserver", None)
    client._http = test_client  # the service in this process; the client's requests as over the wire
    page = client.runs_page()
    assert [r.id for r in page.runs] == ids[-DEFAULT_PAGE:] and page.total == len(ids)
    newest = client.newest_runs(limit=MAX_PAGE + 100)  # two requests: 1000, then 100
    assert [r.id for r in newest.runs] == ids[-(MAX_PAGE + 100) :] and newest.next_cursor is not None
    rest = client.runs_page(limit=MAX_PAGE, cursor=newest.next_cursor)
    assert [r.id for r in rest.runs] == ids[:105] and rest.next_cursor is None
    assert [r.id for r in client.runs()] == ids  # every run, oldest first, as before paging


# ---- the command line ------------------------------------------------------------------------------


def listing(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[list[str], str]:
    """`hdrig runs list ARGS` in this process: stdout's lines, stderr."""
    capsys.readouterr()
    assert cli.main(["runs", "list", *args]) == 0
    out, err = capsys.readouterr()
    return out.splitlines(), err


def test_runs_list_shows_the_newest_page_and_says_how_many_more(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    home = tmp_path / "home"
    monkeypatch.setenv("HDRIG_HOME", str(home))
    monkeypatch.delenv("HDRIG_CATALOG", raising=False)
    monkeypatch.delenv("HDRIG_DATA", raising=False)
    ids = add_runs(RunStore(home), 0, DEFAULT_PAGE + 7, status=lambda n: ("complete", "aborted")[n == 3])
    lines, err = listing(capsys)
    assert lines[0].split()[:3] == ["id", "experiment", "status"]
    assert [line.split()[0] for line in lines[1:]] == ids[-DEFAULT_PAGE:]  # newest last, by the prompt
    assert f"the newest {DEFAULT_PAGE} of {DEFAULT_PAGE + 7} runs in {home}; 7 older not shown" in err
    lines, err = listing(capsys, "--limit", "3")
    assert [line.split()[0] for line in lines[1:]] == ids[-3:]
    assert f"{DEFAULT_PAGE + 4} older not shown (--limit N, or --all)" in err
    lines, err = listing(capsys, "--all")
    assert [line.split()[0] for line in lines[1:]] == ids and err.strip() == f"{len(ids)} runs in {home}"
    lines, err = listing(capsys, "--json", "--limit", "2")
    documents = json.loads("\n".join(lines))
    assert [d["id"] for d in documents] == ids[-2:] and all(set(d) >= RUN_KEYS for d in documents)
    lines, err = listing(capsys, "--status", "aborted")
    aborted = next(i for i in ids if run_of(RunStore(home), i)["samples"] == 3)  # run n = 3
    assert [line.split()[0] for line in lines[1:]] == [aborted] and err.strip() == f"1 run in {home}"
    lines, err = listing(capsys, "--experiment", "step")
    assert lines == [] and err.strip() == f"no runs in {home}"


@pytest.mark.parametrize("limit", ["0", "-2", "many"])
def test_runs_list_refuses_a_limit_that_is_no_count_in_one_line(
    limit: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as stop:
        cli.main(["runs", "list", "--limit", limit])
    err = capsys.readouterr().err
    assert stop.value.code == 2 and err.count("\n") == 1 and "argument --limit" in err
