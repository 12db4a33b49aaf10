"""Fuzzing of the wire protocol: the decoder, the sans-I/O session cores and the relay.

* :mod:`~lab.fuzz.docspec`: the error table of ``docs/protocol.md`` §6, read from the doc
  itself, so every answer the fuzzers see is checked against what the doc promises;
* :mod:`~lab.fuzz.script`: the byte format of a fuzz input that drives a session (a list of
  operations: a message, raw bytes, time passing, a tick, a flush, a disconnect);
* :mod:`~lab.fuzz.seeds`: the seed corpus, real encoded messages of every type;
* :mod:`~lab.fuzz.targets` and :mod:`~lab.fuzz.sessions`: one function per target,
  ``bytes -> None``, raising :class:`~lab.fuzz.targets.Finding` when an input breaks a
  promise (:mod:`~lab.fuzz.registry` lists them);
* :mod:`~lab.fuzz.mutate` and :mod:`~lab.fuzz.engine`: a coverage-less mutation fuzzer of our
  own (byte-level and msgpack-structure mutations), used where atheris is not installed and
  beside it;
* :mod:`~lab.fuzz.atheris_main`: the coverage-guided run under atheris (libFuzzer), one
  subprocess per target;
* :mod:`~lab.fuzz.smoke`: fuzzed frames over real TCP and WebSocket sockets to a relay
  subprocess, which must still serve a good session afterwards.

``teletouch bench fuzz`` (:mod:`lab.bench.fuzz`) runs them all.
"""
