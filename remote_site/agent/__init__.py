"""The remote palpation station agent (``teletouch remote``).

Modules: :mod:`.config` (settings), :mod:`.devices` (device factory, calibrations, worlds by
name), :mod:`.world` (the simulated world: simulator code, never imported by the others),
:mod:`.stiffness_stage` (tracker + map), :mod:`.pipeline` (sensor frame -> tactile frame),
:mod:`.station` (the asyncio loops), :mod:`.app` (start-up and shutdown).
Import the submodules directly; this package imports nothing heavy.
"""
