"""Long runs in constant memory (`make bench`, issue 13): figures printed beside targets; asserts nothing.

1. `hdrig simulate --model seed --input sine:amp=2,freq=0.5 --dt 1e-4 --rate 10` for 200, 4,000 and
   40,000 s: peak memory (flat) and whole-process speed, against a plain C loop of the same model
   (bench/seed_loop.c, built here with gcc -O2 -march=native) doing the same steps and writing its rows.
   Both are whole processes timed by /usr/bin/time (wall s, CPU s, peak RSS); best of REPEATS each,
   interleaved, since the machine is shared. The C loop's own start-up is ~1 ms; the Python process's
   (interpreter, numpy, numba and its compiled-code cache, pyarrow) is ~0.7 s of CPU, more than the C
   loop's whole 200 s run, so 200 s cannot reach the ratio whatever the loop does. The C loop reads
   model.kernel's parameter vector of the preset, and its final state is compared with the Python run's,
   so both integrate the same model.
2. `hdrig run endurance --rig sim-endurance` for 10 s, 1 h and 10 h of duty (virtual time, a checkpoint
   every 15 min), then `hdrig runs export` as Parquet, CSV and MAT: wall time and peak RSS of each
   process. Then `hdrig trend RUN --json`: each checkpoint's friction level against the drift the plant
   was given (seed-wear: thermal_drift and wear_drift of docs/MODEL.md), in units of its stated σ.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
BIN = Path(sys.executable).parent
REPEATS = 3
SIM_DURATIONS_S = (200.0, 4000.0, 40000.0)
ENDURANCE_HOURS = (10 / 3600, 1.0, 10.0)
SPEED_TARGET = 0.5  # whole-process simulate ≥ 0.5 × the C loop


def timed_cpu(cmd: list[str], env: dict[str, str] | None = None) -> tuple[float, float, float, str]:
    """(wall s, CPU s = user + system, peak RSS MB, stdout) of one process, by /usr/bin/time. On a shared
    machine the CPU time is the steadier figure: waiting for a core counts in the wall time only."""
    out = subprocess.run(
        ["/usr/bin/time", "-f", "%e %U %S %M", *cmd], capture_output=True, text=True, env=env, check=True
    )
    wall, user, system, rss_kb = out.stderr.strip().splitlines()[-1].split()
    return float(wall), float(user) + float(system), float(rss_kb) / 1024.0, out.stdout


def timed(cmd: list[str], env: dict[str, str] | None = None) -> tuple[float, float, str]:
    """(wall s, peak RSS MB, stdout) of one process, by /usr/bin/time."""
    wall, _, rss, stdout = timed_cpu(cmd, env)
    return wall, rss, stdout


def bench_simulate(work: Path) -> None:
    from seed_loop_build import compile_seed_loop

    from model.params import load_model
    from model.plant import kernel_vectors
    from model.registry import FL

    p, flags = kernel_vectors(load_model("seed"))
    params = work / "seed_params.bin"
    p.tofile(params)
    loop = compile_seed_loop(work)
    print("\n## hdrig simulate vs a plain C loop (seed, sine 2 V 0.5 Hz, dt 1e-4 s, 10 Hz output)\n")
    print(
        "| simulated s | steps | hdrig wall s / CPU s | hdrig peak MB | C wall s / CPU s | C peak MB"
        " | hdrig M steps/s | C M steps/s | ratio wall | ratio CPU | target |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for duration in SIM_DURATIONS_S:
        steps = round(duration / 1e-4)
        ours, theirs = [], []
        out = work / "sim.parquet"
        for _ in range(REPEATS):
            ours.append(
                timed_cpu(
                    [
                        str(BIN / "hdrig"),
                        "simulate",
                        "--model",
                        "seed",
                        "--input",
                        "sine:amp=2,freq=0.5",
                        "--dt",
                        "1e-4",
                        "--rate",
                        "10",
                        "--duration",
                        f"{duration:g}",
                        "--out",
                        str(out),
                    ]
                )
            )
            theirs.append(
                timed_cpu(
                    [
                        str(loop),
                        str(params),
                        str(int(flags[FL.HARMONICS])),
                        "2",
                        "0.5",
                        "1e-4",
                        str(steps),
                        "1000",
                        str(work / "c.bin"),
                    ]
                )
            )
        wall, cpu, rss = min(r[0] for r in ours), min(r[1] for r in ours), max(r[2] for r in ours)
        c_wall, c_cpu, c_rss = min(r[0] for r in theirs), min(r[1] for r in theirs), max(r[2] for r in theirs)
        ratio, ratio_cpu = c_wall / wall, c_cpu / cpu
        verdict = "PASS" if ratio >= SPEED_TARGET else "MISS"
        print(
            f"| {duration:,.0f} | {steps:,} | {wall:.2f} / {cpu:.2f} | {rss:.0f} | {c_wall:.2f} / {c_cpu:.2f}"
            f" | {c_rss:.1f} | {steps / wall / 1e6:.1f} | {steps / c_wall / 1e6:.1f} | {ratio:.2f}×"
            f" | {ratio_cpu:.2f}× | ≥ {SPEED_TARGET}× (wall) {verdict} |"
        )
        c_rows = np.fromfile(work / "c.bin").reshape(-1, 6)
        import pyarrow.parquet as pq

        theta = pq.read_table(out, columns=["theta_m"]).column(0).to_numpy()
        print(
            f"<!-- {duration:g} s: max |θ_m(hdrig) − θ_m(C)| ="
            f" {np.max(np.abs(theta - c_rows[:-1, 2])):.1e} rad -->"
        )


def drift_truth(points: list[dict[str, float]]) -> list[float]:
    """Each checkpoint's deviation from the drift given to seed-wear, in units of its σ (see module doc)."""
    from model.params import load_model

    model = load_model("seed-wear")
    assert (
        model.thermal_drift is not None and model.wear_drift is not None and model.load_friction is not None
    )
    load_part = model.mechanics.r * model.load_friction.f_cl

    def scale(t_s: float, travel_rad: float) -> float:
        th = model.thermal_drift
        assert th is not None and model.wear_drift is not None
        return (1 + th.d_th * (1 - math.exp(-t_s / th.tau_th))) * (1 + model.wear_drift.k_wear * travel_rad)

    first = points[0]
    s0 = scale(first["time_s"], first["travel_rad"])
    out = []
    for p in points:
        expected = (
            load_part + (first["coulomb_estimate"] - load_part) * scale(p["time_s"], p["travel_rad"]) / s0
        )
        sigma = (
            math.hypot(p["coulomb_sigma"], first["coulomb_sigma"]) if p is not first else p["coulomb_sigma"]
        )
        out.append((p["coulomb_estimate"] - expected) / sigma)
    return out


