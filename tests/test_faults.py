"""Fault injection: however a run ends, the motor stops first, the data are kept, the status is true,
and no traceback reaches the user (issue 15; docs/RELIABILITY.md lists each fault and what happens).

In-process tests use the simulated rig `sim` in virtual time; the process tests run `hdrig` as a user
does, on a realtime copy of it (a run then lasts seconds of wall time, long enough to be hit mid-run)
or on the virtual-can rig, whose raw CAN log shows what the drive was told last.
"""

from __future__ import annotations

import json
import os
import resource
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest
import yaml

from drivers.cia402 import EMCY_HEARTBEAT, State, decode_statusword
from drivers.hardware_rig import RAW_CAN_LOG
from model.errors import UserInputError
from model.params import load_model
from model.simulate import simulate_stream
from rig.config import RIG_DIR, RigConfig, load_rig_config
from rig.interface import Block, open_rig
from rig.runner import RunHooks, run_experiment
from rig.status import RunStatus
from rig.store.runfile import read_run
from rig.store.runs import RunStore
from sim_backend.inprocess import SimRig
from sim_backend.virtual_bus import VirtualCanRig

REPO_ROOT = Path(__file__).resolve().parents[1]
NODE = 1  # configs/rigs/virtual-can.yaml
RPDO, NMT = 0x200 + NODE, 0x000  # RPDO 1 carries the controlword first (drivers.canopen_config.rpdo_layout)
ENABLE_OPERATION = (
    0x000F  # CiA 402 controlword bits 0-3 all set: the only command under which the drive moves
)
START_TIMEOUT_S = 60.0  # a loaded 2-core machine may take this long to start a run; never reached when well
LOST_BOUND_S = 1.0  # the store's promise: a killed run loses at most a flush interval of samples


def sim_config(pace: str = "virtual") -> RigConfig:
    return load_rig_config("sim").model_copy(update={"pace": pace})


# ---- one stop path: the motor first, then the data ------------------------------------------------


class _Recorder:
    """Notes, in order, when the rig was quick-stopped and when the store sealed a run."""

    def __init__(self, rig: SimRig, store: RunStore, monkeypatch: pytest.MonkeyPatch) -> None:
        self.order: list[str] = []
        stop, seal = rig.quick_stop, store._seal

        def quick_stop() -> None:
            self.order.append("quick_stop")
            stop()

        def sealed(run_id: str) -> Any:
            self.order.append("seal")
            return seal(run_id)

        monkeypatch.setattr(rig, "quick_stop", quick_stop)
        monkeypatch.setattr(store, "_seal", sealed)


class _LoopBugError(Exception):
    pass


def test_an_exception_mid_run_quick_stops_before_the_data_are_sealed(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    store = RunStore(tmp_path / "home")
    rig = SimRig(sim_config())
    recorder = _Recorder(rig, store, monkeypatch)
    blocks: list[int] = []

    def on_block(run_id: str, block: Block) -> None:
        blocks.append(len(block["t"]))
        if len(blocks) == 3:  # mid-program, the drive enabled and moving
            raise _LoopBugError("a bug in a block consumer")

    with pytest.raises(_LoopBugError):
        run_experiment("speed-sweep", rig.config, store=store, rig=rig, hooks=RunHooks(on_block=on_block))

    assert recorder.order[:2] == ["quick_stop", "seal"], recorder.order
    (entry,) = store.list_runs()
    assert entry["status"] == RunStatus.ABORTED
    assert entry["reason"] == "aborted: a bug in a block consumer"
    assert entry["samples"] == sum(blocks)  # every block handed out was kept
    assert np.all(np.diff(store.read(entry["id"]).t) > 0)


# ---- the process, as a user runs it: signals -------------------------------------------------------


def realtime_rig_file(tmp_path: Path, name: str) -> Path:
    """A copy of configs/rigs/NAME.yaml paced to the wall clock (a speed sweep then lasts ~18 s)."""
    config = yaml.safe_load((RIG_DIR / f"{name}.yaml").read_text())
    config["pace"] = "realtime"
    path = tmp_path / f"{name}-realtime.yaml"
    path.write_text(yaml.safe_dump(config))
    return path


def hdrig(home: Path, *args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "HDRIG_HOME": str(home)}
    return subprocess.run(
        [sys.executable, "-m", "rig", *args],
        capture_output=True,
        text=True,
        cwd=REPO_ROOT,
        env=env,
        timeout=300,
    )


def start_run(home: Path, rig_file: Path, *options: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "rig", "run", "speed-sweep", "--rig", str(rig_file), "-q", *options],
        env={**os.environ, "HDRIG_HOME": str(home)},
        cwd=REPO_ROOT,
        text=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )


