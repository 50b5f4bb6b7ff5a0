"""The twins on a virtual CAN bus behind the real drivers: `backend: virtual-can`.

It builds, in this process, the CiA 402 drive twin (`Cia402Twin`, running the rig config's `model:`)
on a python-can `virtual` channel of its own (the config's `canopen.channel` plus a suffix unique to
the rig instance, so rigs and tests never share a bus; another interface, a Linux vcan, is used as
given), and the DAQ board's twin (`DaqTwin`) on a pty,
measuring that very plant (`Cia402Twin.measured`). On them it opens a `HardwareRig`: the same servo
driver, DAQ driver, alignment and envelope as on a bench, so a run exercises the real driver code end
to end. With `twins: process` (configs/rigs/virtual-can.yaml) both twins run in a child process
instead (`sim_backend.twin_process`) on a loopback TCP bus, and the child hands back the drive twin's
sample of each SYNC through a shared file (`PlantLog`): the rows and `plant_log` are as in one process.

Time. In virtual time (`pace: virtual`, the default) the servo sends each SYNC as soon as the last
one is answered (its `canopen.pace` is set from the rig's `pace`), and each SYNC steps the plant one
cycle; the rows' `t` is the plant's own time of each sample (the twin's, a sim-only convenience: a
bench has the SYNC's host time), so runs replay exactly. The DAQ twin runs on the wall clock, as a
board does; in virtual time the loop outpaces it, so θ_l is aligned to within the few cycles that go
by per DAQ sample. `pace: realtime` holds the 1 ms SYNC grid, and θ_l is then aligned as on a bench.

Load. A segment's τ_ext is set on the twin (`Cia402Twin.tau_ext_nm`) before each cycle's SYNC: a
sim-only convenience, as no CAN object carries a load torque.

The drive's constants are the model's: gear ratio, resistance and back-EMF for the u estimate, and
the torque constant (which replaces the `canopen.scaling` one, so that any `model:` runs right).
`close()` ends every thread: the twin's notifier, heartbeat and watch, the servo's notifier and
heartbeat, the DAQ twin's device thread, the DAQ driver's reader and the rig's clock thread.
"""

from __future__ import annotations

import contextlib
import json
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import IO, Final, Literal

from pydantic import Field

from drivers.can_bus import BusSettings, open_bus
from drivers.canopen_config import CanopenSettings, DriveLimits
from drivers.canopen_servo import CanopenServo, Feedback
from drivers.hardware_rig import (
    BenchConstants,
    DaqStreamSettings,
    HardwareConfigError,
    HardwareRig,
    daq_section,
)
from drivers.serial_daq import SerialDaq
from model.params import HarmonicDriveModel, load_model
from rig.config import RigConfig
from sim_backend.cia402_twin import LOAD_COB_ID, Cia402Twin, LoadTwin, load_twin_for
from sim_backend.daq_twin import DaqTwin, analog_readings
from sim_backend.twin_process import PlantLog, serve_twins, watchdog_grace_s

TWINS: Final = ("in-process", "process")
"""The rig file's `twins:`: in this process (threads), or in a child process on a loopback TCP bus."""
CHILD_START_TIMEOUT_S: Final = 240.0
"""The child imports numpy, numba and canopen and loads the drive's compiled loop: under a second on a
quiet machine, several times that on a loaded one. After a change to a compiled kernel it compiles it
first, as a twin in this process would, which on a loaded machine can take over a minute. About 3 × the
slowest cold start measured (figures: docs/BENCHMARKS.md, "Figures behind design choices in the code"):
a child that is merely slow is not taken for a dead one."""


class DaqTwinSettings(DaqStreamSettings):
    """The virtual rig's `daq:` section: the stream, and the twin's line and clock (no url: the twin
    serves a pty of its own)."""

    rate_hz: float = Field(default=2000.0, gt=0, le=20000, description="DAQ sample rate [Hz]")
    samples_per_frame: int = Field(
        default=1, ge=1, le=100, description="samples per frame; 1: each sample reads the plant afresh"
    )
    transport: Literal["pty", "socket"] = Field(default="pty", description="the twin's line")
    drift_ppm: float = Field(default=0.0, description="how much faster the twin's clock runs [ppm]")


