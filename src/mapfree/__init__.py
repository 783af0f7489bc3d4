"""mapfree: metric 6-DoF relocalization of a query photo against a single reference photo."""

__version__ = "0.1.0"
