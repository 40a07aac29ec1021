"""jscratch: scratch-based reflection art in JAX.

Stages (data flows one way): ``ndf`` (per-pair scratch NDF) <- ``bvh`` (pixel/scratch binning)
<- ``render`` (multi-view shading) <- ``loss`` <- ``design`` (optimisation);
``fabricate`` reads a saved design and drives a GRBL carver.
"""

__version__ = "0.1.0"
