"""Device drivers: the CiA 402 servo on CANopen, the serial DAQ, and the rig that composes them.

Importing the package registers the hardware backend `canopen` (`drivers.hardware_rig.HardwareRig`),
loaded only when a rig config names it. `rig.interface` loads `sim_backend`, which imports this package.
"""

from rig.config import RigConfig
from rig.interface import Rig, register_backend


def _open_hardware_rig(config: RigConfig) -> Rig:
    from drivers.hardware_rig import HardwareRig

    return HardwareRig(config)


register_backend("canopen", _open_hardware_rig)
