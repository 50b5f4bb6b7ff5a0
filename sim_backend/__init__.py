"""Simulated plants behind the rig interface: in-process now, twins on a virtual bus later."""

from rig.interface import register_backend
from sim_backend.inprocess import SimRig

register_backend("sim", SimRig)
