"""The lab: everything that runs, scores or measures Tele-Touch rather than being part of it.

The top layer of the import graph: it may import every product package (``shared``,
``relay_server``, ``local_site``, ``remote_site``) and their simulators, and nothing in those
packages imports it.

* :mod:`lab.cli`: the ``teletouch`` command's dispatcher (each subcommand lives in its package);
* :mod:`lab.demo`: the one-machine demo orchestrator (relay + both stations as processes);
* :mod:`lab.bench`: the ``teletouch bench NAME`` benchmarks;
* :mod:`lab.scoring`, :mod:`lab.reconstruction_metrics`: scoring against ground truth;
* :mod:`lab.linkemu`: the userspace link emulator (delay, jitter, loss, outages);
* :mod:`lab.display_cli`: characterisation of the simulated ArrayTac against the paper.
"""
