"""Plain NumPy per-run reference implementations (the baselines the benchmarks compare against)."""