def wait_until_recording(child: subprocess.Popen[str], home: Path, samples: int = 1000) -> int:
    """Wait until `samples` of the run are on disk; the samples flushed by then."""
    deadline = time.monotonic() + START_TIMEOUT_S
    flushed = 0
    while flushed < samples and time.monotonic() < deadline and child.poll() is None:
        time.sleep(0.05)
        if (home / "catalog.sqlite").exists():
            flushed = max((r["samples"] for r in RunStore(home).list_runs()), default=0)
    assert child.poll() is None, f"the run ended before it could be hit: {child.communicate()[1]}"
    assert flushed >= samples, f"{samples} samples did not reach the store within {START_TIMEOUT_S} s"
    return flushed


def stopped_in_the_can_log(run_dir: Path) -> bool:
    """Whether the last command the drive was sent says stop: the last RPDO's controlword is not
    `enable operation` (quick stop 0x0002, shutdown 0x0006, disable 0x0000), or an NMT STOP followed it."""
    last_controlword, nmt_stop_after = None, False
    for message in can.LogReader(run_dir / RAW_CAN_LOG):
        if message.arbitration_id == RPDO and len(message.data) >= 2:
            last_controlword = int.from_bytes(message.data[:2], "little")
            nmt_stop_after = False
        elif message.arbitration_id == NMT and message.data[:1] == b"\x02":
            nmt_stop_after = True
    assert last_controlword is not None, "no RPDO in the raw CAN log"
    return nmt_stop_after or last_controlword & ENABLE_OPERATION != ENABLE_OPERATION


def no_traceback(stderr: str) -> None:
    assert "Traceback" not in stderr, stderr


@pytest.mark.parametrize(("sig", "status"), [(signal.SIGTERM, 143), (signal.SIGHUP, 129)])
def test_sigterm_and_sighup_quick_stop_the_drive_then_keep_the_run_aborted(
    tmp_path: Path, sig: signal.Signals, status: int
) -> None:
    home = tmp_path / "home"
    child = start_run(home, realtime_rig_file(tmp_path, "virtual-can"))
    try:
        flushed = wait_until_recording(child, home)
        child.send_signal(sig)
        _, stderr = child.communicate(timeout=60)
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()

    no_traceback(stderr)
    assert child.returncode == status, stderr
    (entry,) = RunStore(home).list_runs()
    # The reason names what stopped it (the run's reader can tell a signal from an operator's stop).
    assert (entry["status"], entry["reason"]) == ("aborted", f"aborted: {sig.name}")
    assert entry["samples"] >= flushed and len(RunStore(home).read(entry["id"])) == entry["samples"]
    assert stopped_in_the_can_log(Path(entry["path"]).parent)


STALL_S = 3.0  # the loop's thread sleeps this long mid-run, the drive enabled and turning
EMCY, HOST_HEARTBEAT = 0x080 + NODE, 0x700 + 127  # the drive's EMCY; the host's heartbeat (host_node_id)
TPDO1 = 0x180 + NODE  # the statusword first (drivers.canopen_config.tpdo_layouts)


