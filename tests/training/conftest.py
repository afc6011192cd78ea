"""The tiny training inputs live in tests/conftest.py (shared with the evaluation and export tests)."""

from tests.conftest import init_from_gt  # noqa: F401  (kept importable from here)
