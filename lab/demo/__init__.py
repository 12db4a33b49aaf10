"""One-command Tele-Touch demo and the palpation benchmark (see :mod:`.orchestrator`)."""

#: the demo's drive board: the emulated ArrayTac board as a process of its own, as a separate
#: board is (``teletouch demo --display``; docs/speed.md section 12)
DEFAULT_DISPLAY = "board-process"
