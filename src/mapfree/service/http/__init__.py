"""HTTP plumbing of the service: guards and limits (credentials checked from the headers, throttled failures, body
timeouts, the heavy-request pool), HTML rendering and error answers, logging. The app that assembles it is
``service/app.py``."""
