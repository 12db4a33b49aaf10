"""The remote palpation station agent (``teletouch remote``).

Modules: :mod:`.config` (settings), :mod:`.world` (device factory and the simulated world),
:mod:`.stiffness_stage` (tracker + map), :mod:`.pipeline` (sensor frame -> tactile frame),
:mod:`.station` (the asyncio loops), :mod:`.app` (start-up and shutdown).
Import the submodules directly; this package imports nothing heavy.
"""
