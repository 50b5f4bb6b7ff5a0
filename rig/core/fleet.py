"""A lab's fleet: batch identification of many gear units on a Dask cluster, and the fleet report.

`hdrig fit --data 'unit=HD25-*' --batch [--scheduler ADDRESS]`: the selectors (`unit=`, `rig=`, `tag=`,
each exact or a glob, all of them together) pick complete runs from the catalog; each unit's newest
complete run of each experiment is fitted as `hdrig fit` fits them (`actions.fit`), one unit per Dask
task, on a LocalCluster of this machine by default or on the cluster at a scheduler address (whose
workers reach the same catalog and data: a database URL and object storage, not a local SQLite file).
Each unit's result goes into the catalog (table `unit_fits`) as it lands.

The report sets each unit's parameters against the fleet: per parameter the median and spread, and a
unit is flagged an outlier when it lies more than OUTLIER_Z robust deviations from the median (Iglewicz
and Hoaglin's cut-off for the modified z-score). The robust deviation is 1.4826 × the median absolute
deviation (the standard deviation for normal data), but never less than the median of the units' own 1σ:
units that agree better than their fits can tell are not told apart by noise. Trends per unit come from
the endurance checkpoints (`rig.core.trend`): each estimate's slope against time, by weighted least squares.
"""

from __future__ import annotations

import json
import logging
import math
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import sqlalchemy as sa
from pydantic import Field

from model.errors import UserInputError
from rig.core import actions
from rig.core.documents import Document
from rig.core.trend import trend_document
from rig.status import RunStatus
from rig.store.catalog import unit_fits
from rig.store.runfile import json_text
from rig.store.runs import RunStore, new_run_id

logger = logging.getLogger(__name__)

OUTLIER_Z = 3.5
MAD_TO_SIGMA = 1.4826  # the MAD of normal data times this is its standard deviation
SELECTOR = re.compile(r"(unit|rig|tag)=(.+)")
FLEET_FILE = "fleet.json"
REPORT_FILE = "fleet.md"

Progress = Callable[[str, float], None]


class UnitParameter(Document):
    estimate: float = Field(description="the unit's fitted model's value")
    uncertainty: float | None = Field(description="1 σ from the unit's fit; None when not determined")
    determined: bool = Field(description="the unit's data determined it (else the start value was kept)")
    z: float | None = Field(default=None, description="(estimate − fleet median) / robust deviation")
    outlier: bool = False


class UnitResult(Document):
    unit: str
    status: str = Field(description="complete, or failed (`error` says why)")
    runs: list[str] = Field(description="the run ids fitted")
    parameters: dict[str, UnitParameter] = Field(default_factory=dict, description="every parameter fitted")
    error: str | None = None
    analysis: str | None = Field(default=None, description="the unit's fit folder (result.json, model.yaml)")


class ParameterSpread(Document):
    units: int
    median: float
    robust_deviation: float = Field(description="max(1.4826·MAD, the median of the units' 1σ)")
    mean: float
    std: float
    minimum: float
    maximum: float
    outliers: list[str] = Field(description="units beyond OUTLIER_Z robust deviations of the median")


class TrendSlope(Document):
    estimate: str = Field(description="coulomb, viscous or stiffness (the endurance checkpoints' estimates)")
    per_hour: float = Field(description="slope against time, in the estimate's unit per hour")
    sigma_per_hour: float | None
    first: float
    last: float
    points: int


class FleetDocument(Document):
    """`hdrig fit --batch --json`: every unit's fit, each parameter across the fleet, trends per unit."""

    batch_id: str
    model: str = Field(description="the starting model every unit's fit began from")
    selectors: list[str]
    units: list[UnitResult]
    spread: dict[str, ParameterSpread] = Field(
        description="per parameter some unit's data determined, over the units fitted (two or more)"
    )
    trends: dict[str, list[TrendSlope]] = Field(description="per unit with endurance checkpoints")
    outlier_z: float = OUTLIER_Z
    folder: str | None = None
    report: str | None = Field(default=None, description="fleet.md, the report as a table")


