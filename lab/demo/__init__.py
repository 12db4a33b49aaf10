"""One-command Tele-Touch demo and the palpation benchmark (see :mod:`.orchestrator`)."""

#: the demo's drive board: the emulated ArrayTac board as a process of its own, as a separate
#: board is (``teletouch demo --display``; docs/speed.md section 12)
DEFAULT_DISPLAY = "board-process"

#: the demo's remote sensor frame rate (``teletouch demo --frame-rate-hz``). Frames keep this
#: rate on average since frames on pose keep an absolute schedule; 80 takes about the frames
#: that the previous default of 120 took when each frame was due a period after the previous
#: one began (73-85 frames/s; docs/speed.md section 17)
DEFAULT_FRAME_RATE_HZ = 80.0
