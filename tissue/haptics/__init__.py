"""Haptics (paper §3.6): instruments coupled to a device, and the multi-rate haptic loop.

    instrument.py  jaws: rigid tools coupled to the device (M_hap, B_hap, K_hap), their compliance in W
    device.py      the device protocol, a scripted device, a UDP bridge for real devices' drivers
    lcp.py         a step's LCP restricted to the instrument's rows, and its compiled re-solve
    loop.py        the haptic loop in its own process, fed through shared memory
    layer.py       the scene options (Grasper, Haptics) and the stage that logs forces
"""

from .instrument import Coupling, DevicePose, Instrument, Jaw, grasper, probe
from .lcp import HapticForce, HapticProblem, HapticSolver, restrict

__all__ = ["Coupling", "DevicePose", "HapticForce", "HapticProblem", "HapticSolver", "Instrument", "Jaw", "grasper",
           "probe", "restrict"]
