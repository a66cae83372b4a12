"""The benchmarks (scripts with results.json + results.md; see README.md), importable as ``benchmarks.<name>``."""
