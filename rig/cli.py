"""The `hdrig` command line (docs/INTERFACE.md): argument parsing and printing over the core (`rig.core`).

Errors a user can cause end as one line on stderr and exit status 2; a device fault or a safety trip
ends the run `aborted: <fault>` and exits 3; anything else is a bug and keeps its traceback. `--json`
output is one JSON document on stdout, exactly the document the service returns; logs and progress go
to stderr.

Why commands import inside themselves: the core, the store and the service pull in SQLAlchemy,
pyarrow, matplotlib, Dask and uvicorn, which take several seconds to import on a loaded machine, so a
command imports only what it uses and `hdrig --help`, `hdrig model show` or `hdrig simulate` start in
well under a second (figures: docs/BENCHMARKS.md, "Figures behind design choices in the code"). Only
the light modules (parameters, inputs, faults, statuses) are imported above.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import importlib.util
import json
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn

from pydantic import BaseModel

from model.errors import UserInputError
from model.inputs import KINDS
from model.params import HarmonicDriveModel, load_model, parse_model
from rig.faults import DeviceFaultError
from rig.status import RunStatus

if TYPE_CHECKING:
    from rig.core import actions, operations
    from rig.core.documents import RunDocument
    from rig.lab import Lab

Handler = Callable[[argparse.Namespace], int]


def _lazy_module(name: str) -> Any:
    """The module `name`, loaded at its first attribute access (importlib's LazyLoader recipe)."""
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.find_spec(name)
    assert spec is not None and spec.loader is not None, name
    spec.loader = importlib.util.LazyLoader(spec.loader)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


if not TYPE_CHECKING:
    # The core imports every experiment (scipy.signal, matplotlib): ~1 s that `hdrig simulate` never uses.
    actions = _lazy_module("rig.core.actions")
    operations = _lazy_module("rig.core.operations")

CAMPAIGN = "campaign"
EXIT_BAD_INPUT = 2
EXIT_ABORTED = 3
EXIT_INTERRUPTED = 130
METRICS_SHOWN = 6  # metrics on a run's one-line summary; `hdrig runs show` prints them all


def _say(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def _print_json(data: Any) -> int:
    """Print one JSON document on stdout (a document, a list of them, or plain data); exit status 0."""
    if isinstance(data, BaseModel):
        data = data.model_dump(mode="json")
    elif isinstance(data, list):
        data = [item.model_dump(mode="json") if isinstance(item, BaseModel) else item for item in data]
    json.dump(data, sys.stdout, indent=2)
    sys.stdout.write("\n")
    return 0


# --- where the work is done: here, or on a service (hdrig --server URL) -------------------------------

KEY_VARIABLE = "HDRIG_KEY"


def _lab(args: argparse.Namespace) -> Lab:
    """The core on this machine, or the service named by --server (`rig.lab`)."""
    from rig.lab import LocalLab, remote_lab  # the core and its experiments: ~1 s `simulate` never pays

    if not args.server:
        return LocalLab()
    key = args.key or os.environ.get(KEY_VARIABLE)
    if not key:
        raise UserInputError(f"--server {args.server}: needs an API key: --key KEY or ${KEY_VARIABLE}")
    return remote_lab(args.server, key)


def _here_only(args: argparse.Namespace) -> None:
    if args.server:
        raise UserInputError(f"hdrig {args.command} runs on this machine only: drop --server")


# --- hdrig model ----------------------------------------------------------------------------------


def cmd_model_list(args: argparse.Namespace) -> int:
    lab = _lab(args)
    rows = lab.list_models()
    if args.json:
        return _print_json(rows)
    width = max((len(r.name) for r in rows), default=4)
    for row in rows:
        print(f"{row.name:<{width}}  {row.description.split('. ')[0][:90]}")
    _say(f"presets live in {lab.presets_where}")
    return 0


def _describe(model: HarmonicDriveModel) -> list[str]:
    lines = [f"{model.name}: {model.description}", f"effects: {', '.join(model.effects) or 'none'}"]
    for section_name in type(model).model_fields:
        section = getattr(model, section_name)
        if section is None or isinstance(section, str):
            continue
        lines.append(f"{section_name}:")
        for field_name, info in type(section).model_fields.items():
            value = getattr(section, field_name)
            if value is None:
                continue
            lines.append(f"  {field_name:<14} {value!s:<24} {info.description or ''}")
    return lines


def cmd_model_show(args: argparse.Namespace) -> int:
    document = _lab(args).show_model(args.model)
    if args.json:
        _print_json(document)
    else:
        print("\n".join(_describe(parse_model(document, args.model))))
    return 0


# --- hdrig simulate -------------------------------------------------------------------------------


def cmd_simulate(args: argparse.Namespace) -> int:
    # The process ends once the file is written, and what it builds is freed by reference counts (the
    # stream's blocks hold arrays): the cyclic collector's walks over the ~10^5 objects numba and scipy
    # load are pure cost here, ~0.07 s of CPU at start-up and ~0.25 s in the exit's final collection
    # (measured), more than a C loop's whole 200 s run. Off, and what exists frozen before exit.
    gc.disable()
    try:
        return _simulate(args)
    finally:
        gc.freeze()


def _simulate(args: argparse.Namespace) -> int:
    from model.simulate import replay, simulate_stream
    from rig.store.runfile import read_run, write_run, write_stream

    _here_only(args)
    model = load_model(args.model)
    if args.input_file:
        source = read_run(args.input_file)
        run = replay(model, source, dt_s=args.dt, diagnostics=args.diagnostics)
        path = write_run(run, args.out)
        _say(f"wrote {len(run)} samples ({run.t[-1] - run.t[0]:.3f} s) to {path}")
        return 0
    if args.duration is None:
        raise UserInputError("simulate --input needs --duration S")
    # Chunk by chunk from the integrator to the file: memory does not grow with --duration.
    stream = simulate_stream(
        model,
        args.input,
        args.duration,
        dt_s=args.dt,
        rate_hz=args.rate,
        mode=args.mode,
        tau_ext=args.load,
        diagnostics=args.diagnostics,
    )
    path, rows = write_stream(stream, stream.columns, stream.meta, args.out)
    _say(f"wrote {rows} samples ({(rows - 1) / args.rate:.3f} s) to {path}")
    return 0


# --- hdrig run -----------------------------------------------------------------------------------


def _summary(run: RunDocument) -> str:
    """One line: id, experiment, status or abort reason, samples, key metrics, where to look."""
    parts = [run.id, run.experiment, run.reason or run.status, f"{run.samples} samples"]
    shown = list(run.metrics.items())[:METRICS_SHOWN]
    if shown:
        more = len(run.metrics) - len(shown)
        parts.append(
            " ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in shown)
            + (f" (+{more} more)" if more else "")
        )
    if run.run_dir is not None:
        if run.status == RunStatus.COMPLETE:
            parts.append(f"results: {Path(run.run_dir) / 'artifacts'}")
        else:
            parts.append(f"data: {run.run_dir}")
    return "  ".join(parts)


def _print_params(lab: Lab, name: str) -> None:
    for info in lab.list_experiments():
        if name not in (CAMPAIGN, info.name):
            continue
        print(f"{info.name}: {info.summary}")
        for key, spec in info.params_schema.get("properties", {}).items():
            default = spec.get("default", "")
            print(f"  {key:<24} {default!s:<28} {spec.get('description', '')}")


def cmd_run(args: argparse.Namespace) -> int:
    from rig.progress import ProgressBar

    name: str = args.experiment
    if name != CAMPAIGN:
        actions.experiment_named(name)
    lab = _lab(args)
    if args.params:
        _print_params(lab, name)
        return 0
    params = actions.params_from_pairs(name, args.set)
    runs: list[RunDocument] = []
    with ProgressBar(enabled=not args.quiet) as bar:

        def landed(run: RunDocument) -> None:
            runs.append(run)
            if not args.json:
                bar.write(_summary(run))

        request = operations.asked(
            operations.RunRequest,
            experiment=name,
            params=params,
            keep_going=args.keep_going,
            unit=args.unit,
            tags=args.tag or [],
        )
        try:
            lab.run(request, args.rig, bar, landed)
        except KeyboardInterrupt as stop:  # the lab has stopped the motion and seen the run end
            _say(f"hdrig: interrupted; quick stop; run {runs[-1].id if runs else '-'} kept")
            return _interrupted_status(stop)
    if args.json:
        data = [run.as_json() for run in runs]
        _print_json(data if name == CAMPAIGN else data[0])
    aborted = [run for run in runs if run.status != RunStatus.COMPLETE]
    for run in aborted:
        _say(f"hdrig: run {run.id} {run.reason or run.status}")
    return EXIT_ABORTED if aborted else 0


# --- hdrig runs ----------------------------------------------------------------------------------


def _page_size(text: str) -> int:
    """`--limit`: a count of runs, at least 1."""
    try:
        count = int(text)
    except ValueError:
        count = 0
    if count < 1:
        raise argparse.ArgumentTypeError(f"{text!r} is not a count of runs (1 or more)")
    return count


def cmd_runs_list(args: argparse.Namespace) -> int:
    from rig.store.catalog import DEFAULT_PAGE
    from rig.store.runs import RunQuery, query_of

    lab = _lab(args)
    filters = {name: getattr(args, name) for name in RunQuery.model_fields if name != "tags"}
    query = query_of(None, {**filters, "tags": args.tag or []})
    page = lab.list_runs(query, limit=None if args.all else args.limit or DEFAULT_PAGE)
    runs = page.runs
    if args.json:
        _print_json(runs)
    elif runs:
        header = {"id": "id", "experiment": "experiment", "status": "status", "started": "started (UTC)"}
        rows = [
            {
                "id": r.id,
                "experiment": r.experiment,
                "status": str(r.status),
                "started": (r.started or "")[:19],
            }
            for r in runs
        ]
        width = {key: max(len(row[key]) for row in [header, *rows]) for key in header}
        for row, run in zip([header, *rows], [None, *runs], strict=True):
            cells = "  ".join(f"{row[key]:<{width[key]}}" for key in header)
            samples = "samples" if run is None else str(run.samples)
            reason = "" if run is None or not run.reason else f"  {run.reason}"
            if run is not None and run.analysis in ("interrupted", "failed"):
                reason += f"  analysis: {run.analysis}"
            print(f"{cells}  {samples:>8}{reason}")
    plural = "s" if page.total != 1 else ""
    older = page.total - len(runs)
    if not page.total:
        _say(f"no runs in {lab.store_where}")
    elif older > 0:
        _say(
            f"the newest {len(runs)} of {page.total} run{plural} in {lab.store_where};"
            f" {older} older not shown (--limit N, or --all)"
        )
    else:
        _say(f"{len(runs)} run{plural} in {lab.store_where}")
    return 0


def cmd_runs_show(args: argparse.Namespace) -> int:
    run = _lab(args).run_document(args.run)
    if args.json:
        return _print_json(run)
    model = f"{run.model_name} ({run.model_hash})" if run.model_name else "-"
    fields = {
        "id": run.id,
        "experiment": run.experiment,
        "rig": run.rig,
        "model": model,
        "status": run.status,
        "reason": run.reason or "-",
        "started": run.started,
        "ended": run.ended or "-",
        "samples": run.samples,
        "data": run.path,
        "analysis": run.analysis or "-",
    }
    for key, value in fields.items():
        print(f"{key:<11} {value}")
    print("metrics:" + ("" if run.metrics else " none"))
    for key, value in run.metrics.items():
        print(f"  {key:<28} {value}")
    print("artifacts:" + ("" if run.artifacts else " none"))
    for path in run.artifacts:
        print(f"  {path}")
    return 0


def cmd_runs_analyze(args: argparse.Namespace) -> int:
    from rig.store.runs import RunStore

    _here_only(args)
    run = actions.analyze_run(RunStore(), args.run)
    if args.json:
        _print_json(run)
    else:
        print(_summary(run))
    return 0


def cmd_runs_export(args: argparse.Namespace) -> int:
    path = _lab(args).export_run(args.run, args.format, args.out)
    _say(f"wrote run {args.run} to {path}")
    return 0


# --- hdrig trend ---------------------------------------------------------------------------------


def cmd_trend(args: argparse.Namespace) -> int:
    from rig.store.runs import RunStore

    store = RunStore()
    document = actions.trend(store, run_id=args.run, unit=args.unit, plot_dir=args.plot, model=args.model)
    if args.json:
        return _print_json(document)
    header = ("run", "#", "time h", "cycles", "F_c N·m", "b N·m·s/rad", "K_s N·m/rad")
    print("{:<36} {:>3} {:>8} {:>8} {:>18} {:>20} {:>16}".format(*header))
    for p in document.points:
        print(
            f"{p.run_id:<36} {p.index:>3} {p.time_s / 3600:>8.3f} {p.duty_cycles:>8.0f}"
            f" {p.coulomb_estimate:>9.5f} ±{p.coulomb_sigma:<7.5f}"
            f" {p.viscous_estimate:>10.3e} ±{p.viscous_sigma:<8.1e}"
            f" {p.stiffness_estimate:>8.1f} ±{p.stiffness_sigma:<6.1f}"
            + (f" T_g {p.temp_gear_c:.1f} °C" if p.temp_gear_c is not None else "")
            + (
                f" F_c at {document.t_ref_c:g} °C {p.coulomb_normalized_estimate:.5f}"
                f" ±{p.coulomb_normalized_sigma:.5f}"
                if p.coulomb_normalized_estimate is not None
                else ""
            )
        )
    for path in document.plots:
        _say(f"plot: {path}")
    return 0


# --- hdrig fit, hdrig gaps -----------------------------------------------------------------------

MAP_HELP = (
    "read files with other column names, units or gains: TARGET=SOURCE[*GAIN][+OFFSET] (e.g."
    " theta_m=enc*deg, i_cmd=volts*2.5), or a YAML/JSON file of such pairs; repeatable; kept in the run's"
    " metadata"
)


def _analysis(args: argparse.Namespace, action: Callable[..., Any], joint: bool = True) -> Any:
    """Run fit or gaps (a `Lab`'s) with a progress bar; the action's document."""
    from rig.progress import ProgressBar

    order = operations.AnalysisOrder(args.data, args.model, args.out, args.report, args.map, joint)
    with ProgressBar(enabled=not args.quiet) as bar:
        return action(order, bar)


def cmd_fit(args: argparse.Namespace) -> int:
    if args.batch:
        return _fit_batch(args)
    if args.out is None:
        raise UserInputError("fit: --out FILE is required (the fitted model file to write), or --batch")
    result = _analysis(args, _lab(args).fit, joint=not args.no_joint)
    if args.json:
        return _print_json(result)
    width = max(len(name) for name in result.parameters)
    for name, row in result.parameters.items():
        sigma = f"± {row.uncertainty:.3g}" if row.uncertainty is not None else "not determined"
        note = f"  ({row.note})" if row.note and not row.identifiable else ""
        print(f"{name:<{width}}  {row.estimate:>12.6g}  {sigma:<16} {row.stage}{note}")
    print(f"fit error: {result.fit_error.before:.4g} → {result.fit_error.after:.4g}")
    _print_lab_quantities(result.lab_quantities)
    print(f"model: {result.model_file}")
    if result.report is not None:
        print(f"report: {result.report}")
    return 0


def _print_lab_quantities(quantities: dict[str, Any]) -> None:
    """`fit`'s derived figures, the ones labs compare (Coulomb at rest, viscous slope, inertias...)."""
    if not quantities:
        return
    print("numbers labs compare:")
    width = max(len(name) for name in quantities)
    for name, q in quantities.items():
        sigma = f"± {q.sigma:.3g}" if q.sigma is not None else "not determined"
        print(f"  {name:<{width}}  {q.value:>12.6g}  {sigma:<16} {q.unit}")


def _fit_batch(args: argparse.Namespace) -> int:
    """`hdrig fit --data 'unit=HD25-*' --batch`: every unit's fit on Dask, and the fleet report."""
    from rig.core import fleet
    from rig.progress import ProgressBar
    from rig.store.runs import RunStore

    if getattr(args, "server", None):
        raise UserInputError("fit --batch runs on this machine's store and a Dask cluster, not over --server")
    if args.out is not None or args.map:
        raise UserInputError(
            "fit --batch: each unit's model goes to the catalog and its folder, not --out/--map"
        )
    with ProgressBar(enabled=not args.quiet) as bar:
        document = fleet.batch_fit(
            RunStore(), args.data, args.model, args.scheduler, args.workers, not args.no_joint, bar
        )
    if args.json:
        return _print_json(document)
    for unit in document.units:
        flagged = [name for name, p in unit.parameters.items() if p.outlier]
        determined = sum(p.determined for p in unit.parameters.values())
        state = unit.error if unit.status != "complete" else f"{determined} parameters determined"
        print(f"{unit.unit}: {state}" + (f"; outlier in {', '.join(flagged)}" if flagged else ""))
    print(f"fleet report: {document.report}")
    return 0


def cmd_gaps(args: argparse.Namespace) -> int:
    result = _analysis(args, _lab(args).find_gaps)
    if args.json:
        return _print_json(result)
    print(result.verdict)
    for number, step in enumerate(result.steps, 1):
        print(
            f"{number}. {step.effect}: gap {step.gap_before:.4g} → {step.gap_after:.4g} rad; {step.evidence}"
        )
    print(f"model: {result.final_model}")
    if result.report:
        print(f"report: {result.report[0]}")
    return 0


# --- hdrig keys and hdrig serve -------------------------------------------------------------------


def cmd_keys_create(args: argparse.Namespace) -> int:
    from rig.core import access
    from rig.store.runs import RunStore

    _here_only(args)
    print(access.create_key(RunStore(), args.role, args.name))  # the key alone: scripts read stdout
    _say("hdrig: the key is shown only this once; it is stored hashed")
    return 0


def cmd_keys_list(args: argparse.Namespace) -> int:
    from rig.core import access
    from rig.store.runs import RunStore

    _here_only(args)
    keys = access.list_keys(RunStore())
    if args.json:
        return _print_json(keys)
    for key in keys:
        state = f"revoked {key.revoked}" if key.revoked else "live"
        print(f"{key.name:<24} {key.role:<9} {key.created}  {state}")
    return 0


def cmd_keys_revoke(args: argparse.Namespace) -> int:
    from rig.core import access
    from rig.store.runs import RunStore

    _here_only(args)
    access.revoke_key(RunStore(), args.name, door="command line")  # audited in the same transaction
    _say(f"hdrig: key {args.name} revoked")
    return 0


def cmd_twin(args: argparse.Namespace) -> int:
    from rig.config import load_rig_config
    from rig.interface import backend_class
    from rig.realtime import freeze_built, quiet_heap

    config = load_rig_config(args.rig)
    # The backend serves its own twins; rig knows no backend, so it asks the class named by the file.
    serve = getattr(backend_class(config.backend), "serve_twins", None)
    if serve is None:
        raise UserInputError(f"rig {config.name!r}: backend {config.backend!r} has no twins to serve")
    _say(f"hdrig: twins of rig {config.name} on 127.0.0.1; Ctrl-C stops them")

    def announce(line: str) -> None:
        freeze_built()  # the twins are built: out of the collector's walks before the first SYNC
        print(line, flush=True)

    with quiet_heap():  # this process is the twins' own: a full collection would hold their answers back
        serve(config, args.port, announce)
    return 0


SERVICE_SIGNALS = tuple(getattr(signal, n) for n in ("SIGTERM", "SIGINT", "SIGHUP") if hasattr(signal, n))
SERVICE_EXIT_S = 5.0  # a signal to `hdrig serve` ends the process within this, however many clients follow
STREAMS_GRACE_S = 3  # [s] uvicorn's wait for open responses; event streams end by themselves well before


def cmd_serve(args: argparse.Namespace) -> int:
    import logging

    import uvicorn

    from rig.config import load_rig_config
    from rig.core import access
    from rig.store.runs import RunStore

    _here_only(args)
    config = load_rig_config(args.rig)
    store = RunStore()
    host = f"[{args.host}]" if ":" in args.host else args.host  # as given: 127.0.0.1, not localhost
    if not access.has_keys(store):
        key = access.create_key(store, access.Role.ADMIN, "admin", door="first start of hdrig serve")
        _say(f"hdrig: no API key in {store.home}: made an admin key, shown only this once:\n    {key}")
        _say(f"hdrig: open http://{host}:{args.port}/ and log in with it (or: Authorization: Bearer <key>)")
    from rig.lab import served_app

    service = served_app()  # the service sits above the rig: it offers its door to rig.lab
    app = service.create_app(config, store)
    served = uvicorn.Config(
        app, host=args.host, port=args.port, log_level="warning", timeout_graceful_shutdown=STREAMS_GRACE_S
    )
    # A request log, one line each, uvicorn's other chatter left at warnings. The page's polls (the rig
    # each second, the lists every 5 s) are left out when answered: they would drown every other line.
    polls = {"/api/v1/rig", "/api/v1/health", "/api/v1/jobs"}

    def not_a_poll(record: logging.LogRecord) -> bool:
        fields = record.args if isinstance(record.args, tuple) and len(record.args) == 5 else None
        if fields is None:
            return True
        _, method, path, _, status = fields
        polled = str(path) in polls or str(path).startswith("/api/v1/runs?")
        return not (method == "GET" and polled and isinstance(status, int) and status < 400)

    request_log = logging.getLogger("uvicorn.access")
    request_log.setLevel(logging.INFO)
    request_log.addFilter(not_a_poll)
    for handler in request_log.handlers:
        handler.setFormatter(logging.Formatter("hdrig: %(asctime)s %(message)s", "%H:%M:%S"))

    def listening(port: int) -> None:
        _say(
            f"hdrig: serving rig {config.name} on http://{host}:{port}/ (store {store.home});"
            " Ctrl-C stops the rig and exits"
        )

    server = _service_server(uvicorn.Server, served, lambda why: service.stop_service(app, why), listening)
    server.run()
    if server.signum is None:
        return 0
    name = signal.Signals(server.signum).name
    _say(f"hdrig: {name}: the rig was quick-stopped at the signal; the service has stopped")
    # Stopped, its run sealed, its streams ended: nothing is left to save, so the process ends here rather
    # than tearing down its modules (numba, pyarrow, matplotlib: seconds on a loaded machine).
    sys.stdout.flush()
    os._exit(128 + server.signum)


def _service_server(
    base: type[Any], served: Any, stop: Callable[[str], None], listening: Callable[[int], None]
) -> Any:
    """uvicorn's server with one stop path: SIGTERM, SIGINT and SIGHUP quick-stop the rig first (`stop`,
    in the signal handler, before uvicorn waits on any connection), then uvicorn shuts down; the service
    ends its event streams itself; a watchdog ends the process SERVICE_EXIT_S after the signal whatever
    is still running (exit status 128 + the signal)."""

    class Service(base):
        signum: int | None = None

        async def startup(self, sockets: Any = None) -> None:
            await super().startup(sockets=sockets)
            if self.started and self.servers and self.servers[0].sockets:
                listening(self.servers[0].sockets[0].getsockname()[1])

        @contextlib.contextmanager
        def capture_signals(self) -> Iterator[None]:
            # uvicorn's own handles SIGINT and SIGTERM, and raises them again once it has shut down;
            # here the three are handled alike, and cmd_serve returns the exit status instead.
            if threading.current_thread() is not threading.main_thread():
                yield
                return
            before = {number: signal.signal(number, self.handle_exit) for number in SERVICE_SIGNALS}
            try:
                yield
            finally:
                for number, handler in before.items():
                    signal.signal(number, handler)

        def handle_exit(self, sig: int, frame: Any) -> None:
            if self.signum is None:
                self.signum = sig
                stop(f"quick stop: the service got {signal.Signals(sig).name}")  # the motor, first
                watchdog = threading.Timer(SERVICE_EXIT_S, _exit_now, args=(sig,))
                watchdog.daemon = True
                watchdog.start()
            super().handle_exit(sig, frame)

    return Service(served)


def _exit_now(signum: int) -> None:
    name = signal.Signals(signum).name
    _say(f"hdrig: still running {SERVICE_EXIT_S:g} s after {name}: exiting now (the rig was quick-stopped)")
    os._exit(128 + signum)


# --- parser ---------------------------------------------------------------------------------------


EXPERIMENT_NAMES = "<experiments>"
"""Stands for the registered experiments in help texts: filled in only when help is shown, since
importing the experiments (and matplotlib with them) would slow every command's start."""


class _Parser(argparse.ArgumentParser):
    """argparse with docs/INTERFACE.md's one-line errors (exit status 2), instead of usage plus error."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"hdrig: error: {message} (see {self.prog} --help)\n")

    def format_help(self) -> str:
        text = super().format_help()
        if EXPERIMENT_NAMES in text:
            from rig.experiments import EXPERIMENTS

            text = text.replace(EXPERIMENT_NAMES, ", ".join(EXPERIMENTS))
        return text


RUN_EPILOG = """\
--set: a single experiment takes key=value (e.g. --set hold_s=0.5); the campaign takes
experiment.key=value (e.g. --set speed-sweep.hold_s=0.5). Values are YAML scalars or lists
(--set speeds_rad_s=[1,10,100]). `hdrig run EXPERIMENT --params` lists them. Every value is checked
before the rig is opened, and every set-point of the program before the motor moves (exit status 2).

Output: one line per run as it lands (run id, status or abort reason, samples, key metrics, and the
run's artifacts folder with its CSV tables, results.json and plots/); --json prints one JSON document
instead (an object for one experiment, a list for the campaign). A progress bar with ETA goes to stderr
when stderr is a terminal.

Exit status: 0 every run complete; 2 bad input (unknown experiment or rig file, bad --set, a set-point
the rig refuses); 3 a run aborted (safety envelope breached, a device fault, or a quick stop): its
data are kept, the reason is on stderr; 130 interrupted (Ctrl-C: the rig quick-stops and the run ends
`aborted` with its data)."""


Subcommands = Any  # argparse's _SubParsersAction, private in typeshed
JSON_HELP = "one JSON document on stdout"
DATA_HELP = "run ids in the store, run files, or `latest` (the newest complete run of each experiment)"


def _command(
    sub: Subcommands, name: str, handler: Handler, help: str, json: str | None = None, **kwargs: Any
) -> argparse.ArgumentParser:
    """A subcommand that `handler` runs; `json` is the help of its --json flag, when it has one."""
    command: argparse.ArgumentParser = sub.add_parser(name, help=help, **kwargs)
    if json is not None:
        command.add_argument("--json", action="store_true", help=json)
    command.set_defaults(handler=handler)
    return command


def _group(sub: Subcommands, name: str, help: str) -> Subcommands:
    """A command made of actions (`hdrig runs list`, `hdrig keys create`...)."""
    return sub.add_parser(name, help=help).add_subparsers(
        dest=f"{name}_command", required=True, metavar="ACTION"
    )


def _run_id(command: argparse.ArgumentParser) -> None:
    command.add_argument("run", metavar="RUN", help="run id (see hdrig runs list)")


def _analysis_arguments(command: argparse.ArgumentParser, model_help: str) -> None:
    """What fit and gaps both take: the runs, the model, a mapping for foreign files, no progress bar."""
    command.add_argument("--data", required=True, nargs="+", metavar="RUN_OR_FILE", help=DATA_HELP)
    command.add_argument("--model", required=True, metavar="M", help=model_help)
    command.add_argument("--map", action="append", metavar="ENTRY_OR_FILE", help=MAP_HELP)
    command.add_argument("-q", "--quiet", action="store_true", help="no progress bar")


def _rig_argument(command: argparse.ArgumentParser) -> None:
    command.add_argument("--rig", required=True, metavar="RIG", help="rig file, or a name in configs/rigs")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="hdrig", description="Characterize harmonic-drive transmissions on a real or simulated rig."
    )
    parser.add_argument(
        "--server",
        metavar="URL",
        help="run `model`, `run`, `runs`, `fit` and `gaps` on the hdrig service at URL"
        " (http://127.0.0.1:8000) with the same output; --data and --model then name its runs and presets",
    )
    parser.add_argument(
        "--key", metavar="KEY", help=f"the API key for --server (default: ${KEY_VARIABLE}; hdrig keys create)"
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    _add_model(sub)
    _add_simulate(sub)
    _add_run(sub)
    _add_runs(sub)
    _add_trend(sub)
    _add_fit(sub)
    _add_gaps(sub)
    _add_keys(sub)
    _add_serve(sub)
    _add_twin(sub)
    return parser


def _add_model(sub: Subcommands) -> None:
    """`model list` and `model show`."""
    model = _group(sub, "model", "list and show model presets and files")
    _command(model, "list", cmd_model_list, "list the presets in configs/models", json=JSON_HELP)
    show = _command(
        model,
        "show",
        cmd_model_show,
        "print a model; --json prints a valid model file",
        json="every parameter by its docs/MODEL.md name, as JSON",
    )
    show.add_argument("model", metavar="NAME_OR_FILE", help="preset name (seed) or YAML/JSON model file")


def _add_simulate(sub: Subcommands) -> None:
    """`simulate`: a model under an input profile, or a replay."""
    kinds = "; ".join(f"{name}: {kind.help}" for name, kind in KINDS.items())
    sim = sub.add_parser(
        "simulate",
        help="simulate a model under an input profile, or replay a run's inputs",
        description=f"Input specs are KIND:key=value,... Kinds — {kinds}.",
    )
    sim.add_argument("--model", required=True, metavar="M", help="preset name or model file")
    source = sim.add_mutually_exclusive_group(required=True)
    source.add_argument("--input", metavar="SPEC", help="input profile, e.g. sine:amp=2,freq=0.5")
    source.add_argument("--input-file", metavar="RUN", help="replay the input columns of a run file")
    sim.add_argument("--duration", type=float, metavar="S", help="simulated time [s] (with --input)")
    sim.add_argument("--dt", type=float, default=1e-4, metavar="S", help="integration step [s] (1e-4)")
    sim.add_argument(
        "--rate", type=float, default=1000.0, metavar="HZ", help="output sample rate [Hz] (1000)"
    )
    sim.add_argument(
        "--mode",
        choices=("voltage", "current", "torque"),
        default="voltage",
        help="what the input drives: motor voltage u, current i_cmd or torque tau_m (voltage)",
    )
    sim.add_argument("--load", default="0", metavar="SPEC", help="external load torque tau_ext: N·m or SPEC")
    sim.add_argument("--diagnostics", action="store_true", help="also write tau_m, F_m, F_l and T_s")
    sim.add_argument("--out", required=True, metavar="FILE", help="run file to write (.parquet, .csv, .mat)")
    sim.set_defaults(handler=cmd_simulate)


def _add_run(sub: Subcommands) -> None:
    """`run`: an experiment or the campaign on a rig."""
    names = EXPERIMENT_NAMES
    run = sub.add_parser(
        "run",
        help="run an experiment, or the whole campaign, on a rig; store and analyze each run",
        description=f"Run one experiment ({names}) or `{CAMPAIGN}` (all of them in turn)\n"
        "on a rig, and store each run under $HDRIG_HOME (default ~/.hdrig).",
        epilog=RUN_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    run.add_argument("experiment", metavar="EXPERIMENT", help=f"{names} or {CAMPAIGN}")
    run.add_argument(
        "--rig", metavar="RIG", help="rig file, or a name in configs/rigs (sim); required to run"
    )
    run.add_argument(
        "--params",
        action="store_true",
        help="list the experiment's parameters (default, unit, meaning) and exit",
    )
    run.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="experiment parameter (repeatable); EXPERIMENT.KEY=VALUE for the campaign",
    )
    run.add_argument("--json", action="store_true", help="one JSON document on stdout when done")
    run.add_argument(
        "--keep-going",
        action="store_true",
        help="campaign: go on to the next experiment after a run aborts (default: stop there)",
    )
    run.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    run.add_argument("--unit", metavar="SERIAL", help="the gear unit on the bench (default: the rig file's)")
    run.add_argument(
        "--tag", action="append", default=[], metavar="TAG", help="a free tag for the catalog (repeatable)"
    )
    run.set_defaults(handler=cmd_run)


def _add_runs(sub: Subcommands) -> None:
    """`runs list|show|analyze|export`: the run catalog."""
    runs = _group(sub, "runs", "the run catalog: list, show, analyze and export runs")
    listed = "the newest runs (a page; --all: every one): id, experiment, status, started, samples"
    searched = _command(runs, "list", cmd_runs_list, listed, json="the runs listed, as a JSON list")
    how_many = searched.add_mutually_exclusive_group()
    how_many.add_argument(
        "--limit", type=_page_size, metavar="N", help="the newest N runs (default: a page of the newest)"
    )
    how_many.add_argument("--all", action="store_true", help="every run the filters select")
    searched.add_argument(
        "--experiment", metavar="NAME", help="only this experiment's runs (exact or a glob)"
    )
    searched.add_argument("--status", choices=[s.value for s in RunStatus], help="only runs with this status")
    searched.add_argument("--unit", metavar="SERIAL", help="only this gear unit's runs (a glob: 'HD25-*')")
    searched.add_argument("--rig", metavar="NAME", help="only this rig's runs (exact or a glob)")
    searched.add_argument("--operator", metavar="WHO", help="only the runs this key name or OS user started")
    searched.add_argument(
        "--tag", action="append", default=[], metavar="TAG", help="only runs with this tag (repeatable: all)"
    )
    shown = "one run: catalog entry, metrics, artifacts"
    _run_id(_command(runs, "show", cmd_runs_show, shown, json="one JSON object"))
    again = "analyze a complete run again (tables, plots, metrics), e.g. after an interruption"
    _run_id(_command(runs, "analyze", cmd_runs_analyze, again, json="the run's document as one JSON object"))
    export = _command(
        runs, "export", cmd_runs_export, "write a run as CSV (+ .json metadata), Parquet or MAT"
    )
    _run_id(export)
    export.add_argument("--format", required=True, choices=("csv", "parquet", "mat"), help="file format")
    export.add_argument(
        "--out", required=True, metavar="PATH", help="file to write, or a folder to write <RUN>.<format> in"
    )


def _add_trend(sub: Subcommands) -> None:
    """`trend`: endurance checkpoints against time."""
    trend = _command(
        sub,
        "trend",
        cmd_trend,
        "endurance checkpoints (friction, stiffness ±1σ) against time, for a run or a gear unit",
        json="the trend document as one JSON object",
    )
    which = trend.add_mutually_exclusive_group(required=True)
    which.add_argument("run", metavar="RUN", nargs="?", help="an endurance run's id")
    which.add_argument("--unit", metavar="SERIAL", help="every run of the gear unit (the rig file's `unit:`)")
    trend.add_argument(
        "--plot", metavar="DIR", help="write friction_trend.png and stiffness_trend.png into DIR"
    )
    trend.add_argument(
        "--model",
        metavar="MODEL",
        help="model file or preset whose thermal law brings each checkpoint's F_c to its T_ref (normalized)",
    )


def _add_fit(sub: Subcommands) -> None:
    """`fit`: identification."""
    fit = _command(
        sub,
        "fit",
        cmd_fit,
        "identify the model's parameters from runs; write the fitted model file",
        json=JSON_HELP,
        description="Staged estimates from each experiment's data (motor constants, stiffness, inertias,"
        " kinematic error, friction against position and velocity, breakaway), then every determined"
        " parameter refined together on the pulse/step/sine trajectories. Parameters the data cannot"
        " determine are reported as such and keep the starting model's value.",
    )
    _analysis_arguments(fit, "starting model: preset name or file")
    fit.add_argument(
        "--out", metavar="FILE", help="fitted model file to write (.yaml/.json); not with --batch"
    )
    fit.add_argument("--report", type=Path, metavar="DIR", help="validation table, plots and report.md")
    fit.add_argument("--no-joint", action="store_true", help="staged estimates only (no joint refinement)")
    fit.add_argument(
        "--batch",
        action="store_true",
        help="--data selects units (unit=PATTERN, rig=PATTERN, tag=PATTERN): each fitted on Dask, a fleet"
        " report",
    )
    fit.add_argument(
        "--scheduler", metavar="ADDRESS", help="--batch: a Dask scheduler (default: a local cluster)"
    )
    fit.add_argument("--workers", type=int, metavar="N", help="--batch: the local cluster's worker processes")


def _add_gaps(sub: Subcommands) -> None:
    """`gaps`: the model-gap workflow."""
    gaps = _command(
        sub,
        "gaps",
        cmd_gaps,
        "find where the model and the data disagree, name the missing effect, add it, show the gap",
        json="one JSON document on stdout (docs/INTERFACE.md)",
        description="The model-gap workflow: simulate the model on the data's own inputs over short windows"
        " restarted from the measured state, locate the disagreement, name the MODEL.md effect that explains"
        " it, add and fit it, and go on until nothing significant is left (an effect must shrink the gap on"
        " held-out windows by 1.25× with determined parameters).",
    )
    _analysis_arguments(gaps, "preset name or model file")
    gaps.add_argument("--report", metavar="DIR", help="write summary.md, plots and model.yaml into DIR")
    gaps.add_argument(
        "--out",
        metavar="FILE",
        help="model file with the effects added (default: model.yaml in the analysis' folder,"
        " $HDRIG_HOME/analyses/<id>/)",
    )


def _add_keys(sub: Subcommands) -> None:
    """`keys create|list|revoke`."""
    keys = _group(sub, "keys", "API keys of the service: create, list, revoke")
    created = _command(keys, "create", cmd_keys_create, "make a key; prints only the key (shown this once)")
    created.add_argument("--role", required=True, choices=["viewer", "operator", "admin"])
    created.add_argument("--name", help="the key's name in lists and the audit log (default: ROLE-N)")
    _command(keys, "list", cmd_keys_list, "every key: name, role, created, revoked", json=JSON_HELP)
    _command(keys, "revoke", cmd_keys_revoke, "revoke a key by name").add_argument("name", metavar="NAME")


def _add_serve(sub: Subcommands) -> None:
    """`serve`: the REST service and page."""
    serve = _command(
        sub,
        "serve",
        cmd_serve,
        "the REST service and browser page for one rig",
        description="Serve one rig over HTTP (REST API under /api/v1, the page at /). On a store without"
        " keys an admin key is made and printed once on stderr.",
    )
    _rig_argument(serve)
    serve.add_argument(
        "--host", default="127.0.0.1", help="address to bind (default 127.0.0.1: this machine only)"
    )
    serve.add_argument("--port", type=int, default=8000, help="TCP port (default 8000)")


def _add_twin(sub: Subcommands) -> None:
    """`twin`: a virtual-can rig's twins standalone."""
    twin = _command(
        sub,
        "twin",
        cmd_twin,
        "run a virtual-can rig's drive and DAQ twins standalone, for a CANopen master elsewhere",
        description="Serve the twins of a virtual-can rig: the CiA 402 drive on a CAN bus over loopback"
        " TCP (python-can interface hdrig-tcp) and the DAQ board on a pty; prints one JSON line saying"
        " where (can, daq, node_id), then runs until Ctrl-C or SIGTERM.",
    )
    _rig_argument(twin)
    twin.add_argument("--port", type=int, default=0, help="TCP port on 127.0.0.1 (default 0: any free)")


def _load_arg(text: str) -> str | float:
    try:
        return float(text)
    except ValueError:
        return text


class StopSignal(KeyboardInterrupt):
    """SIGTERM or SIGHUP: the command ends as on Ctrl-C (a run quick-stops first, then its data are
    sealed), with exit status 128 + the signal's number."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


STOP_SIGNALS = tuple(getattr(signal, name) for name in ("SIGTERM", "SIGHUP") if hasattr(signal, name))


def _raise_stop(signum: int, frame: object) -> None:
    raise StopSignal(signum)


def _interrupted_status(stop: KeyboardInterrupt) -> int:
    return 128 + stop.signum if isinstance(stop, StopSignal) else EXIT_INTERRUPTED


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if hasattr(args, "load"):
        args.load = _load_arg(args.load)
    # Only the main thread may set handlers (a program that calls main() on another thread keeps its own).
    ours = threading.current_thread() is threading.main_thread()
    previous = {number: signal.signal(number, _raise_stop) for number in STOP_SIGNALS} if ours else {}
    try:
        handler: Handler = args.handler
        return handler(args)
    except UserInputError as exc:
        print(f"hdrig: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except DeviceFaultError as exc:
        print(f"hdrig: aborted: {exc}", file=sys.stderr)
        return EXIT_ABORTED
    except KeyboardInterrupt as stop:
        print(f"hdrig: interrupted{f' ({stop})' if isinstance(stop, StopSignal) else ''}", file=sys.stderr)
        return _interrupted_status(stop)
    finally:
        for number, handler_before in previous.items():
            signal.signal(number, handler_before)


if __name__ == "__main__":
    sys.exit(main())
