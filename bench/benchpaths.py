"""What the bench scripts share: ``src/`` on the path (``mapfree_dev`` lives in the checkout, not the wheel) and
the default real-image split, ``realmini-dev`` in the ``shared/`` folder beside the checkout (None when absent)."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

_CANDIDATES = (Path(__file__).resolve().parents[2] / "shared/data/realmini-dev", Path("/work/shared/data/realmini-dev"))
DEFAULT_ROOT: Path | None = next((p for p in _CANDIDATES if p.is_dir()), None)
