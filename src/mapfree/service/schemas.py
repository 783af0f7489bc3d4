"""What every JSON route answers, as Pydantic models: ``/docs`` and ``openapi.json`` describe the outputs, and
FastAPI checks each answer against its model. Routes whose answers leave out keys (a test submission has no
``per_scene``) declare ``response_model_exclude_unset``, so that an absent key stays absent."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from ..geometry import Intrinsics

#: A metric's value: a number, or null where it is not defined (or not published: medians on test).
Metric = float | None


class _Out(BaseModel):
    model_config = ConfigDict(extra="forbid")


class ErrorOut(_Out):
    """Every 4xx and 5xx answer of the JSON API."""

    detail: str = Field(description="what is wrong, naming the field, file or limit")
    status: int
    request_id: str | None = Field(None, description="the X-Request-ID of this request, for the logs")


# ------------------------------------------------------------------------------------------- operations


class HealthOut(_Out):
    status: Literal["ok", "degraded", "error"]


class WorkerOut(_Out):
    id: str
    pid: int
    host: str
    jobs_done: int


class HealthDetailOut(_Out):
    status: Literal["ok", "degraded", "error"]
    db: str = Field(description="the database's dialect, or 'unreachable'")
    jobs: dict[str, int] | None = None
    workers: list[WorkerOut] | None = None
    age_ms: float | None = None
    db_ms: float | None = None


# -------------------------------------------------------------------------------------------- accounts


class MeOut(_Out):
    name: str
    admin: bool
    test_evaluations_left_today: int | Literal["unlimited"]
    test_daily_limit: int | Literal["unlimited"]
    storage_used_bytes: int
    storage_quota_bytes: int


class TokenOut(_Out):
    id: int
    prefix: str
    label: str
    created_at: float
    expires_at: float | None
    revoked: bool
    expired: bool
    current: bool


class NewTokenOut(TokenOut):
    token: str = Field(description="the token itself, shown this once")


class EndedOut(_Out):
    tokens: list[int] = Field(description="ids of the tokens made with it, revoked with it")
    sessions: list[int] = Field(description="ids of the browser sessions signed in with any of them, ended")


class RevokedTokenOut(TokenOut):
    ended: EndedOut


class SessionOut(_Out):
    id: int
    created_at: float | None
    expires_at: float
    current: bool


class SessionEndedOut(_Out):
    id: int
    ended: bool


# ----------------------------------------------------------------------------------------- submissions


class MethodMetaOut(_Out):
    description: str
    paper_url: str
    code_url: str
    runtime_ms: float | None
    extra_data: bool


class SubmissionOut(_Out):
    id: str
    name: str
    split: str
    public: bool
    user: str | None
    status: Literal["uploading", "queued", "running", "done", "failed", "withdrawn"]
    attempts: int
    error: str | None
    created_at: float
    started_at: float | None
    finished_at: float | None
    withdrawn_at: float | None
    size_bytes: int
    sha256: str
    url: str
    api_url: str
    metrics: dict[str, Metric] | None
    problems: list[str]
    plots: list[str]
    per_scene: dict[str, dict[str, Metric]] | None = Field(None, description="val only: per scene")
    eval_seconds: float | None = Field(None, description="once scored")
    method: MethodMetaOut | None = Field(None, description="at upload: the method's description")


# ------------------------------------------------------------------------------------------ leaderboard


class EntryOut(_Out):
    id: str
    name: str
    user: str
    created_at: float
    rank: int | None
    url: str
    method: MethodMetaOut
    metrics: dict[str, Metric]


class ReferenceOut(_Out):
    name: str
    dataset: str
    note: str
    metrics: dict[str, Metric]


class BoardOut(_Out):
    split: str
    sort: str
    view: str
    scene: str | None
    entries: list[EntryOut]
    page: int
    per_page: int
    total: int
    pages: int
    reference: list[ReferenceOut] | None = Field(None, description="published results, unless reference=false")


class SideOut(_Out):
    id: str
    name: str
    user: str | None
    url: str


class CompareRowOut(_Out):
    metric: str
    a: Metric
    b: Metric
    diff: Metric
    better: Literal["a", "b"] | None


class CompareOut(_Out):
    split: str
    a: SideOut
    b: SideOut
    metrics: list[CompareRowOut]
    per_scene: dict[str, list[CompareRowOut]]


# --------------------------------------------------------------------------------------------- anchors


class AnchorPhotoOut(_Out):
    index: int
    intrinsics: Intrinsics
    intrinsics_source: str = Field(
        "given", description="given, exif (the photo's EXIF focal length) or default (a 64° camera)"
    )
    has_depth: bool
    pose: list[float] = Field(description="world-to-camera from the anchor's frame: qw qx qy qz tx ty tz")


class AnchorCalibrationOut(_Out):
    method: str = Field(description="the method (a cascade: one of its stages) this calibration is for")
    source: Literal["uploaded", "shipped", "none"] = Field(
        description="uploaded with the anchor, shipped with the method, or none: answers carry no p_correct"
    )
    name: str | None = Field(None, description="the calibration file's name")
    frames: int | None = Field(None, description="frames it was fitted on")
    ece: float | None = Field(None, description="its held-out expected calibration error of p_correct")


class AnchorOut(_Out):
    id: str
    name: str
    method: str
    intrinsics: Intrinsics
    private: bool
    has_depth: bool
    num_photos: int
    photos: list[AnchorPhotoOut]
    created_at: float
    url: str
    calibrations: list[AnchorCalibrationOut] = Field(
        default_factory=list, description="what turns the anchor's estimates into p_correct, per method it runs"
    )
    accept: float | None = Field(None, description="answers say accepted when p_correct is at least this")


class LocalizeOut(_Out):
    ok: bool
    confidence: float
    inliers: int
    reason: str
    timings: dict[str, float]
    q_wxyz: list[float] | None = None
    t: list[float] | None = None
    R: list[list[float]] | None = None
    center: list[float] | None = None
    method: str
    num_matches: int
    scale_free: bool
    photo: int | None = Field(None, description="the index of the anchor's photo that answered")
    retrieval_similarity: float | None = None
    anchor: str
    intrinsics_source: str | None = Field(
        None, description="the query's intrinsics: given, exif (its EXIF focal length) or default (a 64° camera)"
    )
    signals: dict[str, float] = Field(
        default_factory=dict,
        description="the method's per-frame evidence (matches, inliers, inlier ratio, residual, depth coverage, ...)",
    )
    p_correct: float | None = Field(None, description="calibrated probability that the pose is within 90 px VCRE")
    stage: str | None = Field(None, description="a cascade's stage that answered")
    calibration: Literal["uploaded", "shipped"] | None = Field(
        None,
        description="where p_correct's calibration came from: uploaded with the anchor, or the method's shipped one",
    )
    accepted: bool | None = Field(
        None, description="p_correct is at least the anchor's accept threshold (only for anchors with one)"
    )


#: The error answers every JSON route may give, for ``openapi.json``.
ERRORS = {code: {"model": ErrorOut} for code in (400, 401, 403, 404, 408, 409, 410, 413, 422, 429, 500, 503)}


#: OpenAPI links: which later calls take an id from a response, by (path, method, status) of the response, as
#: {link name: ((path, method) of the call, {its parameter: where the value is in the response})}. Clients that read
#: links (and the stateful fuzz test) chain the calls from them.
LINKS: dict[tuple[str, str, str], dict[str, tuple[tuple[str, str], dict[str, Any]]]] = {
    ("/api/tokens", "post", "201"): {
        "RevokeToken": (("/api/tokens/{tid}", "delete"), {"tid": "$response.body#/id"}),
    },
    ("/api/sessions", "get", "200"): {
        "EndSession": (("/api/sessions/{session_id}", "delete"), {"session_id": "$response.body#/0/id"}),
    },
    ("/api/submissions", "post", "202"): {
        "GetSubmission": (("/api/submissions/{sid}", "get"), {"sid": "$response.body#/id"}),
        "SetVisibility": (("/api/submissions/{sid}", "patch"), {"sid": "$response.body#/id"}),
        "DescribeMethod": (("/api/submissions/{sid}/method", "put"), {"sid": "$response.body#/id"}),
        "DownloadZip": (("/api/submissions/{sid}/zip", "get"), {"sid": "$response.body#/id"}),
        "Withdraw": (("/api/submissions/{sid}", "delete"), {"sid": "$response.body#/id"}),
    },
    ("/anchors", "post", "201"): {
        "GetAnchor": (("/anchors/{aid}", "get"), {"aid": "$response.body#/id"}),
        "Localize": (("/anchors/{aid}/localize", "post"), {"aid": "$response.body#/id"}),
        "AddPhoto": (("/anchors/{aid}/photos", "post"), {"aid": "$response.body#/id"}),
        "GetFirstPhoto": (("/anchors/{aid}/photos/{k}", "get"), {"aid": "$response.body#/id", "k": 0}),
        "DeleteAnchor": (("/anchors/{aid}", "delete"), {"aid": "$response.body#/id"}),
    },
    ("/anchors/{aid}/photos", "post", "201"): {
        "GetAnchorAgain": (("/anchors/{aid}", "get"), {"aid": "$response.body#/id"}),
        "LocalizeAgain": (("/anchors/{aid}/localize", "post"), {"aid": "$response.body#/id"}),
        "DeleteSecondPhoto": (("/anchors/{aid}/photos/{k}", "delete"), {"aid": "$response.body#/id", "k": 1}),
    },
}


def _optional_file(prop: Any) -> dict[str, Any] | None:
    """The file schema of an optional upload (``anyOf: [file, null]``, FastAPI's ``UploadFile | None``), else None."""
    options = prop.get("anyOf") if isinstance(prop, dict) else None
    if not isinstance(options, list) or len(options) != 2 or {"type": "null"} not in options:
        return None
    (file,) = [o for o in options if o != {"type": "null"}]
    return file if file.get("contentMediaType") == "application/octet-stream" else None


def for_clients(spec: dict[str, Any]) -> dict[str, Any]:
    """The OpenAPI document as clients read it best (in place; again is a no-op): ``LINKS`` written in by the
    operation ids the document has, and an optional upload declared as a file part that may be left out (not as
    "a file or null", which client generators and schemathesis send as a text field).

    Args:
        spec: The app's ``openapi()`` document.

    Returns:
        The same document.
    """
    for schema in spec.get("components", {}).get("schemas", {}).values():
        for name, prop in schema.get("properties", {}).items():
            file = _optional_file(prop)
            if file is not None:
                extra = {k: v for k, v in prop.items() if k != "anyOf"}
                schema["properties"][name] = {**file, **extra}
    paths = spec.get("paths", {})
    for (path, method, status), links in LINKS.items():
        response = paths.get(path, {}).get(method, {}).get("responses", {}).get(status)
        if response is None:
            continue
        out = {}
        for name, ((to_path, to_method), parameters) in links.items():
            target = paths.get(to_path, {}).get(to_method)
            if target is not None:
                out[name] = {"operationId": target["operationId"], "parameters": parameters}
        response["links"] = out
    return spec
