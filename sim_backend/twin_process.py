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
"""

from __future__ import annotations

import json
import logging
import signal
import sys
import threading
from collections.abc import Callable
from typing import Any

from drivers.canopen_config import CanopenSettings
from drivers.tcp_can import CanHub
from model.params import HarmonicDriveModel, load_model
from rig.config import RigConfig
from rig.realtime import quiet_heap
from sim_backend.cia402_twin import Cia402Twin
from sim_backend.daq_twin import DaqTwin

logger = logging.getLogger(__name__)


def serve_twins(
    config: RigConfig,
    model: HarmonicDriveModel | None = None,
    port: int = 0,
    announce: Callable[[str], None] = print,
    stop: threading.Event | None = None,
) -> None:
    """Run the rig's drive and DAQ twins until `stop` is set (or SIGINT/SIGTERM); `announce` gets the
    JSON line saying where they are once they answer."""
    settings = CanopenSettings.from_rig_config(config)
    model = model if model is not None else load_model(config.model or "seed")
    stop = stop or threading.Event()
    hub = CanHub(port)
    twin = daq = None
    try:
        twin = Cia402Twin(hub.bus(), settings.node_id, model, config, settings.eds_path())
        line = dict(config.extra.get("daq") or {})  # the rig file's `daq:` (the virtual-can rig checked it)
        daq = DaqTwin.from_sensors(
            twin.measured,
            config.sensors,
            transport=line.get("transport", "pty"),
            drift_ppm=float(line.get("drift_ppm", 0.0)),
            source_clock="host",
        )
        announce(json.dumps({"can": hub.channel, "daq": daq.url, "node_id": settings.node_id}))
        stop.wait()
    finally:
        if daq is not None:
            daq.close()
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
    stop = threading.Event()

    def watch_parent() -> None:
        sys.stdin.read()  # EOF: the rig closed us, or its process is gone
        stop.wait(watchdog_grace_s(config))  # let the drive's watchdog see a silent host first
        stop.set()

    threading.Thread(target=watch_parent, name="twin parent watch", daemon=True).start()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())

    def announce(line: str) -> None:
        print(line, flush=True)

    with quiet_heap():  # this process is the twins' own: a full collection would hold their answers back
        serve_twins(config, model, int(spec.get("port", 0)), announce, stop)


if __name__ == "__main__":
    _child()
