"""Helpers for mapfree's own tests and benchmarks, kept out of the wheel (``pip install mapfree`` does not
install them). From a checkout they import with ``src/`` on the path: the test suite sets it
(``[tool.pytest.ini_options] pythonpath``), the scripts under ``bench/`` add it, and elsewhere run with
``PYTHONPATH=src``."""