@pytest.mark.usefixtures("quiet_heap")
def test_a_stalled_control_loop_is_stopped_by_the_drives_watchdog(tmp_path: Path) -> None:
    """The loop's thread hangs (a hook that sleeps in it) with the process alive: the host's heartbeat
    is fed by the cycle, so it falls silent and the drive twin's consumer (0x1016) faults the drive
    before the loop comes back; the run then ends aborted with that fault, its rows kept."""
    config = load_rig_config("virtual-can").model_copy(update={"pace": "realtime"})
    settings = config.extra["canopen"]
    loop_timeout_s = settings["loop_timeout_ms"] / 1000.0
    consumer_timeout_s = settings["host_heartbeat_timeout_ms"] / 1000.0
    assert loop_timeout_s + consumer_timeout_s < STALL_S  # else the stall would not be seen
    store = RunStore(tmp_path / "home")
    blocks: list[int] = []

    def on_block(run_id: str, block: Block) -> None:
        blocks.append(len(block["t"]))
        if len(blocks) == 3:  # mid-program: the settle is done and the sweep's first speed turns
            time.sleep(STALL_S)

    outcome = run_experiment("speed-sweep", config, store=store, hooks=RunHooks(on_block=on_block))

    assert outcome.status == RunStatus.ABORTED
    assert outcome.reason is not None and "EMCY 0x8130" in outcome.reason, outcome.reason
    assert "control loop stalled" in outcome.reason, outcome.reason
    (entry,) = store.list_runs()
    assert entry["samples"] == sum(blocks) == len(store.read(entry["id"]))

    # The raw CAN log: the last RPDO before the stall, the host's heartbeats, the drive's EMCY and FAULT.
    assert outcome.run_dir is not None
    frames = list(can.BLFReader(outcome.run_dir / RAW_CAN_LOG))
    rpdo_times = [m.timestamp for m in frames if m.arbitration_id == RPDO]
    gaps = np.diff(rpdo_times)
    stalled_at = rpdo_times[int(np.argmax(gaps))]  # the last cycle before the stall
    resumed_at = stalled_at + float(np.max(gaps))
    assert np.max(gaps) >= STALL_S
    emcy = [m for m in frames if m.arbitration_id == EMCY and m.timestamp > stalled_at]
    assert emcy and int.from_bytes(emcy[0].data[:2], "little") == EMCY_HEARTBEAT
    # The drive stopped by itself while the loop still slept: after its consumer's timeout without a
    # heartbeat, and the heartbeat withheld once the loop had not cycled for loop_timeout_ms. (Its
    # timestamps are the host's wall clock at send and receive, in one process: no offset between them.)
    reacted_s = emcy[0].timestamp - stalled_at
    assert consumer_timeout_s <= reacted_s < resumed_at - stalled_at, reacted_s
    heartbeats = [m.timestamp for m in frames if m.arbitration_id == HOST_HEARTBEAT]
    silent = [t for t in heartbeats if stalled_at + loop_timeout_s + 0.1 < t < emcy[0].timestamp]
    assert not silent, "the host's heartbeat went on while the loop was stalled"
    statuswords = [
        int.from_bytes(m.data[:2], "little")
        for m in frames
        if m.arbitration_id == TPDO1 and m.timestamp > resumed_at
    ]
    assert statuswords and decode_statusword(statuswords[0]) == State.FAULT
    assert stopped_in_the_can_log(outcome.run_dir)


@pytest.mark.usefixtures("quiet_heap")
def test_a_daq_that_drops_out_mid_run_stops_the_motor_and_aborts_the_run(tmp_path: Path) -> None:
    """The DAQ board goes silent mid-run (its twin closes its line): the next chunk's wait for θ_l ends
    in a device fault, the drive is quick-stopped and the run ends aborted with what it recorded.
    The twins run in this process here, so the test can close the DAQ twin's line itself."""
    data = load_rig_config("virtual-can").model_dump() | {"pace": "realtime", "twins": "in-process"}
    config = RigConfig.model_validate(data)
    store = RunStore(tmp_path / "home")
    rig = open_rig(config)
    assert isinstance(rig, VirtualCanRig)
    blocks: list[int] = []

    def on_block(run_id: str, block: Block) -> None:
        blocks.append(len(block["t"]))
        if len(blocks) == 3:  # mid-program, the drive enabled and turning
            rig.daq_twin.close()

    try:
        outcome = run_experiment(
            "speed-sweep", config, store=store, rig=rig, hooks=RunHooks(on_block=on_block)
        )
    finally:
        rig.close()
    assert outcome.status == RunStatus.ABORTED
    assert outcome.reason is not None and "DAQ on" in outcome.reason, outcome.reason
    (entry,) = store.list_runs()
    assert entry["samples"] == sum(blocks) == len(store.read(entry["id"]))
    assert outcome.run_dir is not None and stopped_in_the_can_log(outcome.run_dir)


