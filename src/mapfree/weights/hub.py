"""The network (is a download host reachable), the Hugging Face cache, and transformers model folders."""

from __future__ import annotations

import os
import socket
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import urlparse

from .integrity import HUB_WEIGHT_FILES
from .paths import OFFLINE_ENV, Found, MissingWeightsError, find_in_dirs, missing_message, target_dir


def reachable(url: str, timeout: float = 3.0) -> bool:
    """Whether a download host answers, so that an offline machine fails in seconds instead of retrying.

    Args:
        url: The address; its host is tried on port 443.
        timeout: Seconds to wait for the connection.

    Returns:
        True when it answers; False at once when ``$MAPFREE_OFFLINE`` or ``$HF_HUB_OFFLINE`` is set.
    """
    host = urlparse(url).hostname
    if not host or os.environ.get(OFFLINE_ENV) or os.environ.get("HF_HUB_OFFLINE"):
        return False
    try:
        with socket.create_connection((host, 443), timeout=timeout):
            return True
    except OSError:
        return False


def offline_why(url: str) -> str:
    """Why nothing will be downloaded, for a missing-weights message.

    Args:
        url: The address that was not fetched.

    Returns:
        The variable that says so, or ``offline: HOST unreachable``.
    """
    flag = next((v for v in (OFFLINE_ENV, "HF_HUB_OFFLINE") if os.environ.get(v)), None)
    return f"${flag} is set" if flag else f"offline: {urlparse(url).hostname} unreachable"


def in_hf_cache(repo_id: str) -> bool:
    """Whether the Hugging Face cache holds a model (its config.json), without any network access.

    Args:
        repo_id: Hub id, ``org/name``.

    Returns:
        True when cached.
    """
    return hf_cache_folder(repo_id) is not None


def hf_cache_folder(repo_id: str) -> Path | None:
    """The snapshot folder of a model in the Hugging Face cache.

    Args:
        repo_id: Hub id, ``org/name``.

    Returns:
        The folder holding its config.json, or None.
    """
    try:
        from huggingface_hub import try_to_load_from_cache
    except ImportError:  # pragma: no cover - transformers depends on huggingface_hub
        return None
    hit = try_to_load_from_cache(repo_id, "config.json")
    return Path(hit).parent if isinstance(hit, str) else None


@dataclass(frozen=True)
class HubModel:
    """A transformers model on the Hugging Face hub and where the weights rule finds it (a ``Model``).

    Kept as a folder (``config.json`` + ``model.safetensors``) named like the last part of its id.

    Attributes:
        repo_id: Hub id, ``org/name``.
        what: What it is for, in words (the start of every message about it).
        licence: The weights' licence, named in messages.
    """

    repo_id: str
    what: str
    licence: str = ""

    @property
    def folder(self) -> str:
        """The folder name looked for in the weights folders."""
        return self.repo_id.rsplit("/", 1)[-1]

    @property
    def name(self) -> str:
        """Same as ``folder``."""
        return self.folder

    @property
    def url(self) -> str:
        """The model's page on the hub."""
        return f"https://huggingface.co/{self.repo_id}"

    def item(self) -> str:
        """``model 'ORG/NAME'``."""
        return f"model '{self.repo_id}'"

    def locate(self, explicit: str | os.PathLike | None = None) -> Found | None:
        """Find the model's folder by the rule, the Hugging Face cache last.

        A folder that is there but incomplete counts as found: loading it says what is wrong with it
        (``check_folder``).

        Args:
            explicit: A folder the user gave: then only there.

        Returns:
            Where it was found, or None.
        """
        if explicit is not None:
            p = Path(explicit).expanduser()
            return Found(p, "the path given") if p.is_dir() else None
        hit = find_in_dirs(self.folder, self.repo_id.replace("/", "--"))
        if hit is not None and hit[0].is_dir():
            return Found(*hit)
        snap = hf_cache_folder(self.repo_id)
        return Found(snap, "the Hugging Face cache") if snap is not None else None

    def how(self) -> str:
        """Download it with ``fetch_command`` on a machine with internet and copy the folder here."""
        lic = f"; licence: {self.licence}" if self.licence else ""
        return (
            f"On a machine with internet run `{self.fetch_command()}` and copy that folder here (published at "
            f"{self.url}{lic})"
        )

    def fetch_command(self) -> str:
        """``hf download ORG/NAME --local-dir WEIGHTS/NAME``."""
        return f"hf download {self.repo_id} --local-dir {target_dir() / self.folder}"

    def missing(self, why: str = "", explicit: str | os.PathLike | None = None) -> MissingWeightsError:
        """The error for a model not found (see ``Model.missing``)."""
        if explicit is not None:
            return MissingWeightsError(f"{self.what}: {self.item()} not found at the folder given ({explicit})")
        return MissingWeightsError(
            missing_message(self.what, self.item(), self.folder, self.how(), why, ("the Hugging Face cache",))
        )


def iter_weight_files(found: Found) -> Iterator[Path]:
    """The weight files of a found model: the file itself, or a folder's weight files."""
    if found.path.is_file():
        yield found.path
    else:
        for w in HUB_WEIGHT_FILES:
            if (found.path / w).is_file():
                yield found.path / w
