"""Run the whole test suite; 'no tests collected' (pytest exit 5) is a failure."""
import sys

import pytest

NO_TESTS_COLLECTED = 5

code = pytest.main(["-q", "-ra", "test", *sys.argv[1:]])
if code == NO_TESTS_COLLECTED:
    print("error: pytest collected no tests", file=sys.stderr)
    code = 1
sys.exit(int(code))