# ---- the store: nothing lost, nothing overwritten, nothing hidden -----------------------------------


def test_the_first_rows_reach_the_disk_long_before_the_flush_interval(tmp_path: Path) -> None:
    store = RunStore(tmp_path / "home")
    writer = store.open_run(
        "pulse", "sim", None, None, ["t", "u"], {}, flush_interval_s=60.0, background=True
    )
    writer.append({"t": np.arange(10) / 1000.0, "u": np.zeros(10)})
    # FIRST_FLUSH_S is 0.25 s; 10 s is a deadline for a loaded machine, still far below the 60 s interval.
    deadline = time.monotonic() + 10.0
    while store.get(writer.run_id)["samples"] < 10 and time.monotonic() < deadline:
        time.sleep(0.02)
    assert store.get(writer.run_id)["samples"] == 10
    writer.finish()


class _SlowFlushStore(RunStore):
    """A store whose runs flush only every minute: what reaches the disk sooner came by a segment's end."""

    def open_run(self, *args: Any, **kwargs: Any) -> Any:
        return super().open_run(*args, **{**kwargs, "flush_interval_s": 60.0})


def test_each_segment_is_on_disk_once_it_ends_even_in_virtual_time(tmp_path: Path) -> None:
    store = _SlowFlushStore(tmp_path / "home")
    rig = SimRig(sim_config())
    ends: list[tuple[int, int]] = []  # (rows recorded before a segment began, rows on disk by then)

    def on_segment(run_id: str, segment: Any) -> None:
        recorded = sum(blocks)
        deadline = time.monotonic() + 10.0  # a deadline for a loaded machine; the flush is asked at once
        while store.get(run_id)["samples"] < recorded and time.monotonic() < deadline:
            time.sleep(0.01)
        ends.append((recorded, store.get(run_id)["samples"]))

    blocks: list[int] = []
    hooks = RunHooks(on_block=lambda run_id, block: blocks.append(len(block["t"])), on_segment=on_segment)
    run_experiment("speed-sweep", rig.config, {"hold_s": 0.3}, store=store, rig=rig, hooks=hooks)
    assert len(ends) > 2
    assert all(on_disk == recorded for recorded, on_disk in ends), ends


FILE_SIZE_LIMIT_BYTES = 200_000  # parts of a speed sweep fit (~60 kB each); its sealed data file does not


def _file_size_limited() -> None:
    """In the child: files stop growing at FILE_SIZE_LIMIT_BYTES, as on a full disk (write() fails with
    EFBIG; SIGXFSZ, which would kill the process instead, is ignored). Unprivileged, and no disk fills."""
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (FILE_SIZE_LIMIT_BYTES, FILE_SIZE_LIMIT_BYTES))


def test_a_full_disk_ends_the_run_aborted_in_one_line_with_the_rows_written_before(tmp_path: Path) -> None:
    home = tmp_path / "home"
    result = subprocess.run(
        # 17 s of rig time, as the default sweep was: the catalog's write-ahead log grows with a run's
        # progress records and must stay under the limit for the run to end as aborted (a full disk that
        # stops the catalog too leaves it interrupted, a later check's business); the data does not fit.
        [
            sys.executable,
            "-m",
            "rig",
            "run",
            "speed-sweep",
            "--rig",
            "sim",
            "-q",
            "--set",
            "speeds_rad_s=[2,10,50]",
        ],
        capture_output=True,
        text=True,
        cwd=REPO_ROOT,
        env={**os.environ, "HDRIG_HOME": str(home)},
        preexec_fn=_file_size_limited,
        timeout=300,
    )
    (entry,) = RunStore(home).list_runs()
    assert entry["status"] == RunStatus.ABORTED and "File too large" in entry["reason"], entry
    assert 0 < entry["samples"] == len(RunStore(home).read(entry["id"]))  # what reached the disk: readable
    no_traceback(result.stderr)
    assert result.returncode != 0 and result.stderr.count("\n") == 1, result.stderr


