"""The twins of a virtual-can rig in a process of their own: `hdrig twin --rig RIG`, or the rig's child.

`serve_twins` builds the CiA 402 drive twin on a `CanHub` (drivers.tcp_can: a CAN bus on a loopback
TCP port) and the DAQ twin on a pty measuring the same plant, prints one line of JSON saying where
they are (`{"can": "127.0.0.1:PORT", "daq": "/dev/pts/N", "node_id": 1}`), and serves until told to
stop. Any CANopen master in another process reaches the drive with `can.Bus(interface="hdrig-tcp",
channel=...)`; the load torque comes as the sim-only frame `LOAD_COB_ID`.

Run as the virtual-can rig's child (`python -m sim_backend.twin_process`, the rig config and model as
JSON on stdin), it ends when its stdin closes (the rig closed it, or the rig's process died) — but
not before the drive's own watchdog has had its timeout to notice a silent host, so a host killed
mid-run is stopped by the drive, as on a bench, and the twin's log says so.

The plant log. In one process the rig reads the drive twin's own sample of each cycle (the plant's
time `t` for the row, and the truth a test compares the drivers' measurements with). Across
processes the child writes each SYNC's sample into a `PlantLog`: a file the host names (in a temp
dir of its own), mapped into both processes, a ring of the latest `PlantLog.SLOTS` samples. The child
writes a SYNC's sample before that SYNC's TPDOs go out (`Cia402Twin.on_sample`), so the host, once
answered, finds it there: no message, no wait, no system call per cycle. The file outlives the child,
so the samples of a child that died stay readable until the host closes.
"""

from __future__ import annotations

import json
import logging
import mmap
import operator
import signal
import struct
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any, Final

from drivers.canopen_config import CanopenSettings
from drivers.serial_daq import AnalogChannel
from drivers.tcp_can import CanHub
from model.params import HarmonicDriveModel, load_model
from rig.config import RigConfig
from rig.interface import SAMPLE_COLUMNS
from rig.realtime import freeze_built, quiet_heap
from sim_backend.cia402_twin import Cia402Twin, load_twin_for
from sim_backend.daq_twin import DaqTwin, analog_readings

logger = logging.getLogger(__name__)

_COUNT = struct.Struct("<Q")
_SAMPLE = struct.Struct(f"<{len(SAMPLE_COLUMNS)}d")
_COLUMNS = operator.itemgetter(*SAMPLE_COLUMNS)  # a sample's values in column order, in one C call
_DOUBLE = struct.Struct("<d")
_T_OFFSET = SAMPLE_COLUMNS.index("t") * _DOUBLE.size  # of `t` within a sample


class PlantLog:
    """The drive twin's sample of each SYNC, shared by the twins' process (writer) and the host (reader).

    A file: the count of samples written (uint64), then a ring of `SLOTS` samples (SAMPLE_COLUMNS as
    float64). The writer puts a sample in its slot, then raises the count. The host reads the newest
    sample after its SYNC was answered; the child writes the next one only after the host's next SYNC,
    so the slot read is never being written (a slot is reused `SLOTS` SYNCs later).
    """

    SLOTS: Final = 4096
    """Samples kept: 4 s at 1 kHz. The host reads one per cycle; the ring only has to outlast a read."""
    SIZE_BYTES: Final = _COUNT.size + SLOTS * _SAMPLE.size

    def __init__(self, path: Path, create: bool = False) -> None:
        """Map the file at `path`; `create` makes it (empty, full size) first: the host does, then the
        child maps it."""
        if create:
            with path.open("xb") as f:
                f.truncate(self.SIZE_BYTES)
        with path.open("r+b") as f:
            self._map = mmap.mmap(f.fileno(), self.SIZE_BYTES)
        self.path = path

    @property
    def count(self) -> int:
        """Samples written so far."""
        count: int = _COUNT.unpack_from(self._map, 0)[0]
        return count

    def write(self, sample: dict[str, float]) -> None:
        """Append one SYNC's sample (a `Cia402Twin.last_sample`)."""
        count = self.count
        offset = _COUNT.size + (count % self.SLOTS) * _SAMPLE.size
        _SAMPLE.pack_into(self._map, offset, *_COLUMNS(sample))
        _COUNT.pack_into(self._map, 0, count + 1)

    def latest(self) -> dict[str, float] | None:
        """The newest sample, or None before the first SYNC."""
        count = self.count
        if not count:
            return None
        values = _SAMPLE.unpack_from(self._map, _COUNT.size + ((count - 1) % self.SLOTS) * _SAMPLE.size)
        return dict(zip(SAMPLE_COLUMNS, values, strict=True))

    def latest_t(self) -> float | None:
        """The newest sample's plant time `t` [s] alone (the host's every cycle), or None before the first."""
        count = self.count
        if not count:
            return None
        offset = _COUNT.size + ((count - 1) % self.SLOTS) * _SAMPLE.size + _T_OFFSET
        t_s: float = _DOUBLE.unpack_from(self._map, offset)[0]
        return t_s

    def close(self) -> None:
        self._map.close()


