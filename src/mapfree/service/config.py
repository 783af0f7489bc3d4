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
    """Hostile-input limits. Sizes in bytes."""

    max_request_bytes: int = 64 << 20  # whole HTTP body
    max_submission_bytes: int = 50 << 20  # compressed ZIP
    max_zip_entries: int = 2000
    max_zip_entry_bytes: int = 64 << 20  # one pose file, uncompressed
    max_zip_uncompressed_bytes: int = 256 << 20  # all pose files together, uncompressed
    max_zip_ratio: float = 200.0  # per entry, uncompressed / compressed (zip bombs)
    max_image_bytes: int = 16 << 20
    max_image_pixels: int = 4096 * 4096
    max_name_chars: int = 120
    max_anchor_photos: int = 16  # photos of one anchor's place, the first included
    # decoded photos are downscaled to this long side at once (0: never); the benchmark's photos are 540x720,
    # every method is tuned at about that size
    work_max_side: int = 1024


@dataclass
class Settings:
    """Everything the app and its workers need. ``data_root`` holds the public splits; ``gt_root`` the private
    test ground truth (``gt_root/test/sNNNNN/poses.txt``), read only by workers, never served."""

    db_url: str = "sqlite:///mapfree.db"
    data_root: Path | None = None
    gt_root: Path | None = None
    splits: tuple[str, ...] = ("val", "test")
    test_daily_limit: int = 5  # per account and 24 h; 0: no test evaluations, UNLIMITED (-1): no limit
    lease_seconds: float = 60.0
    max_attempts: int = 3
    poll_seconds: float = 0.5
    default_method: str = ""  # empty: the registry's best offline feature-matching preset
    secure_cookies: bool = False
    session_hours: float = 12.0
    methods_dir: Path | None = None  # the operator's method YAMLs, offered to clients by name
    val_hourly_limit: int = 30  # val submissions per account per hour (0: unlimited)
    storage_quota_bytes: int = 1 << 30  # stored submission ZIPs and anchor photos per account (0: unlimited)
    zip_retention_days: float = 90.0  # stored ZIPs of finished submissions are deleted after this (0: kept)
    auth_failures_per_minute: int = 20  # failed token checks per client address before a 429 (0: unlimited)
    operator_token: str = ""  # bearer token of monitoring (/health/detail, /metrics) besides admins' own
    heavy_threads: int = 0  # localize / anchor computations at once per API process (0: min(4, CPUs))
    heavy_queue: int = 8  # heavy requests waiting for one of those threads; past that a 429 with Retry-After
    anchor_cache_mb: float = 256.0  # prepared anchors kept per API process (features and depth, no pixels)
    method_pool_mb: float = 1024.0  # built relocalizers (models) kept per API process, shared by equal configs
    body_timeout: float = 30.0  # seconds for the next piece of a request body before a 408 (0: no limit)
    body_total_timeout: float = 600.0  # seconds for a whole request body before a 408 (0: no limit)
    limits: Limits = field(default_factory=Limits)

    def __post_init__(self) -> None:
        self.data_root = Path(self.data_root) if self.data_root else None
        self.gt_root = Path(self.gt_root) if self.gt_root else None
        self.methods_dir = Path(self.methods_dir) if self.methods_dir else None
