"""What the tests and the benchmarks share and production code never needs: buses of their own, test
data with known answers, plants that move under a script.

Installed with hdrig so that `tests/` and `bench/` import it by name; nothing in `model`, `rig`,
`sim_backend`, `drivers` or `api` may import it.
"""
