"""What every JSON route answers, as Pydantic models: ``/docs`` and ``openapi.json`` describe the outputs, and
FastAPI checks each answer against its model. Routes whose answers leave out keys (a test submission has no
``per_scene``) declare ``response_model_exclude_unset``, so that an absent key stays absent."""

from __future__ import annotations

from typing import Literal, Optional

from pydantic import BaseModel, ConfigDict, Field

from ..geometry import Intrinsics

#: A metric's value: a number, or null where it is not defined (or not published: medians on test).
Metric = Optional[float]


class _Out(BaseModel):
    model_config = ConfigDict(extra="forbid")


class ErrorOut(_Out):
    """Every 4xx and 5xx answer of the JSON API."""

    detail: str = Field(description="what is wrong, naming the field, file or limit")
    status: int
    request_id: Optional[str] = Field(None, description="the X-Request-ID of this request, for the logs")


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
    jobs: Optional[dict[str, int]] = None
    workers: Optional[list[WorkerOut]] = None
    age_ms: Optional[float] = None
    db_ms: Optional[float] = None


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
    expires_at: Optional[float]
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
    created_at: Optional[float]
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
    runtime_ms: Optional[float]
    extra_data: bool


class SubmissionOut(_Out):
    id: str
    name: str
    split: str
    public: bool
    user: Optional[str]
    status: Literal["uploading", "queued", "running", "done", "failed", "withdrawn"]
    attempts: int
    error: Optional[str]
    created_at: float
    started_at: Optional[float]
    finished_at: Optional[float]
    withdrawn_at: Optional[float]
    size_bytes: int
    sha256: str
    url: str
    api_url: str
    metrics: Optional[dict[str, Metric]]
    problems: list[str]
    plots: list[str]
    per_scene: Optional[dict[str, dict[str, Metric]]] = Field(None, description="val only: per scene")
    eval_seconds: Optional[float] = Field(None, description="once scored")
    method: Optional[MethodMetaOut] = Field(None, description="at upload: the method's description")


# ------------------------------------------------------------------------------------------ leaderboard


class EntryOut(_Out):
    id: str
    name: str
    user: str
    created_at: float
    rank: Optional[int]
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
    scene: Optional[str]
    entries: list[EntryOut]
    page: int
    per_page: int
    total: int
    pages: int
    reference: Optional[list[ReferenceOut]] = Field(None, description="published results, unless reference=false")


class SideOut(_Out):
    id: str
    name: str
    user: Optional[str]
    url: str


class CompareRowOut(_Out):
    metric: str
    a: Metric
    b: Metric
    diff: Metric
    better: Optional[Literal["a", "b"]]


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
    has_depth: bool
    pose: list[float] = Field(description="world-to-camera from the anchor's frame: qw qx qy qz tx ty tz")


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


class LocalizeOut(_Out):
    ok: bool
    confidence: float
    inliers: int
    reason: str
    timings: dict[str, float]
    q_wxyz: Optional[list[float]] = None
    t: Optional[list[float]] = None
    R: Optional[list[list[float]]] = None
    center: Optional[list[float]] = None
    method: str
    num_matches: int
    scale_free: bool
    photo: Optional[int] = Field(None, description="the index of the anchor's photo that answered")
    retrieval_similarity: Optional[float] = None
    anchor: str


#: The error answers every JSON route may give, for ``openapi.json``.
ERRORS = {code: {"model": ErrorOut} for code in (400, 401, 403, 404, 408, 409, 410, 413, 422, 429, 500, 503)}
