"""One-command Tele-Touch demo and the palpation benchmark (see :mod:`.orchestrator`)."""
