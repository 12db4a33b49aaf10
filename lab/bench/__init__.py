"""``teletouch bench NAME``: benchmarks of the product, results in ``benchmarks/results/``."""