def serve_twins(
    config: RigConfig,
    model: HarmonicDriveModel | None = None,
    port: int = 0,
    announce: Callable[[str], None] = print,
    stop: threading.Event | None = None,
    plant_log: PlantLog | None = None,
) -> None:
    """Run the rig's drive and DAQ twins until `stop` is set (or SIGINT/SIGTERM); `announce` gets the
    JSON line saying where they are once they answer; `plant_log` gets the drive twin's sample of each
    SYNC."""
    settings = CanopenSettings.from_rig_config(config)
    model = model if model is not None else load_model(config.model or "seed")
    stop = stop or threading.Event()
    hub = CanHub(port)
    twin = daq = load_twin = None
    try:
        bus = hub.bus()
        twin = Cia402Twin(bus, settings.node_id, model, config, settings.eds_path())
        load_twin = load_twin_for(twin, settings)  # on the same network: the one SYNC steps both
        bus.deliver_directly(twin.network.listeners)  # one thread wake-up less per frame to the drive
        if plant_log is not None:
            twin.on_sample = plant_log.write
        line = dict(config.extra.get("daq") or {})  # the rig file's `daq:` (the virtual-can rig checked it)
        channels = {name: AnalogChannel.model_validate(c) for name, c in (line.get("channels") or {}).items()}
        daq = DaqTwin.from_sensors(
            twin.measured,
            config.sensors,
            transport=line.get("transport", "pty"),
            drift_ppm=float(line.get("drift_ppm", 0.0)),
            source_clock="host",
            analog=analog_readings(twin.measured, channels),
        )
        announce(json.dumps({"can": hub.channel, "daq": daq.url, "node_id": settings.node_id}))
        stop.wait()
    finally:
        if daq is not None:
            daq.close()
        if load_twin is not None:
            load_twin.close()
        if twin is not None:
            twin.close()
        hub.close()


def watchdog_grace_s(config: RigConfig) -> float:
    """How long a twin outlives its host: the drive's host-heartbeat timeout, twice, for the watch to
    trip and be told."""
    settings = CanopenSettings.from_rig_config(config)
    return 2 * settings.host_heartbeat_timeout_ms / 1000.0 + 0.1


def _child() -> None:
    """As the virtual-can rig's child: the spec on stdin, the JSON line on stdout, log lines on stderr."""
    logging.basicConfig(level=logging.WARNING, format="twin: %(message)s", stream=sys.stderr)
    spec: dict[str, Any] = json.loads(sys.stdin.readline())
    config = RigConfig.model_validate(spec["config"])
    model = HarmonicDriveModel.model_validate(spec["model"]) if spec.get("model") else None
    plant_log = PlantLog(Path(spec["plant_log"])) if spec.get("plant_log") else None
    stop = threading.Event()

    def watch_parent() -> None:
        sys.stdin.read()  # EOF: the rig closed us, or its process is gone
        stop.wait(watchdog_grace_s(config))  # let the drive's watchdog see a silent host first
        stop.set()

    threading.Thread(target=watch_parent, name="twin parent watch", daemon=True).start()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())

    def announce(line: str) -> None:
        freeze_built()  # the twins are built: out of the collector's walks before the first SYNC
        print(line, flush=True)

    with quiet_heap():  # this process is the twins' own: a full collection would hold their answers back
        serve_twins(config, model, int(spec.get("port", 0)), announce, stop, plant_log)


if __name__ == "__main__":
    _child()
