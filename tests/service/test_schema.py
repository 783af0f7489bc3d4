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
# Seconds for loading openapi.json and for each call: schemathesis' 10 s default is passed on a loaded CI machine
# (a localize runs a method; the schema of the whole app is built on the first request).
TIMEOUT = 120


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
        loaded = schemathesis.openapi.from_asgi("/openapi.json", app, timeout=TIMEOUT)
        app.state.engine.dispose()
    ops = [r.ok() for r in loaded.get_all_operations()]
    return [pytest.param(op.method.upper() + " " + op.path, id=f"{op.method.upper()} {op.path}") for op in ops]


@pytest.fixture(scope="module")
def schema(app_and_token):
    """The app's ``openapi.json`` as schemathesis reads it, loaded once for the module."""
    return schemathesis.openapi.from_asgi("/openapi.json", app_and_token[0], timeout=TIMEOUT)


@pytest.mark.parametrize("route", _operations())
def test_every_route_answers_as_declared(route, app_and_token, schema):
    """Each route: a few generated requests, sent as an account and anonymously."""
    from hypothesis import given

    _, token = app_and_token
    method, path = route.split(" ", 1)
    operation = schema[path][method]

    @given(case=operation.as_strategy())
    @settings(
        max_examples=EXAMPLES, deadline=None, derandomize=True, database=None, suppress_health_check=list(HealthCheck)
    )
    def fuzz(case):
        for headers in ({"Authorization": f"Bearer {token}"}, {}):
            case.call_and_validate(headers=headers, checks=CHECKS, timeout=TIMEOUT)

    fuzz()


def test_calls_chained_by_the_declared_links_answer_as_declared(split_data, realmini_dir, tmp_path):
    """Stateful: sequences of calls that follow the links ``openapi.json`` declares (an anchor created, then
    fetched, localized against, given a photo, that photo deleted, the anchor deleted; a submission uploaded,
    then read, renamed, downloaded, withdrawn; a token minted then revoked). The calls that create something get
    real inputs (photos of a real scene, a valid submission ZIP) so that the chains reach the resources; every
    other input is generated. No 5xx, every answer as declared."""
    from hypothesis import settings as hsettings
    from hypothesis.stateful import run_state_machine_as_test

    from mapfree.data import Dataset
    from mapfree.service import Settings, create_app

    from .conftest import make_submission

    url = f"sqlite:///{tmp_path / 'stateful.db'}"
    create_users(url, {})  # the schema
    app = create_app(Settings(db_url=url, data_root=split_data.root, gt_root=split_data.gt, auth_failures_per_minute=0))
    scene = Dataset(realmini_dir).scene("val", "s00000")
    ref, query = scene.reference, scene.frame("seq1/frame_00009.jpg")

    def photo(frame, depth: bool) -> dict:
        K = frame.intrinsics
        out = {"image": frame.image_path.read_bytes(), "fx": repr(K.fx), "fy": repr(K.fy), "cx": repr(K.cx)}
        out["cy"] = repr(K.cy)
        if depth:
            out["depth"] = frame.depth_path("sensor").read_bytes()
        return out

    real = {
        ("POST", "/anchors"): {**photo(ref, True), "method": "sift_pnp_sensor"},
        ("POST", "/anchors/{aid}/photos"): {**photo(query, True), "pose": "1 0 0 0 0 0 0.1"},
        ("POST", "/anchors/{aid}/localize"): photo(query, False),
        ("POST", "/api/tokens"): {"expires_in_days": "7", "label": "chain"},
        ("POST", "/api/submissions"): {
            "file": make_submission(split_data.root / "val"),
            "split": "val",
            "name": "chain",
        },
    }
    seen: dict[str, int] = {}
    accounts = iter(range(1_000_000))

    class Chains(schemathesis.openapi.from_asgi("/openapi.json", app, timeout=TIMEOUT).as_state_machine()):  # type: ignore[misc]
        def setup(self):
            # Each scenario as a new account: what earlier scenarios left (tokens, sessions, uploads, rate limits)
            # must not change which links this one can follow, or hypothesis replays it differently (flaky).
            name = f"chain{next(accounts)}"
            self.token = create_users(url, {name: None})[name]

        def before_call(self, case):
            body = real.get((case.method.upper(), case.operation.path))
            if body is not None:
                case.body = dict(body)

        def get_call_kwargs(self, case):
            return {"headers": {"Authorization": f"Bearer {self.token}"}, "timeout": TIMEOUT}

        def validate_response(self, response, case, **kwargs):
            key = f"{case.method.upper()} {case.operation.path} {response.status_code}"
            seen[key] = seen.get(key, 0) + 1
            case.validate_response(response, checks=CHECKS)

    run_state_machine_as_test(
        Chains,
        settings=hsettings(
            max_examples=30,
            stateful_step_count=8,
            deadline=None,
            derandomize=True,
            database=None,
            suppress_health_check=list(HealthCheck),
        ),
    )
    app.state.engine.dispose()
    # The chains reached the resources: created, then used through their links (which links a run follows
    # depends on hypothesis's draws, so the count is asserted, not each one).
    for created in ("POST /anchors 201", "POST /api/submissions 202", "POST /api/tokens 201"):
        assert seen.get(created), (created, seen)
    followed = {k.rsplit(" ", 1)[0] for k in seen if k.rsplit(" ", 1)[1].startswith("2") and "{" in k}
    assert len(followed) >= 5, seen
