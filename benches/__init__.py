"""Benchmarks, the stress harness and the demo: they measure and exercise zoo and pipeline, and are no stage of either."""
