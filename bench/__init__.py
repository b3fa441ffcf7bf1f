"""Side-by-side benchmarks of this tmrl against the original tmrl 0.7.1 (and Stable-Baselines3,
rtgym), on one harness (:mod:`bench.harness`). Not part of the installed ``tmrl`` package.

    python -m bench --list
    python -m bench NAME [--help | options]
"""

BENCHMARKS = (
    "trainer_speed",
    "pendulum_pipeline",
    "pendulum_learning",
    "track_learning",
    "pipeline_throughput",
    "transport_compare",
    "trainer_ingest",
    "memory_speed",
    "sim_speed",
    "realtime_jitter",
    "first_lap",
    "chaos",
    "update_cost",
)
"""The benchmarks, as modules of this package with a ``main(argv)``."""