@dataclass(frozen=True)
class StoreAddress:
    """What a worker needs to open the same store: its home, catalog URL and data root."""

    home: str
    catalog: str
    data: str

    @classmethod
    def of(cls, store: RunStore) -> StoreAddress:
        return cls(str(store.home), store.catalog.url.render_as_string(hide_password=False), store.data.url)

    def open(self) -> RunStore:
        return RunStore(self.home, catalog=self.catalog, data=self.data)


def select_units(store: RunStore, selectors: Sequence[str]) -> dict[str, list[str]]:
    """unit → its newest complete run of each experiment, for the runs every selector picks."""
    filters: dict[str, Any] = {"tags": []}
    for selector in selectors:
        match = SELECTOR.fullmatch(selector)
        if match is None:
            raise UserInputError(
                f"--data {selector!r}: with --batch, name runs by unit=PATTERN, rig=PATTERN or tag=PATTERN"
            )
        key, value = match.groups()
        if key == "tag":
            filters["tags"].append(value)
        elif key in filters:
            raise UserInputError(f"--data: {key}= given twice")
        else:
            filters[key] = value
    newest: dict[str, dict[str, str]] = {}
    for entry in store.list_runs(status=RunStatus.COMPLETE.value, **filters):
        if entry["unit"]:
            newest.setdefault(entry["unit"], {})[entry["experiment"]] = entry[
                "id"
            ]  # oldest first: newest wins
    if not newest:
        raise UserInputError(
            f"--data {' '.join(selectors)}: no complete run of a gear unit in {store.catalog.where}"
        )
    return {unit: list(runs.values()) for unit, runs in sorted(newest.items())}


def fit_unit(
    address: StoreAddress, batch_id: str, unit: str, run_ids: list[str], model: str, joint: bool
) -> dict[str, Any]:
    """One unit's fit (a Dask task): `actions.fit` on its runs, the result put in the catalog."""
    store = address.open()
    analysis_id = f"{batch_id}-{re.sub(r'[^A-Za-z0-9._-]+', '_', unit)}"
    result = UnitResult(unit=unit, status="complete", runs=run_ids)
    document = None
    try:
        document = actions.fit(run_ids, model, store, joint=joint, analysis_id=analysis_id)
    except UserInputError as exc:  # this unit's data cannot be fitted: said, and the batch goes on
        result.status, result.error = "failed", str(exc)
    else:
        result.analysis = document.folder
        # Every parameter's fitted value (the start's where the data did not determine it, or where the
        # start was no worse on held-out windows); the report compares those some unit's data determined.
        result.parameters = {
            name: UnitParameter(estimate=p.estimate, uncertainty=p.uncertainty, determined=p.identifiable)
            for name, p in document.parameters.items()
        }
    with store.catalog.write() as db:
        db.execute(sa.delete(unit_fits).where(unit_fits.c.batch_id == batch_id, unit_fits.c.unit == unit))
        db.execute(
            unit_fits.insert().values(
                batch_id=batch_id,
                unit=unit,
                created=datetime.now(UTC).isoformat(timespec="milliseconds"),
                status=result.status,
                runs=json.dumps(run_ids),
                result=None if document is None else json_text(document.as_json()),
                error=result.error,
            )
        )
    return result.as_json()


def _client(scheduler: str | None, workers: int | None) -> Any:
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise UserInputError("--batch needs Dask: pip install 'hdrig[fleet]'") from None
    if scheduler is not None:
        try:
            return Client(scheduler, timeout="10s")
        except OSError as exc:
            raise UserInputError(f"--scheduler {scheduler}: no Dask scheduler there ({exc})") from None
    # One process per worker and one thread each: a fit is numpy and numba work that holds the GIL.
    cluster = LocalCluster(
        n_workers=workers or None,
        threads_per_worker=1,
        processes=True,
        host="127.0.0.1",
        dashboard_address=None,
    )
    return Client(cluster)


