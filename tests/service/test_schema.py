"""The JSON API fuzzed from its own ``openapi.json`` (schemathesis): for inputs generated from every route's
declared parameters and bodies, as an account and anonymously, no answer is a 5xx and every answer conforms to
the route's declared responses (status, content type, schema). Bounded: a few examples per route, so that the
whole runs in seconds."""

from __future__ import annotations

import pytest

schemathesis = pytest.importorskip("schemathesis")

from hypothesis import HealthCheck, settings
from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import (
    content_type_conformance,
    response_schema_conformance,
    status_code_conformance,
)

from .conftest import create_users

CHECKS = [not_a_server_error, status_code_conformance, content_type_conformance, response_schema_conformance]
EXAMPLES = 4


@pytest.fixture(scope="module")
def app_and_token(split_data, tmp_path_factory):
    from mapfree.service import Settings, create_app

    url = f"sqlite:///{tmp_path_factory.mktemp('schema') / 'fuzz.db'}"
    token = create_users(url, {"fuzz": None})["fuzz"]
    app = create_app(Settings(db_url=url, data_root=split_data.root, gt_root=split_data.gt, auth_failures_per_minute=0))
    return app, token


def _operations():
    """(id, operation) of every route in the served ``openapi.json``, loaded from an app of the current code
    (the schema does not depend on the settings)."""
    import tempfile

    from mapfree.service import Settings, create_app

    with tempfile.TemporaryDirectory() as d:
        app = create_app(Settings(db_url=f"sqlite:///{d}/schema.db"))
        loaded = schemathesis.openapi.from_asgi("/openapi.json", app)
        app.state.engine.dispose()
    ops = [r.ok() for r in loaded.get_all_operations()]
    return [pytest.param(op.method.upper() + " " + op.path, id=f"{op.method.upper()} {op.path}") for op in ops]


@pytest.mark.parametrize("route", _operations())
def test_every_route_answers_as_declared(route, app_and_token):
    """Each route: a few generated requests, sent as an account and anonymously."""
    from hypothesis import given

    app, token = app_and_token
    method, path = route.split(" ", 1)
    operation = schemathesis.openapi.from_asgi("/openapi.json", app)[path][method]

    @given(case=operation.as_strategy())
    @settings(
        max_examples=EXAMPLES, deadline=None, derandomize=True, database=None, suppress_health_check=list(HealthCheck)
    )
    def fuzz(case):
        for headers in ({"Authorization": f"Bearer {token}"}, {}):
            case.call_and_validate(headers=headers, checks=CHECKS)

    fuzz()
