"""Standalone developer benchmark scripts (not installed; run from the repository root).

The benchmark suite behind ``plcstack bench`` is the installed package ``plcstack.bench``. This
directory keeps scripts that need extra services or a source checkout, each run as
``python -m benchmarks.NAME`` from the repository root (which puts the checkout on ``sys.path``).
Its README.md documents the suite too; RESULTS.md holds the measured numbers.
"""
