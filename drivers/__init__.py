"""Device drivers: the CiA 402 servo on CANopen, the serial DAQ, and the rig that composes them.

The hardware backend `canopen` is `drivers.hardware_rig.HardwareRig`, named by module path in
`rig.interface.BUILTIN_BACKENDS` and imported only when a rig config names it; importing this package
loads nothing.
"""
