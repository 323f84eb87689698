"""slidecal's benchmarks: studies of the package, run from a checkout, never imported by it.

``python -m tests.bench --list`` names them; ``python -m tests.bench NAME [options]`` runs one and
writes its report to ``docs/results/`` (``NAME --help`` gives its options).
"""
