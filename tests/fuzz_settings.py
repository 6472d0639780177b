"""The hypothesis settings of the fuzz suites: derandomized (the database off, a fixed example
stream), so CI sees the same cases every run; ``FUZZ_EXAMPLES`` scales the cases per property."""

from __future__ import annotations

import os

from hypothesis import HealthCheck, settings

EXAMPLES = int(os.environ.get("FUZZ_EXAMPLES", "200"))
FUZZ = settings(
    max_examples=EXAMPLES,
    derandomize=True,
    database=None,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)