@pytest.fixture(scope="module")
def pulse_home(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    """A store with one complete pulse run on `sim` (virtual time: a second or two)."""
    home = tmp_path_factory.mktemp("home")
    result = hdrig(home, "run", "pulse", "--rig", "sim", "-q", "--json")
    assert result.returncode == 0, result.stderr
    return home, str(json.loads(result.stdout)["id"])


def test_export_into_a_run_folder_of_the_store_is_refused(pulse_home: tuple[Path, str]) -> None:
    home, run_id = pulse_home
    data = home / "runs" / run_id / "data.parquet"
    before = data.read_bytes()
    for out in (data, home / "runs" / run_id / ".." / run_id / "copy.parquet", home / "runs"):
        result = hdrig(home, "runs", "export", run_id, "--format", "parquet", "--out", str(out))
        assert result.returncode == 2, result.stderr
        assert result.stderr.count("\n") == 1 and "inside the run store's own files" in result.stderr
    assert data.read_bytes() == before


ANALYSIS_KILLED = """
import os, signal, sys
from rig.experiments.pulse import Pulse
def killed(*args, **kwargs):
    os.kill(os.getpid(), signal.SIGKILL)  # as a power cut or the OOM killer would, mid-analysis
Pulse.analyze = killed
from rig.cli import main
sys.exit(main(["run", "pulse", "--rig", "sim", "-q"]))
"""


def test_a_killed_analysis_is_listed_interrupted_and_runs_analyze_makes_it(tmp_path: Path) -> None:
    home = tmp_path / "home"
    env = {**os.environ, "HDRIG_HOME": str(home), "PYTHONPATH": str(REPO_ROOT)}
    child = subprocess.run([sys.executable, "-c", ANALYSIS_KILLED], env=env, cwd=REPO_ROOT, timeout=300)
    assert child.returncode == -signal.SIGKILL

    listed = hdrig(home, "runs", "list")
    assert listed.returncode == 0 and "analysis: interrupted" in listed.stdout, listed.stdout
    (entry,) = json.loads(hdrig(home, "runs", "list", "--json").stdout)
    assert (entry["status"], entry["analysis"], entry["metrics"]) == ("complete", "interrupted", {})

    again = hdrig(home, "runs", "analyze", entry["id"], "--json")
    assert again.returncode == 0, again.stderr
    document = json.loads(again.stdout)
    assert document["analysis"] == "done" and document["metrics"] and document["artifacts"]
    assert json.loads(hdrig(home, "runs", "show", entry["id"], "--json").stdout)["analysis"] == "done"


# ---- one process per hardware rig --------------------------------------------------------------------

BENCH = """
import sys, time
import numpy as np
from rig import interface
from rig.config import load_rig_config

class Bench(interface.Rig):  # a hardware backend (source "hardware") that touches no device
    def _run_cycles(self, mode, setpoint, tau_ext):
        return {}, 0
    def _enable(self): pass
    def _disable(self): pass
    def _quick_stop(self): pass
    gear_ratio = 0.01
    torque_constant_nm_per_a = 0.03

interface.backend_class = lambda name: Bench
config = load_rig_config("sim").model_copy(update={"name": sys.argv[1], "backend": "bench"})
rig = interface.open_rig(config)
print("open", flush=True)
if sys.argv[2] == "hold":
    time.sleep(600)
rig.close()
print("closed", flush=True)
"""


def test_a_second_process_on_a_hardware_rig_is_told_which_pid_has_it(tmp_path: Path) -> None:
    name = f"bench-{os.getpid()}-{time.monotonic_ns()}"  # a lock of this test's own
    env = {**os.environ, "PYTHONPATH": str(REPO_ROOT)}
    holder = subprocess.Popen(
        [sys.executable, "-c", BENCH, name, "hold"], env=env, stdout=subprocess.PIPE, text=True
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "open"
        second = subprocess.run(
            [sys.executable, "-c", BENCH, name, "once"], env=env, capture_output=True, text=True, timeout=120
        )
        assert second.returncode != 0
        assert f"rig '{name}' in use by pid {holder.pid}" in second.stderr
    finally:
        holder.kill()
        holder.wait()
    # The kernel dropped the lock with its holder (killed, not closed): the rig opens again.
    again = subprocess.run(
        [sys.executable, "-c", BENCH, name, "once"], env=env, capture_output=True, text=True, timeout=120
    )
    assert again.stdout.split() == ["open", "closed"], again.stderr


def test_the_simulated_rig_takes_no_lock() -> None:
    from rig.interface import open_rig

    first, second = open_rig(sim_config()), open_rig(sim_config())  # one process, two sim rigs: both open
    first.close()
    second.close()
    assert first._lock is None and second._lock is None


# ---- bad input: one line naming what and where, exit 2, never a traceback ---------------------------


@pytest.fixture(scope="module")
def bad_files(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("bad")
    (folder / "latin1.yaml").write_bytes("name: Messstand Köln\n".encode("latin-1"))
    (folder / "deep.json").write_text("[" * 3000 + "]" * 3000)
    (folder / "deep.yaml").write_text("motor: " + "{a: " * 3000 + "1" + "}" * 3000 + "\n")
    (folder / "aliases.yaml").write_text(
        "a: &a [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]\n"
        + "".join(
            f"{c}: &{c} [{', '.join(['*' + p] * 10)}]\n" for p, c in zip("abcdef", "bcdefg", strict=True)
        )
    )
    (folder / "huge.yaml").write_text("# padding\n" * 200_000)
    (folder / "a-folder.yaml").mkdir()
    # A SYNC period of 5e9 µs: more than the drive's 0x1006 (UNSIGNED32) holds.
    slow = yaml.safe_load((RIG_DIR / "virtual-can.yaml").read_text()) | {"sample_rate_hz": 0.0002}
    (folder / "slow-rig.yaml").write_text(yaml.safe_dump(slow))
    return folder


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["model", "show", "{bad}/latin1.yaml"], "not UTF-8 text (byte 0xf6 at offset 17)"),
        (["model", "show", "{bad}/deep.json"], "nested deeper than a model file is"),
        (["model", "show", "{bad}/deep.yaml"], "nested deeper than a model file is"),
        (["model", "show", "{bad}/aliases.yaml"], "more than 100000 values"),
        (["model", "show", "{bad}/huge.yaml"], "too large for a model file"),
        (["model", "show", "{bad}/a-folder.yaml"], "is a folder, not a model file"),
        (["run", "pulse", "--rig", "{bad}/latin1.yaml"], "not UTF-8 text"),
        (["run", "pulse", "--rig", "{bad}/deep.yaml"], "nested deeper than a rig file is"),
        (["run", "pulse", "--rig", "{bad}/a-folder.yaml"], "is a folder, not a rig file"),
        (["run", "pulse", "--rig", "sim", "--set", "hold_s=[1,"], "the value is not YAML"),
        (
            ["run", "pulse", "--rig", "{bad}/slow-rig.yaml"],
            "asks what the drive's EDS refuses: 0x1006:00 = 5000000000",
        ),
        (["fit", "--data", "latest", "--model", "seed", "--out", "{bad}/no/such/m.yaml"], "does not exist"),
    ],
)
def test_bad_input_is_one_line_naming_it(bad_files: Path, tmp_path: Path, args: list[str], says: str) -> None:
    result = hdrig(tmp_path / "home", *(a.replace("{bad}", str(bad_files)) for a in args))
    no_traceback(result.stderr)
    assert result.returncode == 2, result.stderr
    assert result.stderr.count("\n") == 1 and says in result.stderr, result.stderr


