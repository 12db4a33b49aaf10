"""Row layout of the state and command arrays the two engines of :mod:`.plant` share.

:class:`~local_site.arraytac_sim.plant.ArrayTacPlant` keeps its state and its commands as rows
of two small arrays (each attribute is a view of a row), so the compiled kernel
(:mod:`.kernel`) reads and updates them in place without packing on every call.
"""

from __future__ import annotations

__all__ = ["N_CMD_ROWS", "N_STATE_ROWS"]

#: state rows: piezo voltage, true height, PID integrator, last measurement, last PID output
S_U, S_Y, S_I, S_M_PREV, S_U_CMD = range(5)
N_STATE_ROWS = 5

#: command rows: clamped height/stiffness/friction, finger force, firmware sine test
#: (amplitude, angular frequency), open-loop drive override (voltage, amplitude, angular freq.)
(CMD_HEIGHT, CMD_K, CMD_F, CMD_FORCE, CMD_TEST_AMP, CMD_TEST_OMEGA, CMD_OV_V, CMD_OV_A,
 CMD_OV_OMEGA) = range(9)
N_CMD_ROWS = 9
