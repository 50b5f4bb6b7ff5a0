"""Simulated plants behind the rig interface: in-process (`sim`), and twins on a virtual CAN bus behind
the real drivers (`virtual-can`).

`rig.interface` loads only this package; the hardware backend (`canopen`) lives in `drivers`, which
registers it when imported: it is imported here, as the virtual-can backend is built on it anyway.
Backends that need the CAN and serial stacks are imported only when a rig config names them.
"""

import drivers  # noqa: F401  (registers `canopen`)
from rig.config import RigConfig
from rig.interface import Rig, register_backend
from sim_backend.inprocess import SimRig


def _open_virtual_can_rig(config: RigConfig) -> Rig:
    from sim_backend.virtual_bus import VirtualCanRig

    return VirtualCanRig(config)


register_backend("sim", SimRig)
register_backend("virtual-can", _open_virtual_can_rig)