def load_average() -> str:
    """The machine's 1/5/15-minute load averages: figures from a shared machine are read beside them."""
    return " / ".join(f"{x:.1f}" for x in os.getloadavg())


def bench_endurance(work: Path) -> None:
    print("\n## Endurance on the simulated rig (sim-endurance, virtual time), sealed and exported\n")
    print(f"load average at start: {load_average()}\n")
    print(
        "| duty | samples | record+seal+analyze wall s | peak MB | export parquet s / MB | csv s / MB"
        " | mat s / MB | trend: worst |dev|/σ | load after |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for hours in ENDURANCE_HOURS:
        home = work / f"home-{hours:g}"
        env = {**os.environ, "HDRIG_HOME": str(home)}
        wall, rss, out = timed(
            [
                str(BIN / "hdrig"),
                "run",
                "endurance",
                "--rig",
                "sim-endurance",
                "--set",
                f"duration_h={hours}",
                "--json",
                "-q",
            ],
            env,
        )
        doc = json.loads(out)
        run_id, samples = doc["id"], doc["samples"]
        exports = []
        for fmt in ("parquet", "csv", "mat"):
            target = work / f"export.{fmt}"
            e_wall, e_rss, _ = timed(
                [str(BIN / "hdrig"), "runs", "export", run_id, "--format", fmt, "--out", str(target)], env
            )
            exports.append(f"{e_wall:.1f} / {e_rss:.0f}")
            target.unlink()
        _, _, trend = timed([str(BIN / "hdrig"), "trend", run_id, "--json"], env)
        deviations = drift_truth(json.loads(trend)["points"])
        label = f"{hours * 3600:.0f} s" if hours < 1 else f"{hours:g} h"
        print(
            f"| {label} | {samples:,} | {wall:.1f} | {rss:.0f} | {' | '.join(exports)} |"
            f" {max(abs(d) for d in deviations):.2f} ({len(deviations)} checkpoints) | {load_average()} |"
        )
        shutil.rmtree(home)


def main() -> None:
    with tempfile.TemporaryDirectory(prefix="bench-endurance-") as folder:
        work = Path(folder)
        if "--endurance-only" not in sys.argv:
            bench_simulate(work)
        if "--simulate-only" not in sys.argv:
            bench_endurance(work)


if __name__ == "__main__":
    main()
