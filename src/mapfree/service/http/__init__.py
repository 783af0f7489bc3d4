"""HTTP plumbing of the service: the app, who is calling, guards and limits, metrics, health."""
