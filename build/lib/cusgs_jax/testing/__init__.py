"""Float64 NumPy oracles and small random scenes used by the tests (not imported by production code)."""
