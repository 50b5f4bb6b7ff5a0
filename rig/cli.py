"""The `hdrig` command line (CONTRACT.md). A thin shell: each command parses, calls the core, prints.

Errors a user can cause end as one line on stderr and exit status 2; anything else is a bug and
keeps its traceback. `--json` output is one JSON document on stdout; logs and progress go to stderr.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Sequence
from typing import Any

from model.errors import UserInputError
from model.inputs import KINDS
from model.params import PRESET_DIR, HarmonicDriveModel, load_model, preset_names

Handler = Callable[[argparse.Namespace], int]


def _say(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def _print_json(data: Any) -> None:
    json.dump(data, sys.stdout, indent=2)
    sys.stdout.write("\n")


# --- hdrig model ----------------------------------------------------------------------------------


def cmd_model_list(args: argparse.Namespace) -> int:
    rows: list[dict[str, Any]] = []
    for name in preset_names():
        model = load_model(name)
        rows.append({"name": name, "effects": model.effects, "description": model.description})
    if args.json:
        _print_json(rows)
        return 0
    width = max((len(r["name"]) for r in rows), default=4)
    for row in rows:
        summary = row["description"].split(". ")[0][:90]
        print(f"{row['name']:<{width}}  {summary}")
    _say(f"presets live in {PRESET_DIR}")
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
    model = load_model(args.model)
    if args.json:
        _print_json(model.to_dict())
    else:
        print("\n".join(_describe(model)))
    return 0


# --- hdrig simulate -------------------------------------------------------------------------------


def cmd_simulate(args: argparse.Namespace) -> int:
    from model.simulate import replay, simulate
    from rig.runfile import read_run, write_run

    model = load_model(args.model)
    if args.input_file:
        source = read_run(args.input_file)
        run = replay(model, source, dt_s=args.dt, diagnostics=args.diagnostics)
    else:
        if args.duration is None:
            raise UserInputError("simulate --input needs --duration S")
        run = simulate(
            model,
            args.input,
            args.duration,
            dt_s=args.dt,
            rate_hz=args.rate,
            mode=args.mode,
            tau_ext=args.load,
            diagnostics=args.diagnostics,
        )
    path = write_run(run, args.out)
    _say(f"wrote {len(run)} samples ({run.t[-1] - run.t[0]:.3f} s) to {path}")
    return 0


# --- parser ---------------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="hdrig", description="Characterize harmonic-drive transmissions on a real or simulated rig."
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    model = sub.add_parser("model", help="list and show model presets and files")
    model_sub = model.add_subparsers(dest="model_command", required=True, metavar="ACTION")
    listing = model_sub.add_parser("list", help="list the presets in configs/models")
    listing.add_argument("--json", action="store_true", help="one JSON document on stdout")
    listing.set_defaults(handler=cmd_model_list)
    show = model_sub.add_parser("show", help="print a model; --json prints a valid model file")
    show.add_argument("model", metavar="NAME_OR_FILE", help="preset name (seed) or YAML/JSON model file")
    show.add_argument("--json", action="store_true", help="every parameter by its MODEL.md name, as JSON")
    show.set_defaults(handler=cmd_model_show)

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
    return parser


def _load_arg(text: str) -> str | float:
    try:
        return float(text)
    except ValueError:
        return text


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if hasattr(args, "load"):
        args.load = _load_arg(args.load)
    try:
        handler: Handler = args.handler
        return handler(args)
    except UserInputError as exc:
        print(f"hdrig: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("hdrig: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
