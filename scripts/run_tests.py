"""Run the whole test suite; 'no tests collected' (pytest exit 5) is a failure.
The 30 slowest tests are listed at the end, so that a CI log shows where its time went."""
import sys

import pytest

NO_TESTS_COLLECTED = 5

code = pytest.main(["-q", "-ra", "--durations=30", "test", *sys.argv[1:]])
if code == NO_TESTS_COLLECTED:
    print("error: pytest collected no tests", file=sys.stderr)
    code = 1
sys.exit(int(code))
