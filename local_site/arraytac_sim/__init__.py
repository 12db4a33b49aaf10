"""ArrayTac simulator: the drive-board firmware (PID + stiffness law + friction) and the plant.

Modules, one job each:

- :mod:`.params`      -- :class:`PlantParams`, every physical and controller constant.
- :mod:`.design`      -- analytic derivation of the constants from the paper's figures.
- :mod:`.sensor`      -- Hall A1324 model and its cubic sensor-to-displacement calibration.
- :mod:`.stiffness`   -- the paper's two-stage stiffness law (Eq. 1, Eq. 2, Eq. S15-S21).
- :mod:`.integrators` -- plant integrators (exact ZOH, forward Euler, RK4).
- :mod:`.blockpath`   -- exact block integration of the linear closed loop (the fast path).
- :mod:`.plant`       -- :class:`ArrayTacPlant`, the 16-unit simulator used by the CAN emulator.
- :mod:`.characterize`-- step/frequency/force-displacement measurements (``teletouch display
  characterize``).
"""

from local_site.arraytac_sim.params import PlantParams
from local_site.arraytac_sim.plant import ArrayTacPlant, PlantTrace

__all__ = ["ArrayTacPlant", "PlantParams", "PlantTrace"]
