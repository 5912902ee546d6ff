"""Which frames are kept and optimised again (config: mapping.keyframes).

- keyframe_set.py: keyframe insertion (voxel IoU, frame gap) and each step's selection (coverage);
- budget.py: keeping the keyframes within a memory budget without losing coverage of the map.
"""

from h2viz.mapping.keyframes.budget import KeyframeBudget
from h2viz.mapping.keyframes.keyframe_set import KeyframeSet

__all__ = ["KeyframeBudget", "KeyframeSet"]
