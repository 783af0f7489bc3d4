"""Operations: the server's health (liveness for anyone, readiness in detail) and its Prometheus metrics, with their
routes (``/health``, ``/health/detail``, ``/metrics``)."""
