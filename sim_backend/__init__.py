"""Simulated plants behind the rig interface: in-process (`sim`, `inprocess.SimRig`), and twins on a
virtual CAN bus behind the real drivers (`virtual-can`, `virtual_bus.VirtualCanRig`).

Nothing registers itself on import: `rig.interface.BUILTIN_BACKENDS` names these classes by module path,
and a backend's module is imported only when a rig config names it.
"""
