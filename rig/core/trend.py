"""Trends of a gear over its life: the checkpoint estimates of endurance runs against time and duty cycles,
for one run or every run of one gear unit (the rig file's `unit:`), with the online tracker's level beside.

Reads only the catalog (table `checkpoints`) and each run's metadata (`observed`): no samples.

Warm-up and wear (issue 27 item 6): friction falls as the gear's grease warms and rises as the gear wears,
so a raw trend mixes the two. Given the friction's temperature law (a model's `thermal` section: friction
× exp(−beta_T·(T_g − T_ref)), identified from `warm-up` runs), each checkpoint that recorded the gear's
temperature is also brought to T_ref: (F_c − u)·exp(beta_T·(T_g − T_ref)) + u, shown beside the raw F_c,
u the share the law does not scale (the output side's friction seen at the motor).
"""

from __future__ import annotations

import math
from datetime import datetime
from pathlib import Path

from model.errors import UserInputError
from model.params import Thermal
from rig.core.documents import TrackPoint, TrendDocument, TrendPoint
from rig.experiments.plots import new_figure, save_figure
from rig.store.runs import RunStore

_ESTIMATES = ("coulomb", "viscous", "stiffness")


def normalized_friction(
    coulomb_nm: float, sigma_nm: float, temp_gear_c: float, law: Thermal, unscaled_nm: float = 0.0
) -> tuple[float, float]:
    """A friction level measured at the gear temperature `temp_gear_c`, brought to the law's T_ref, with
    its σ scaled alike: (F − u)·exp(beta_T·(T_g − T_ref)) + u [N·m]. `unscaled_nm` (u): the share of F
    the law does not scale, the output side's friction seen at the motor (docs/MODEL.md: the law is the
    motor friction's)."""
    factor = math.exp(law.beta_T * (temp_gear_c - law.T_ref))
    return (coulomb_nm - unscaled_nm) * factor + unscaled_nm, sigma_nm * factor


def trend_document(
    store: RunStore,
    run_id: str | None = None,
    unit: str | None = None,
    law: Thermal | None = None,
    unscaled_nm: float = 0.0,
) -> TrendDocument:
    """The checkpoints of one run (`run_id`) or of every run of a gear `unit`, oldest first; time is
    counted from the first run's start, so runs of one unit line up on one axis. With `law` (a model's
    thermal section) each checkpoint with a gear temperature also gets its friction at the law's T_ref,
    `unscaled_nm` of it left as measured (`normalized_friction`)."""
    if (run_id is None) == (unit is None):
        raise UserInputError("trend: name one run (RUN) or one gear unit (--unit SERIAL)")
    rows = store.checkpoints(run_id=run_id, unit=unit)
    if not rows:
        what = f"run {run_id}" if run_id is not None else f"unit {unit!r}"
        raise UserInputError(f"trend: {what} has no checkpoints in {store.catalog.where} (run `endurance`)")
    origin = datetime.fromisoformat(rows[0]["started"])
    points, tracks = [], []
    cycles_before = 0.0  # duty cycles of the earlier runs of the unit
    last_run, run_cycles = None, 0.0
    for row in rows:
        if row["run_id"] != last_run:
            cycles_before += run_cycles
            last_run = row["run_id"]
            offset_s = (datetime.fromisoformat(row["started"]) - origin).total_seconds()
            observed = store.get(row["run_id"])["meta"].get("observed", {}).get("track", {})
            tracks += [
                TrackPoint(run_id=row["run_id"], time_s=offset_s + t, level_nm=level)
                for t, level in zip(observed.get("t_s", []), observed.get("level_nm", []), strict=True)
            ]
        run_cycles = float(row.get("duty_cycles") or 0.0)
        thermal: dict[str, float] = {}
        if row.get("temp_gear_c") is not None:
            thermal["temp_gear_c"] = float(row["temp_gear_c"])
            if law is not None:
                value, sigma = normalized_friction(
                    float(row["coulomb_nm"]),
                    float(row["coulomb_sigma_nm"]),
                    thermal["temp_gear_c"],
                    law,
                    unscaled_nm,
                )
                thermal |= {"coulomb_normalized_estimate": value, "coulomb_normalized_sigma": sigma}
        points.append(
            TrendPoint(
                run_id=row["run_id"],
                index=int(row["index"]),
                time_s=offset_s + float(row["t_s"]),
                duty_cycles=cycles_before + run_cycles,
                travel_rad=float(row["travel_rad"]),
                **{f"{name}_{kind}": float(row[key]) for name, kind, key in _fields()},
                **thermal,
            )
        )
    return TrendDocument(
        unit=unit or rows[0]["unit"],
        run_ids=list(dict.fromkeys(r["run_id"] for r in rows)),
        points=points,
        track=tracks,
        t_ref_c=law.T_ref if law is not None else None,
        beta_per_k=law.beta_T if law is not None else None,
    )


def _fields() -> list[tuple[str, str, str]]:
    keys = {
        "coulomb": ("coulomb_nm", "coulomb_sigma_nm"),
        "viscous": ("viscous_nm_s_rad", "viscous_sigma_nm_s_rad"),
        "stiffness": ("stiffness_nm_rad", "stiffness_sigma_nm_rad"),
    }
    return [(n, kind, keys[n][i]) for n in _ESTIMATES for i, kind in enumerate(("estimate", "sigma"))]


def plot_trend(document: TrendDocument, out_dir: Path) -> list[Path]:
    """Friction level and stiffness against time, checkpoints with ±1σ bars and the online level."""
    out_dir.mkdir(parents=True, exist_ok=True)
    hours = [p.time_s / 3600.0 for p in document.points]
    fig, ax = new_figure(f"Friction level over time ({document.unit or ', '.join(document.run_ids)})")
    ax.errorbar(
        hours,
        [p.coulomb_estimate for p in document.points],
        yerr=[p.coulomb_sigma for p in document.points],
        fmt="o",
        capsize=3,
        label="checkpoint fit F_c (±1σ)",
    )
    normalized = [p for p in document.points if p.coulomb_normalized_estimate is not None]
    if normalized:
        ax.errorbar(
            [p.time_s / 3600.0 for p in normalized],
            [p.coulomb_normalized_estimate or math.nan for p in normalized],
            yerr=[p.coulomb_normalized_sigma or math.nan for p in normalized],
            fmt="s",
            capsize=3,
            label=f"F_c at T_ref = {document.t_ref_c:g} °C (thermal law, ±1σ)",
        )
    if document.track:
        ax.plot(
            [p.time_s / 3600.0 for p in document.track],
            [p.level_nm for p in document.track],
            lw=1.0,
            label="online RLS level (duty cycle)",
        )
    ax.set_xlabel("time since the first run's start [h]")
    ax.set_ylabel("friction level [N·m]")
    ax.legend()
    paths = [save_figure(fig, out_dir / "friction_trend.png")]
    fig, ax = new_figure("Stiffness over time")
    ax.errorbar(
        hours,
        [p.stiffness_estimate for p in document.points],
        yerr=[p.stiffness_sigma for p in document.points],
        fmt="o",
        capsize=3,
    )
    ax.set_xlabel("time since the first run's start [h]")
    ax.set_ylabel("K_s [N·m/rad]")
    paths.append(save_figure(fig, out_dir / "stiffness_trend.png"))
    return paths