def batch_fit(
    store: RunStore,
    selectors: Sequence[str],
    model: str,
    scheduler: str | None = None,
    workers: int | None = None,
    joint: bool = True,
    progress: Progress | None = None,
    client: Any = None,
) -> FleetDocument:
    """Fit every selected unit on a Dask cluster and report the fleet (see the module doc).

    `client`: a Dask client to use (else one on `scheduler`, else a LocalCluster of `workers` processes,
    one per core by default, closed at the end)."""
    units = select_units(store, selectors)
    if store.catalog.is_sqlite and scheduler is not None:
        raise UserInputError(
            f"--scheduler: the workers of a cluster cannot share the SQLite catalog {store.catalog.where};"
            " put the catalog on a database (HDRIG_CATALOG) and the data on shared storage (HDRIG_DATA)"
        )
    batch_id = new_run_id("fleet-fit")
    address = StoreAddress.of(store)
    own = client is None
    if own:
        client = _client(scheduler, workers)
    try:
        from distributed import as_completed

        futures = [
            client.submit(fit_unit, address, batch_id, unit, runs, model, joint, key=f"fit-{batch_id}-{unit}")
            for unit, runs in units.items()
        ]
        results: list[UnitResult] = []
        for done, future in enumerate(as_completed(futures), 1):
            results.append(UnitResult.model_validate(future.result()))  # a bug on a worker is raised here
            if progress is not None:
                progress(f"fit {results[-1].unit}", done / len(futures))
    finally:
        if own:
            cluster = client.cluster
            client.close()
            if cluster is not None:
                cluster.close()
    results.sort(key=lambda r: r.unit)
    document = fleet_report(store, batch_id, model, list(selectors), results)
    folder = store.home / actions.ANALYSES_DIR / batch_id
    folder.mkdir(parents=True, exist_ok=True)
    document.folder = str(folder)
    document.report = str(folder / REPORT_FILE)
    (folder / REPORT_FILE).write_text(report_markdown(document))
    (folder / FLEET_FILE).write_text(json_text(document.as_json(), indent=2) + "\n")
    return document


def spread_of(
    values: dict[str, float], sigmas: dict[str, float | None]
) -> tuple[ParameterSpread, dict[str, float]]:
    """One parameter across units: its spread, and each unit's robust z."""
    x = np.array(list(values.values()))
    median = float(np.median(x))
    mad = float(np.median(np.abs(x - median)))
    own = [s for s in sigmas.values() if s is not None and math.isfinite(s)]
    floor = float(np.median(own)) if own else 0.0
    scale = max(MAD_TO_SIGMA * mad, floor, 1e-12 * max(abs(median), 1.0))
    z = {unit: (value - median) / scale for unit, value in values.items()}
    spread = ParameterSpread(
        units=len(x),
        median=median,
        robust_deviation=scale,
        mean=float(np.mean(x)),
        std=float(np.std(x, ddof=1)) if len(x) > 1 else 0.0,
        minimum=float(np.min(x)),
        maximum=float(np.max(x)),
        outliers=[unit for unit, value in z.items() if abs(value) > OUTLIER_Z],
    )
    return spread, z


def _slopes(store: RunStore, unit: str) -> list[TrendSlope]:
    try:
        trend = trend_document(store, unit=unit)
    except UserInputError:  # no endurance checkpoints for this unit
        return []
    t_h = np.array([p.time_s for p in trend.points]) / 3600.0
    slopes = []
    for name in ("coulomb", "viscous", "stiffness"):
        y = np.array([getattr(p, f"{name}_estimate") for p in trend.points])
        sigma = np.array([getattr(p, f"{name}_sigma") for p in trend.points])
        keep = np.isfinite(y)
        if keep.sum() < 2 or np.ptp(t_h[keep]) == 0:
            continue
        usable = keep & np.isfinite(sigma) & (sigma > 0)
        w = 1.0 / sigma[usable] ** 2 if usable.sum() == keep.sum() else np.ones(keep.sum())
        tk, yk = t_h[keep], y[keep]
        design = np.column_stack([np.ones_like(tk), tk]) * np.sqrt(w)[:, None]
        coef, *_ = np.linalg.lstsq(design, yk * np.sqrt(w), rcond=None)
        cov = np.linalg.inv(design.T @ design) if usable.sum() == keep.sum() else None
        slopes.append(
            TrendSlope(
                estimate=name,
                per_hour=float(coef[1]),
                sigma_per_hour=float(math.sqrt(cov[1, 1])) if cov is not None else None,
                first=float(yk[0]),
                last=float(yk[-1]),
                points=int(keep.sum()),
            )
        )
    return slopes