def test_fit_on_an_aborted_run_is_refused_before_it_runs(tmp_path: Path) -> None:
    home = tmp_path / "home"
    aborted = hdrig(home, "run", "speed-sweep", "--rig", "sim", "-q", "--set", "tau_ext_nm=50", "--json")
    assert aborted.returncode == 3, aborted.stderr
    run_id = json.loads(aborted.stdout)["id"]
    result = hdrig(home, "fit", "--data", run_id, "--model", "seed", "--out", str(tmp_path / "m.yaml"), "-q")
    no_traceback(result.stderr)
    assert result.returncode == 2 and f"run {run_id} is aborted: travel limit" in result.stderr


def test_an_unusable_store_folder_or_a_damaged_catalog_is_one_line(tmp_path: Path) -> None:
    a_file = tmp_path / "a-file"
    a_file.write_text("")
    result = hdrig(a_file, "runs", "list")
    no_traceback(result.stderr)
    assert result.returncode == 2 and "cannot hold the run store (Not a directory)" in result.stderr

    home = tmp_path / "home"
    home.mkdir()
    (home / "catalog.sqlite").write_bytes(b"this is no SQLite file, a disk error wrote it" * 100)
    result = hdrig(home, "runs", "list")
    no_traceback(result.stderr)
    assert result.returncode == 2 and "the run catalog is damaged (file is not a database)" in result.stderr


