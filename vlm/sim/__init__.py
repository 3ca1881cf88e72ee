"""The simulated VLM: answers OnFly's prompts from what the camera frame shows.

Everything about its errors, latency and randomness is documented in
:mod:`vlm.sim.error_model`.
"""

from vlm.sim.backend import Perception, SimulatedVlm
from vlm.sim.error_model import PRESETS, ErrorModel, ErrorModelError, LatencyModel, get_preset

__all__ = ["SimulatedVlm", "Perception", "ErrorModel", "ErrorModelError", "LatencyModel", "PRESETS", "get_preset"]