def fleet_report(
    store: RunStore, batch_id: str, model: str, selectors: list[str], results: list[UnitResult]
) -> FleetDocument:
    """Each parameter across the units fitted, each unit's robust z against it, trends per unit."""
    spread: dict[str, ParameterSpread] = {}
    names = sorted({name for r in results for name, p in r.parameters.items() if p.determined})
    for name in names:
        having = [r for r in results if name in r.parameters]
        if len(having) < 2:
            continue
        values = {r.unit: r.parameters[name].estimate for r in having}
        sigmas = {r.unit: r.parameters[name].uncertainty for r in having}
        spread[name], z = spread_of(values, sigmas)
        for r in having:
            r.parameters[name].z = z[r.unit]
            r.parameters[name].outlier = r.unit in spread[name].outliers
    trends = {r.unit: slopes for r in results if (slopes := _slopes(store, r.unit))}
    return FleetDocument(
        batch_id=batch_id, model=model, selectors=selectors, units=results, spread=spread, trends=trends
    )


def report_markdown(document: FleetDocument) -> str:
    """The fleet report as Markdown: each parameter's spread, each unit against it, the trends."""
    lines = [f"# Fleet report {document.batch_id}", "", f"Units: {len(document.units)}; runs selected by "
             f"{' '.join(document.selectors)}; starting model {document.model}.", ""]  # fmt: skip
    lines += [
        "| parameter | units | median | robust σ | min | max | outliers |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, s in document.spread.items():
        lines.append(
            f"| {name} | {s.units} | {s.median:.6g} | {s.robust_deviation:.3g} | {s.minimum:.6g} |"
            f" {s.maximum:.6g} | {', '.join(s.outliers) or '-'} |"
        )
    lines += [
        "",
        "| unit | status | parameter | estimate | ±1σ | z | outlier |",
        "|---|---|---|---|---|---|---|",
    ]
    for unit in document.units:
        if unit.status != "complete":
            lines.append(f"| {unit.unit} | failed: {unit.error} | | | | | |")
        for name, p in unit.parameters.items():
            if name not in document.spread:
                continue
            sigma = f"{p.uncertainty:.3g}" if p.uncertainty is not None else "-"
            z = f"{p.z:+.2f}" if p.z is not None else "-"
            lines.append(
                f"| {unit.unit} | {unit.status} | {name} | {p.estimate:.6g} | {sigma} | {z} |"
                f" {'**yes**' if p.outlier else ''} |"
            )
    if document.trends:
        lines += [
            "",
            "| unit | estimate | per hour | ±1σ | first | last | checkpoints |",
            "|---|---|---|---|---|---|---|",
        ]
        for unit_name, slopes in document.trends.items():
            for t in slopes:
                sigma = f"{t.sigma_per_hour:.3g}" if t.sigma_per_hour is not None else "-"
                lines.append(
                    f"| {unit_name} | {t.estimate} | {t.per_hour:.4g} | {sigma} | {t.first:.6g} |"
                    f" {t.last:.6g} | {t.points} |"
                )
    return "\n".join(lines) + "\n"


def unit_results(store: RunStore, unit: str) -> list[dict[str, Any]]:
    """Every batch fit of a unit in the catalog, oldest first: batch id, when, status, runs, the fit."""
    query = sa.select(unit_fits).where(unit_fits.c.unit == unit).order_by(unit_fits.c.created)
    with store.catalog.read() as db:
        rows = [dict(r._mapping) for r in db.execute(query)]
    for row in rows:
        row["runs"] = json.loads(row["runs"])
        row["result"] = json.loads(row["result"]) if row["result"] else None
    return rows


def is_batch(data: Sequence[str]) -> bool:
    """Whether `--data` names runs by selectors (`unit=...`) rather than ids, files or `latest`."""
    return bool(data) and all(SELECTOR.fullmatch(d) and not Path(d).exists() for d in data)