# ---- garbage in run files: refused in one line, with the limit ------------------------------------


def _csv_run(folder: Path, text: str, meta: dict[str, Any] | None = None) -> Path:
    path = folder / "run.csv"
    path.write_text(text)
    if meta is not None:
        (folder / "run.csv.json").write_text(json.dumps(meta))
    return path


GOOD_CSV = "t,u,i_cmd,theta_m\n0,0,0,0\n0.001,1,0.1,0\n0.002,1,0.1,0.001\n"


@pytest.mark.parametrize(
    ("text", "meta", "says"),
    [
        (GOOD_CSV.replace("0.001,1,0.1,0\n", "0.001,1,1e300,0\n"), None, "column 'i_cmd' row 1 is 1e+300 A"),
        (
            GOOD_CSV,
            {"sample_rate_hz": -5},
            "metadata sample_rate_hz is -5; it must be a number of Hz in (0, 1e+07]",
        ),
        (GOOD_CSV, {"sample_rate_hz": "fast"}, "metadata sample_rate_hz is 'fast'"),
        (GOOD_CSV.replace("0.002,", "0.001,"), None, "column 't' must be strictly increasing; row 2"),
        ("t;u;theta_m\n0;0;0\n0,001;1;0\n", None, "the columns look separated by ';'"),
    ],
)
def test_garbage_in_a_run_file_is_refused_in_one_line(
    tmp_path: Path, text: str, meta: dict[str, Any] | None, says: str
) -> None:
    path = _csv_run(tmp_path, text, meta)
    with pytest.raises(UserInputError) as refused:
        read_run(path)
    assert says in str(refused.value) and "\n" not in str(refused.value), refused.value
    result = hdrig(
        tmp_path / "home", "simulate", "--model", "seed", "--input-file", str(path), "--out", "x.csv"
    )
    no_traceback(result.stderr)
    assert result.returncode == 2 and result.stderr.count("\n") == 1 and says in result.stderr, result.stderr


def test_a_run_of_plausible_values_is_still_read(tmp_path: Path) -> None:
    # Magnitudes a real long run reaches (10 h at 600 rad/s on the motor; a Unix-epoch time base) pass.
    t0 = 1.7e9
    text = f"t,i_cmd,theta_m\n{t0},9.5,2.1e7\n{t0 + 0.001},-9.5,2.1e7\n"
    run = read_run(_csv_run(tmp_path, text, {"sample_rate_hz": 1000}))
    assert run.sample_rate_hz == 1000 and run["theta_m"][0] == 2.1e7


def test_a_simulation_too_long_to_write_is_refused_before_its_first_step(tmp_path: Path) -> None:
    with pytest.raises(UserInputError, match=r"at most 1e\+08 samples"):
        simulate_stream(load_model("seed"), 1.0, 1e9)  # 1e12 samples at 1 kHz: ~80 TB
    out = tmp_path / "long.parquet"
    result = hdrig(
        tmp_path / "home",
        "simulate",
        "--model",
        "seed",
        "--input",
        "1",
        "--duration",
        "1e9",
        "--out",
        str(out),
    )
    no_traceback(result.stderr)
    assert result.returncode == 2 and result.stderr.count("\n") == 1, result.stderr
    assert "duration 1e+09 s is 1e+12 samples at 1000 Hz" in result.stderr and not out.exists()
    # The bound leaves room for long runs: 10 h at 1 kHz is accepted (and not run here).
    assert simulate_stream(load_model("seed"), 1.0, 36_000.0).rows == 36_000_000
