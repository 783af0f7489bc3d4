"""Service settings: one dataclass, filled from ``mapfree serve`` flags (defaults suit a small deployment)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

#: A daily test limit (the server's or one account's) meaning "no limit"; 0 means none at all.
UNLIMITED = -1


def parse_daily_limit(text: str | int) -> int:
    """A test-evaluation limit as typed by an operator: a count (0: no test evaluation at all) or ``unlimited``
    (a negative number means the same) -> the count, or ``UNLIMITED``."""
    word = str(text).strip().lower()
    if word == "unlimited":
        return UNLIMITED
    try:
        n = int(word)
    except ValueError:
        raise ValueError(f"expected a number of evaluations (0: none) or 'unlimited'; got {str(text)[:40]!r}") from None
    return UNLIMITED if n < 0 else n


def shown_limit(limit: int) -> int | str:
    """A daily test limit as accounts and operators read it: the count, or ``"unlimited"``."""
    return "unlimited" if limit < 0 else limit


@dataclass
class Limits:
    """What one request may send: every upload is checked against these before it costs memory or time, and
    refused with a 413 or 422 naming the limit (``mapfree serve`` sets the submission sizes and
    ``work_max_side`` from its flags).

    Attributes:
        max_request_bytes: A whole HTTP body, in bytes (64 MiB).
        max_submission_bytes: A submission ZIP as uploaded (compressed), in bytes (50 MiB).
        max_zip_entries: Files in one submission ZIP.
        max_zip_entry_bytes: One pose file of a ZIP, uncompressed, in bytes (64 MiB).
        max_zip_uncompressed_bytes: All pose files of a ZIP together, uncompressed, in bytes (256 MiB).
        max_zip_ratio: Uncompressed / compressed size of any one ZIP entry (a higher ratio is a ZIP bomb).
        max_image_bytes: One uploaded photo or depth map file, in bytes (16 MiB).
        max_image_pixels: Pixels of one decoded photo (4096 x 4096).
        max_name_chars: Characters of a submission's or an anchor's name.
        max_anchor_photos: Photos of one anchor's place, the first included.
        work_max_side: Decoded photos are downscaled at once so that their long side is at most this many
            pixels (0: never). The benchmark's photos are 540 x 720 and every method is tuned at about that
            size; the intrinsics and depth maps are scaled with them, so poses stay metric.
    """

    max_request_bytes: int = 64 << 20
    max_submission_bytes: int = 50 << 20
    max_zip_entries: int = 2000
    max_zip_entry_bytes: int = 64 << 20
    max_zip_uncompressed_bytes: int = 256 << 20
    max_zip_ratio: float = 200.0
    max_image_bytes: int = 16 << 20
    max_image_pixels: int = 4096 * 4096
    max_name_chars: int = 120
    max_anchor_photos: int = 16
    work_max_side: int = 1024


@dataclass
class Settings:
    """Everything the app and its workers need; the defaults suit a small deployment on one machine.
    ``mapfree serve`` fills it from its flags (the operator guide lists them); folders may be given as strings.

    Attributes:
        db_url: The database: ``sqlite:///FILE`` (one host) or a PostgreSQL URL (several hosts share it).
        data_root: The dataset folder holding the public splits (their scenes, the val ground truth) that
            submissions are scored against; None: uploads are checked without knowing the scenes, and nothing
            is scored.
        gt_root: The private test ground truth (``gt_root/test/sNNNNN/poses.txt``), read by the workers only,
            never served; None: test submissions cannot be scored.
        splits: The splits submissions may be made to, each with its leaderboard.
        test_daily_limit: Test evaluations per account and 24 h, unless the account has its own limit
            (0: none at all; ``UNLIMITED``, -1: no limit).
        lease_seconds: How long a worker's claim on a job lasts without a heartbeat; a job whose worker died
            is taken again after it.
        max_attempts: Claims of one job before it is failed (a submission that kills every worker).
        poll_seconds: How often an idle worker looks for a queued job.
        default_method: The relocalization method of an anchor created without one (empty: the registry's best
            offline feature-matching preset).
        secure_cookies: Mark the session cookies ``Secure`` (behind HTTPS).
        session_hours: Lifetime of a browser session, in hours (it ends with its token at the latest).
        methods_dir: A folder of the operator's method YAML files, offered to clients by their names.
        val_hourly_limit: Val submissions per account per hour (0: unlimited).
        storage_quota_bytes: Stored submission ZIPs and anchor photos per account, in bytes (0: unlimited).
        zip_retention_days: Stored ZIPs of finished submissions are deleted after this many days; their results
            stay (0: kept for good).
        auth_failures_per_minute: Failed token checks per client address and minute before a 429
            (0: unlimited).
        operator_token: A bearer token that reads the monitoring endpoints (``/health/detail``, ``/metrics``)
            besides the admins' own (empty: admins only).
        heavy_threads: Localize and anchor computations running at once per API process (0: min(4, CPUs)).
        heavy_queue: Heavy requests waiting for one of those threads; past that a 429 with ``Retry-After``.
        method_threads: Threads of one heavy computation (OpenCV, torch, BLAS, OpenMP), set on each heavy
            thread whatever the environment says (0: the CPUs divided among the heavy threads, at least 1).
        anchor_cache_mb: Prepared anchors kept per API process (features and depth, no pixels), in MiB.
        method_pool_mb: Built relocalizers (their models) kept per API process, shared by equal
            configurations, in MiB.
        body_timeout: Seconds to wait for the next piece of a request body before a 408 (0: no limit).
        body_total_timeout: Seconds for a whole request body before a 408 (0: no limit).
        limits: What one request may send (``Limits``).
    """

    db_url: str = "sqlite:///mapfree.db"
    data_root: Path | None = None
    gt_root: Path | None = None
    splits: tuple[str, ...] = ("val", "test")
    test_daily_limit: int = 5
    lease_seconds: float = 60.0
    max_attempts: int = 3
    poll_seconds: float = 0.5
    default_method: str = ""
    secure_cookies: bool = False
    session_hours: float = 12.0
    methods_dir: Path | None = None
    val_hourly_limit: int = 30
    storage_quota_bytes: int = 1 << 30
    zip_retention_days: float = 90.0
    auth_failures_per_minute: int = 20
    operator_token: str = ""
    heavy_threads: int = 0
    heavy_queue: int = 8
    method_threads: int = 0
    anchor_cache_mb: float = 256.0
    method_pool_mb: float = 1024.0
    body_timeout: float = 30.0
    body_total_timeout: float = 600.0
    limits: Limits = field(default_factory=Limits)

    def __post_init__(self) -> None:
        self.data_root = Path(self.data_root) if self.data_root else None
        self.gt_root = Path(self.gt_root) if self.gt_root else None
        self.methods_dir = Path(self.methods_dir) if self.methods_dir else None