class VirtualCanRig(HardwareRig):
    """`backend: virtual-can`: a `HardwareRig` on the drive twin and the DAQ twin, in this process."""

    source = "sim"

    def __init__(self, config: RigConfig, model: HarmonicDriveModel | None = None) -> None:
        self.model: HarmonicDriveModel = model if model is not None else load_model(config.model or "seed")
        if "hardware" in config.extra:
            raise HardwareConfigError(
                f"rig {config.name!r}: the virtual-can backend takes its `hardware:` constants from"
                " the model: leave the section out"
            )
        stream = daq_section(config, DaqTwinSettings) or DaqTwinSettings()
        assert isinstance(stream, DaqTwinSettings)
        settings = self._bus_settings(config)
        motor = self.model.motor
        constants = BenchConstants(
            gear_ratio=self.model.mechanics.r,
            torque_constant_nm_per_a=motor.K_m,
            resistance_ohm=motor.R,
            back_emf_v_s_rad=motor.K_b,
            daq=stream,
        )
        self.twin: Cia402Twin | None = None
        self.load_twin: LoadTwin | None = None
        """The load drive's twin (a dynamometer bench, `canopen.drives` with role `load`), in this process."""
        self.daq_twin: DaqTwin | None = None
        self.child: subprocess.Popen[str] | None = None
        """The twins' process, when the rig file says `twins: process`."""
        self.child_plant_log: PlantLog | None = None
        """The child's drive twin's sample of each SYNC (`twin_process.PlantLog`), in a temp dir."""
        self.child_start_s: float | None = None
        """From starting the child to its twins answering [s] (mostly imports: numba, canopen)."""
        self.plant_log: list[dict[str, float]] | None = None
        """When a list, the drive twin's own sample of each recorded cycle is appended (true θ_l and the
        rest, `SAMPLE_COLUMNS`): tests compare what the drivers measured with what the plant did."""
        twins = config.extra.get("twins", "in-process")
        if twins not in TWINS:
            raise HardwareConfigError(
                f"rig {config.name!r}: twins {twins!r} is not one of {', '.join(TWINS)}"
            )
        if twins == "process":
            self._open_in_child(config, settings, constants, stream)
            return
        servo_daq: SerialDaq | None = None
        try:
            bus = BusSettings(
                interface=settings.interface, channel=settings.channel, bitrate=settings.bitrate
            )
            self.twin = Cia402Twin(open_bus(bus), settings.node_id, self.model, config, settings.eds_path())
            self.load_twin = load_twin_for(self.twin, settings)
            self.daq_twin = DaqTwin.from_sensors(
                self.twin.measured,
                config.sensors,
                transport=stream.transport,
                drift_ppm=stream.drift_ppm,
                source_clock="host",
                analog=analog_readings(self.twin.measured, stream.channels),
            )
            servo_daq = SerialDaq(self.daq_twin.url, timeout_s=stream.timeout_s, clock=time.monotonic)
            servo = CanopenServo(settings, DriveLimits.from_rig_config(config), 1.0 / config.sample_rate_hz)
        except BaseException:
            if servo_daq is not None:
                servo_daq.close()
            self._close_twins()
            raise
        self._open_drivers(config, constants, servo, servo_daq, None if self.load_twin else self._set_load)

    def _open_drivers(
        self,
        config: RigConfig,
        constants: BenchConstants,
        servo: CanopenServo,
        daq: SerialDaq,
        load: Callable[[float], None] | None,
    ) -> None:
        """The drivers composed into the rig, wherever the twins run; the twins closed if that fails."""
        try:
            super().__init__(
                config, constants=constants, servo=servo, daq=daq, load=load, sample_clock=self._plant_time
            )
        except BaseException:
            self._close_twins()  # HardwareRig released the servo and the DAQ driver
            raise

    def _open_in_child(
        self,
        config: RigConfig,
        settings: CanopenSettings,
        constants: BenchConstants,
        stream: DaqTwinSettings,
    ) -> None:
        """The twins in a child process (`sim_backend.twin_process`), the drivers here on its bus."""
        self._load_sent: float | None = None
        self._stderr_lines: list[str] = []
        self._child_grace_s = watchdog_grace_s(config) + 2.0  # before HardwareRig keeps the config
        log_dir = Path(tempfile.mkdtemp(prefix="hdrig-twins-"))
        try:
            self.child_plant_log = PlantLog(log_dir / "plant.log", create=True)
        except BaseException:
            shutil.rmtree(log_dir, ignore_errors=True)
            raise
        started_s = time.monotonic()
        self.child = subprocess.Popen(
            [sys.executable, "-m", "sim_backend.twin_process"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        servo_daq: SerialDaq | None = None
        try:
            assert self.child.stdin is not None and self.child.stdout is not None
            spec = {
                "config": config.model_dump(mode="json"),
                "model": self.model.to_dict(),
                "plant_log": str(self.child_plant_log.path),
            }
            self.child.stdin.write(json.dumps(spec) + "\n")
            self.child.stdin.flush()
            where = json.loads(self._first_line(self.child.stdout))
            self.child_start_s = time.monotonic() - started_s
            threading.Thread(target=self._keep_stderr, name="twin stderr", daemon=True).start()
            settings = settings.model_copy(update={"interface": "hdrig-tcp", "channel": where["can"]})
            servo_daq = SerialDaq(where["daq"], timeout_s=stream.timeout_s, clock=time.monotonic)
            servo = CanopenServo(settings, DriveLimits.from_rig_config(config), 1.0 / config.sample_rate_hz)
        except BaseException:
            if servo_daq is not None:
                servo_daq.close()
            self._close_twins()
            raise
        has_load_drive = settings.load_entry is not None
        self._open_drivers(config, constants, servo, servo_daq, None if has_load_drive else self._send_load)

    def _first_line(self, stdout: IO[str]) -> str:
        """The child's JSON line, within CHILD_START_TIMEOUT_S; its stderr in the error otherwise."""
        line: list[str] = []
        reader = threading.Thread(target=lambda: line.append(stdout.readline()), daemon=True)
        reader.start()
        reader.join(CHILD_START_TIMEOUT_S)
        if not line or not line[0].strip():
            assert self.child is not None
            self.child.kill()
            _out, err = self.child.communicate()
            said = err.strip() or f"no answer in {CHILD_START_TIMEOUT_S:g} s"
            raise RuntimeError(f"the twins' process did not start: {said}")
        return line[0]

    def _keep_stderr(self) -> None:
        child = self.child
        if child is not None and child.stderr is not None:
            for line in child.stderr:
                self._stderr_lines.append(line.rstrip())

    @property
    def twin_log(self) -> list[str]:
        """What the twins' process has written to stderr so far (its watchdog says so there)."""
        return list(getattr(self, "_stderr_lines", []))

    def _send_load(self, tau_ext_nm: float) -> None:
        """The load torque to the twin in the other process, as the sim-only frame, when it changes."""
        if tau_ext_nm != self._load_sent and self.servo.network is not None:
            self.servo.network.send_message(LOAD_COB_ID, struct.pack("<d", tau_ext_nm))
            self._load_sent = tau_ext_nm

    @classmethod
    def serve_twins(cls, config: RigConfig, port: int, announce: Callable[[str], None]) -> None:
        """`hdrig twin`: this rig's twins in this process until SIGINT/SIGTERM (`serve_twins`)."""
        stop = threading.Event()
        signal.signal(signal.SIGTERM, lambda *_: stop.set())
        signal.signal(signal.SIGINT, lambda *_: stop.set())
        serve_twins(config, None, port, announce, stop)

    def _bus_settings(self, config: RigConfig) -> CanopenSettings:
        """The `canopen:` section on a channel of this rig's own, paced by the rig, scaled by the model."""
        settings = CanopenSettings.from_rig_config(config)
        channel = settings.channel
        if settings.interface == "virtual":
            channel = f"{settings.channel}-{uuid.uuid4().hex[:8]}"
        scaling = settings.scaling.model_copy(update={"torque_constant_nm_per_a": self.model.motor.K_m})
        return settings.model_copy(
            update={"channel": channel, "pace": config.pace == "realtime", "scaling": scaling}
        )

    def _set_load(self, tau_ext_nm: float) -> None:
        assert self.twin is not None
        self.twin.tau_ext_nm = tau_ext_nm

    def _plant_time(self, feedback: Feedback) -> float:
        """The plant time of the sample the drive twin just reported (its last SYNC's row), in this
        process or the child's (written before the answer went out)."""
        if self.twin is not None:
            sample = self.twin.last_sample
        else:
            assert self.child_plant_log is not None
            if self.plant_log is None:  # its time alone: no dict of the whole sample every cycle
                t_s = self.child_plant_log.latest_t()
                assert t_s is not None  # the drive answered a SYNC: its sample is in
                return t_s
            latest = self.child_plant_log.latest()
            assert latest is not None
            sample = latest
        if self.plant_log is not None:
            self.plant_log.append(dict(sample))
        return sample["t"]

    def _close(self) -> None:
        try:
            super()._close()  # the servo first: it says goodbye to the drive over SDO
        finally:
            self._close_twins()

    def _close_twins(self) -> None:
        daq_twin, twin, child, load_twin = self.daq_twin, self.twin, self.child, self.load_twin
        self.daq_twin, self.twin, self.child, self.load_twin = None, None, None, None
        try:
            if child is not None:
                _end_child(child, self._child_grace_s)
        finally:
            plant_log, self.child_plant_log = self.child_plant_log, None
            if plant_log is not None:  # the rows took what they needed; the child has ended
                plant_log.close()
                shutil.rmtree(plant_log.path.parent, ignore_errors=True)
        try:
            if daq_twin is not None:
                daq_twin.close()
        finally:
            try:
                if load_twin is not None:
                    load_twin.close()
            finally:
                if twin is not None:
                    twin.close()


def _end_child(child: subprocess.Popen[str], timeout_s: float) -> None:
    """Close the child's stdin (it ends after its watchdog grace) and wait; SIGTERM, then kill, if not."""
    if child.stdin is not None and not child.stdin.closed:
        with contextlib.suppress(BrokenPipeError):  # it has gone already
            child.stdin.close()
    child.terminate()  # the host is closing on purpose: no grace to wait for
    try:
        child.wait(timeout_s)
    except subprocess.TimeoutExpired:
        child.kill()
        child.wait()
